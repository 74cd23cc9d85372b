"""Another tool's method for the suite tests (tests/test_suite_methods.py), run through a
method spec (nerfgauge.methods.external). It imports only what each mode needs, so a
command costs a Python start-up.

    fake_tool.py train RUN SEED              writes RUN/out/weights.txt
    fake_tool.py render DATASET SPLIT OUT SEED
                                             each frame of SPLIT: the ground truth's PNG with
                                             noise drawn from SEED (sd 6/255 on colour), as
                                             OUT/<split>/r_NNN.png: finite scores that differ by seed
    fake_tool.py fail                        exits with status 3
    fake_tool.py sleep                       sleeps a minute (a grandchild too)
    fake_tool.py nothing                     does nothing (its render writes no images)
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

NOISE = 6.0  # sd of the render's noise, in 8-bit levels


def frames(dataset: Path, split: str) -> list[str]:
    """The split's frame paths as transforms_<split>.json lists them (test/r_000)."""
    return [frame["file_path"] for frame in json.loads((dataset / f"transforms_{split}.json").read_text())["frames"]]


def render(dataset: Path, split: str, out: Path, seed: int) -> None:
    import numpy as np  # numpy, PIL: only where it renders
    from PIL import Image

    rng = np.random.default_rng(seed)
    for rel in frames(dataset, split):
        truth = np.asarray(Image.open(dataset / f"{rel}.png").convert("RGBA"), dtype=np.float64)
        noisy = truth.copy()
        noisy[..., :3] = np.clip(np.round(truth[..., :3] + rng.normal(0.0, NOISE, truth[..., :3].shape)), 0, 255)
        target = out / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(noisy.astype(np.uint8), "RGBA").save(target.with_suffix(".png"))


def main(argv: list[str]) -> int:
    mode = argv[0]
    if mode == "train":
        run, seed = Path(argv[1]), int(argv[2])
        (run / "out").mkdir(exist_ok=True)
        (run / "out" / "weights.txt").write_text(f"{seed}\n")
    elif mode == "render":
        render(Path(argv[1]), argv[2], Path(argv[3]), int(argv[4]))
    elif mode == "fail":
        print("fake_tool: failing on purpose", file=sys.stderr)
        return 3
    elif mode == "sleep":
        subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])  # a grandchild in its group
        time.sleep(60)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
