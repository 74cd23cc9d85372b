"""The home of "a method": the interface every method the harness runs goes through
(`interface`), the methods nerfgauge ships (`builtin`), finding one by name, `module:Class`
or spec file (`registry`), and `nerfgauge methods` (`commands`).

This package sits on top of the stages (nerf, eval): it imports them inside the functions
that train or render, so importing it stays light."""

from nerfgauge.methods.interface import Method, Needs, Produces, RenderResult, TrainRequest, TrainResult

__all__ = ["Method", "Needs", "Produces", "RenderResult", "TrainRequest", "TrainResult"]
