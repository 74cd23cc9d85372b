"""Mitsuba variant choice: one place, explicit overrides, a clear fallback note."""

import os

import pytest
from nerfgauge.generate import variant

from nerfgauge.core.errors import InputError


def test_auto_prefers_cuda_then_llvm_then_scalar(monkeypatch, capsys):
    monkeypatch.delenv(variant.ENVIRONMENT, raising=False)  # `tox -e scalar` sets it
    variant._note_once.cache_clear()
    monkeypatch.setattr(variant, "cuda_available", lambda: True)
    assert variant.resolve_variant("auto") == "cuda_ad_rgb"
    monkeypatch.setattr(variant, "cuda_available", lambda: False)
    monkeypatch.setattr(variant, "prepare_llvm_path", lambda: "/usr/lib/libLLVM-19.so")
    assert variant.resolve_variant("auto") == "llvm_ad_rgb"
    monkeypatch.setattr(variant, "prepare_llvm_path", lambda: None)
    assert variant.resolve_variant("auto") == "scalar_rgb"
    assert variant.resolve_variant("auto") == "scalar_rgb"
    notes = capsys.readouterr().err.strip().splitlines()
    assert len(notes) == 1 and "scalar_rgb" in notes[0] and "libllvm19" in notes[0]  # said once


def test_explicit_choices_and_bad_names(monkeypatch):
    monkeypatch.setattr(variant, "cuda_available", lambda: False)
    monkeypatch.setattr(variant, "prepare_llvm_path", lambda: None)
    assert variant.resolve_variant("scalar") == "scalar_rgb"
    with pytest.raises(InputError, match="libllvm19"):
        variant.resolve_variant("llvm")
    with pytest.raises(InputError, match="GPU"):
        variant.resolve_variant("cuda")
    with pytest.raises(InputError, match="unknown variant 'metal'"):
        variant.resolve_variant("metal")


def test_old_llvm_is_never_picked(monkeypatch):
    found = ["/usr/lib/x86_64-linux-gnu/libLLVM-14.so.1", "/usr/lib/x86_64-linux-gnu/libLLVM-15.so",
             "/usr/lib/x86_64-linux-gnu/libLLVM-19.so", "/usr/lib/llvm-18/lib/libLLVM.so.1"]
    monkeypatch.setattr(variant.glob, "glob", lambda pattern: [p for p in found if p.startswith(pattern.split("*")[0])])
    assert variant.find_libllvm() == "/usr/lib/x86_64-linux-gnu/libLLVM-19.so"
    monkeypatch.setattr(variant.glob, "glob", lambda pattern: [p for p in found[:2] if p.startswith(pattern.split("*")[0])])
    assert variant.find_libllvm() is None


def test_environment_variable_decides_auto(monkeypatch, capsys):
    variant._note_once.cache_clear()
    monkeypatch.setattr(variant, "cuda_available", lambda: False)
    monkeypatch.setattr(variant, "prepare_llvm_path", lambda: "/usr/lib/libLLVM-19.so")  # libLLVM present
    monkeypatch.setenv(variant.ENVIRONMENT, "scalar")
    assert variant.resolve_variant("auto") == "scalar_rgb"
    assert variant.resolve_variant("llvm") == "llvm_ad_rgb"  # an explicit choice wins over the variable
    assert capsys.readouterr().err == ""  # asked for scalar: no "libLLVM not found" note
    monkeypatch.setenv(variant.ENVIRONMENT, "")
    assert variant.resolve_variant("auto") == "llvm_ad_rgb"  # empty = unset
    monkeypatch.setenv(variant.ENVIRONMENT, "auto")
    assert variant.resolve_variant("auto") == "llvm_ad_rgb"
    monkeypatch.setenv(variant.ENVIRONMENT, "llvm")
    monkeypatch.setattr(variant, "prepare_llvm_path", lambda: None)  # libLLVM absent
    with pytest.raises(InputError, match=r"^NERFGAUGE_MITSUBA_VARIANT=llvm needs libLLVM >= 17 .*libllvm19"):
        variant.resolve_variant("auto")
    monkeypatch.setenv(variant.ENVIRONMENT, "cuda")
    with pytest.raises(InputError, match="^NERFGAUGE_MITSUBA_VARIANT=cuda needs a CUDA driver"):
        variant.resolve_variant("auto")


def test_bad_environment_value_is_one_line_error(monkeypatch):
    monkeypatch.setenv(variant.ENVIRONMENT, "LLVM_ad_rgb")
    with pytest.raises(InputError) as caught:
        variant.resolve_variant("auto")
    message = str(caught.value)
    assert "\n" not in message and "NERFGAUGE_MITSUBA_VARIANT='LLVM_ad_rgb'" in message
    assert "auto, cuda, llvm, scalar" in message
    assert variant.resolve_variant("scalar") == "scalar_rgb"  # not consulted for explicit choices


def test_cli_reports_bad_environment_value_with_exit_2(tmp_path, monkeypatch, capsys):
    from nerfgauge.cli import main

    monkeypatch.setenv(variant.ENVIRONMENT, "fast")
    code = main(["generate", "primitives", "--out", str(tmp_path / "d"), "--views", "1", "--res", "8"])
    assert code == 2
    assert capsys.readouterr().err.strip() == ("nerfgauge generate: error: NERFGAUGE_MITSUBA_VARIANT='fast' is not "
                                               "a variant; choose one of auto, cuda, llvm, scalar")
    assert not (tmp_path / "d").exists()  # refused before anything was written


def test_session_variant_follows_the_environment(mi):
    """What `tox -e scalar` relies on: with the variable set, every Mitsuba test runs on it."""
    wanted = os.environ.get(variant.ENVIRONMENT, "").strip()
    if wanted in ("", "auto"):
        assert mi.variant() == variant.resolve_variant("auto")
    else:
        assert mi.variant() == variant.VARIANTS[wanted]
