"""Camera layout defaults and the generator's options, shared by `generate` and `run`."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from nerfgauge.core.errors import InputError
from nerfgauge.generate.options import add_generate_arguments, generate_fields
from nerfgauge.generate.pipeline import DEFAULT_ELEVATION, GenerateConfig, layout_spec, plan
from nerfgauge.scenes import make_scene

from cli_errors import one_line_exit_2


def elevations(poses: dict) -> np.ndarray:
    """Degrees above the horizon of every camera's viewing direction (-Z of c2w)."""
    forward = -np.concatenate([p[:, :3, 2] for p in poses.values()])
    return np.degrees(np.arcsin(np.clip(forward[:, 2], -1, 1)))


def test_inside_layout_defaults_to_a_band_around_the_horizon():
    """A user mesh or recipe with --layout inside and no hint: views look at the walls."""
    config = GenerateConfig(scene="primitives", layout="inside", views=20, val_views=2, test_views=4)
    spec = layout_spec(config, make_scene("primitives", 0))
    assert spec.elevation == (-20.0, 20.0)
    angles = elevations(plan(config).poses)
    assert angles.min() >= -20 - 1e-6 and angles.max() <= 20 + 1e-6 and angles.min() < 0 < angles.max()


def test_a_scene_hint_and_the_command_line_still_win_over_the_inside_default():
    hinted = layout_spec(GenerateConfig(scene="inside"), make_scene("inside", 0))
    assert hinted.layout == "inside" and hinted.elevation == tuple(make_scene("inside", 0).cameras.elevation)
    given = layout_spec(GenerateConfig(scene="inside", elevation=(-15.0, 25.0)), make_scene("inside", 0))
    assert given.elevation == (-15.0, 25.0)
    orbit = layout_spec(GenerateConfig(scene="primitives", layout="hemisphere"), make_scene("primitives", 0))
    assert orbit.elevation == DEFAULT_ELEVATION


def parser():
    p = argparse.ArgumentParser(exit_on_error=False)
    p.add_argument("scene")
    return add_generate_arguments(p)


@pytest.mark.parametrize("argv, expected", [
    (["--elevation", "-15,25"], (-15.0, 25.0)),
    (["--elevation", "-30,-5"], (-30.0, -5.0)),
    (["--elevation=-15,25"], (-15.0, 25.0)),
    (["--elevation", "10,75"], (10.0, 75.0)),
])
def test_elevation_takes_negative_values_as_written(argv, expected):
    fields = generate_fields(parser().parse_args(["primitives", *argv]))
    assert fields["elevation"] == expected


@pytest.mark.parametrize("value", ["-15", "25,-15", "nan,3", "1,2,3", "a,b"])
def test_bad_elevations_are_refused_by_the_parser(value):
    with pytest.raises(argparse.ArgumentError):
        parser().parse_args(["primitives", "--elevation", value])


def test_spp_takes_auto_and_a_target():
    fields = generate_fields(parser().parse_args(["primitives", "--spp", "auto", "--noise-psnr", "35",
                                                  "--max-spp", "512", "--radius", "2", "--fov", "50"]))
    assert fields["spp"] == "auto" and fields["noise_psnr"] == 35.0 and fields["max_spp"] == 512
    assert GenerateConfig(scene="primitives", **fields).noise_target.noise_psnr == 35.0


@pytest.mark.parametrize("argv, message", [
    (["--spp", "auto"], "--spp auto needs --noise-psnr"),
    (["--spp", "auto", "--noise-psnr", "nan"], "finite"),
    (["--spp", "auto", "--noise-psnr", "81"], "argument --noise-psnr: expected a number above 0, up to 80, got '81'"),
    (["--spp", "1", "--noise-psnr", "30"], "--spp 1 renders one pass"),
    (["--elevation", "-15,25", "--fov", "-3"], "argument --fov: expected a number above 0, below 180, got '-3'"),
])
def test_run_refuses_bad_generator_options_in_one_line(tmp_path, capsys, argv, message):
    one_line_exit_2(capsys, ["run", "primitives", "--out", tmp_path / "out", "--steps", "1", *argv], message)
    assert not (tmp_path / "out").exists()


def test_run_passes_every_generator_option_to_the_dataset():
    from nerfgauge.run import RunConfig

    config = RunConfig(generate_options={"elevation": (-15.0, 25.0), "fov": 55.0, "radius": 3.0})
    generated = config.generate_config()
    assert (generated.elevation, generated.fov, generated.radius) == ((-15.0, 25.0), 55.0, 3.0)
    with pytest.raises(InputError, match="unknown generator option bogus"):
        RunConfig(generate_options={"bogus": 1}).generate_config()


def test_api_run_pipeline_takes_generator_options(tmp_path):
    import nerfgauge

    with pytest.raises(InputError, match="--fov must be in"):
        nerfgauge.run_pipeline("primitives", tmp_path / "out", fov=-3.0, elevation=(-15.0, 25.0), steps=1)
    with pytest.raises(InputError, match="unknown option"):
        nerfgauge.run_pipeline("primitives", tmp_path / "out", not_an_option=1)
