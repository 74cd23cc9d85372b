"""3D Gaussian splatting (Kerbl et al. 2023) on the CPU: EWA projection, spherical-harmonic
colour, a tiled rasteriser with a hand-written backward (numba), a brute-force oracle, the
model, its training loop and its renders in the layout `nerfgauge evaluate` reads."""
