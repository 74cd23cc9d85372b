"""nerfgauge: ground-truth NeRF datasets with Mitsuba 3, a compact NeRF, and an evaluation harness.

The library API (see README, "Python API"):

    generate_dataset(scene, out, **options) -> Path           render a dataset
    train(dataset, out, **options) -> dict                    train a NeRF; its summary
    render(run_dir, split="test") -> Path                     render a split with the trained model
    evaluate(dataset, pred, out=None, split="test") -> dict   the metrics document
    check(metrics, thresholds) -> list[CheckResult]           the CI gate
    run_pipeline(scene, out, **options) -> dict               the whole pipeline, as `nerfgauge run`
    Dataset(root)                     read a dataset: frames, cameras, images, depth, normals, masks
    InputError, NumericalError        bad input (CLI exit 2), NaN/inf where numbers must be finite (exit 3)

Names are imported on first use (module __getattr__), so `import nerfgauge` and
`import nerfgauge.core` load neither torch nor mitsuba and have no side effects.
"""

from __future__ import annotations

import importlib

# public name -> module that defines it
_EXPORTS = {
    "generate_dataset": "nerfgauge.api",
    "train": "nerfgauge.api",
    "render": "nerfgauge.api",
    "evaluate": "nerfgauge.api",
    "check": "nerfgauge.api",
    "run_pipeline": "nerfgauge.api",
    "Dataset": "nerfgauge.core.dataset",
    "InputError": "nerfgauge.core.errors",
    "NumericalError": "nerfgauge.core.errors",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'nerfgauge' has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)


def __dir__():
    return sorted(set(globals()) | set(__all__))
