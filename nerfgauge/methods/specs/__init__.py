"""The method specs nerfgauge ships (package data): other tools' methods, each named by its
file name like a built-in method (`nerfgauge methods` lists them with their install lines;
nerfgauge.methods.external reads them). gsplat_render.py is not part of nerfgauge: the gsplat
spec runs it with the gsplat environment's own interpreter."""
