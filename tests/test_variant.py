"""Mitsuba variant choice: one place, explicit overrides, a clear fallback note."""

import pytest
from nerfgauge.generate import variant

from nerfgauge.core.errors import InputError


def test_auto_prefers_cuda_then_llvm_then_scalar(monkeypatch, capsys):
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
