"""Shared fixtures: the Mitsuba variant (set once, like Mitsuba's own test fixtures) and
small generated datasets, made once per session and shared read-only."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def mi():
    """Mitsuba with the variant `auto` resolves to on this machine (llvm_ad_rgb here)."""
    from nerfgauge.generate.variant import resolve_variant, use_variant

    return use_variant(resolve_variant("auto"))


def generate_small(out, scene="primitives", **overrides):
    """Generate a tiny dataset in-process; returns its folder."""
    from nerfgauge.generate.pipeline import GenerateConfig, generate

    settings = dict(scene=scene, views=4, val_views=1, test_views=2, width=32, height=32, spp=4)
    settings.update(overrides)
    generate(GenerateConfig(**settings), out, progress=False)
    return out


@pytest.fixture(scope="session")
def make_dataset():
    """The in-process generator with tiny defaults: make_dataset(out, scene=..., **config)."""
    return generate_small


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """primitives, 4/1/2 views at 32x32, 4 spp: enough for format and depth checks."""
    return generate_small(tmp_path_factory.mktemp("datasets") / "primitives")
