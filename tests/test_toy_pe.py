"""The 2D memorisation experiment of positional encoding (Tancik et al. 2020), its
command, and the positional encoding."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from nerfgauge.nerf.encoding import (
    PositionalEncoding,
    encoded_size,
    positional_encoding,
)
from nerfgauge.nerf.toy_pe import ToyPEConfig, make_image, run_toy_pe

from nerfgauge.cli import main


@pytest.fixture
def one_thread():
    """The fits multiply [4096, 64] matrices: one thread is about as fast as two on an idle
    machine and many times faster when another job holds the cores (OpenMP threads
    oversubscribed on 2 cores measured 25x slower). Restored afterwards."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


def test_positional_encoding_values_and_size():
    p = torch.tensor([[0.25, -0.5]], dtype=torch.float64)
    gamma = positional_encoding(p, 2)
    assert gamma.shape == (1, encoded_size(2, 2)) == (1, 10)
    # Layout [p, sin(pi p), cos(pi p), sin(2 pi p), cos(2 pi p)], each over both coordinates.
    expected = [0.25, -0.5,
                math.sin(math.pi / 4), math.sin(-math.pi / 2), math.cos(math.pi / 4), math.cos(-math.pi / 2),
                math.sin(math.pi / 2), math.sin(-math.pi), math.cos(math.pi / 2), math.cos(-math.pi)]
    torch.testing.assert_close(gamma[0], torch.tensor(expected, dtype=torch.float64), rtol=0, atol=1e-15)
    assert positional_encoding(p, 2, include_input=False).shape == (1, 8)


def test_positional_encoding_sizes_of_the_vanilla_nerf():
    assert PositionalEncoding(3, 10).out_dim == 63 and PositionalEncoding(3, 4).out_dim == 27
    x = torch.rand(5, 7, 3, generator=torch.Generator().manual_seed(0))
    assert PositionalEncoding(3, 10)(x).shape == (5, 7, 63)
    with pytest.raises(ValueError, match=r"expected \[..., 3\] input, got shape \(5, 2\)"):
        PositionalEncoding(3, 4)(torch.zeros(5, 2))


def test_image_is_seeded_and_high_frequency():
    a, b = make_image(64, np.random.default_rng(0)), make_image(64, np.random.default_rng(0))
    assert np.array_equal(a, b) and not np.array_equal(a, make_image(64, np.random.default_rng(1)))
    assert a.shape == (64, 64, 3) and a.dtype == np.float32 and 0 < a.min() and a.max() < 1
    # High frequency: neighbouring pixels differ much more than a smooth ramp's 1/64.
    assert np.abs(np.diff(a, axis=1)).mean() > 0.05


def test_positional_encoding_wins_by_at_least_5_db(one_thread):
    # The experiment shows a plain MLP learning only a blurred image while the
    # encoded one reproduces the stripes. Here the gap measures 10.5-12 dB over seeds 0-2
    # (about 12.8 dB vs 24 dB); 5 dB is half of that, so slower convergence on another
    # CPU or BLAS does not flip the test, while a broken encoding (no gap: both fits ~13 dB)
    # or a mis-wired experiment does.
    result = run_toy_pe(ToyPEConfig(seed=0))
    assert result.gap >= 5.0, (result.psnr_no_pe, result.psnr_pe)
    assert result.psnr_pe > 20.0


def test_runs_are_reproducible_without_global_seeds(one_thread):
    config = ToyPEConfig(steps=5, seed=3, size=16)
    first, second = run_toy_pe(config), run_toy_pe(config)
    assert first.psnr_pe == second.psnr_pe and first.psnr_no_pe == second.psnr_no_pe
    assert np.array_equal(first.fit_pe, second.fit_pe)


def test_config_rejects_bad_values():
    for bad in ({"steps": 0}, {"seed": -1}, {"size": 4}, {"learning_rate": 0.0}, {"steps": 1.5}):
        with pytest.raises(ValueError):
            ToyPEConfig(**bad)


def test_command_writes_png_and_json(tmp_path, capsys, one_thread):
    out = tmp_path / "pe"
    assert main(["toy-pe", "--out", str(out), "--steps", "3", "--seed", "1"]) == 0
    printed = capsys.readouterr().out
    assert "PSNR without positional encoding" in printed and "gap:" in printed
    assert sorted(p.name for p in out.iterdir()) == ["toy_pe.json", "toy_pe.png"]  # no temporaries left
    summary = json.loads((out / "toy_pe.json").read_text())
    assert summary["config"]["steps"] == 3 and summary["config"]["seed"] == 1
    assert summary["gap_db"] == pytest.approx(summary["psnr_pe"] - summary["psnr_no_pe"])
    from PIL import Image
    with Image.open(out / "toy_pe.png") as image:
        assert image.size == (3 * 64 * 4 + 2 * 4, 64 * 4) and image.mode == "RGB"


@pytest.mark.parametrize("argv, message", [
    (["--steps", "0"], "argument --steps: expected an integer from 1 to 1000000, got '0'"),
    (["--seed", "-2"], "argument --seed: expected an integer from 0 to 2147483647, got '-2'"),
])
def test_command_rejects_bad_input(argv, message, capsys):
    assert main(["toy-pe", *argv]) == 2
    assert message in capsys.readouterr().err


def test_command_rejects_a_file_as_out_directory(tmp_path, capsys):
    file = tmp_path / "file.png"
    file.write_bytes(b"")
    assert main(["toy-pe", "--out", str(file), "--steps", "1"]) == 2
    assert "--out must be a directory" in capsys.readouterr().err
