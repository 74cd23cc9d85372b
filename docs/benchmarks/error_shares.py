"""Where a model's squared error sits: by object (the scene's instances) and by pixel class
(outline: partial ground-truth coverage; edge: the other pixels whose box filter differs from
the centre ray's value; interior: the rest), each cell's share of the total squared error of
premultiplied sRGB and its RMS. docs/results.md, "Where the error sits".

The ground truth carries the renderer's noise, so part of any model's error is not the
model's. A second draw of the same views with other sampler seeds measures it: two draws
differ by twice one draw's noise variance, so a cell's excess over the noise is the model's
mean squared error minus half the two draws'.

    python docs/benchmarks/error_shares.py draw DATASET OUT      # a copy of DATASET whose test
                                                                 # views are drawn again
    python docs/benchmarks/error_shares.py shares DATASET PRED_DIR [OUT/test]

PRED_DIR: a folder of predicted test PNGs (`nerfgauge render RUN --split test` writes them
under OUT/test). A pixel on an outline belongs to the instance seen in its 3 x 3 neighbourhood
(the pixel-centre ray may miss); pixels near two instances are counted apart.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from nerfgauge.eval.metrics import edge_pixels, outline_pixels

# Added to every view's sampler seed for the second draw: poses, scene and spp stay.
SECOND_DRAW_SEED_OFFSET = 987_654
CLASSES = ("outline", "edge", "interior")


def draw(dataset: Path, out: Path) -> None:
    """Copy `dataset` to `out` and render its test views again with shifted sampler seeds
    (the generator resumes a dataset with views missing). The command repeats the recipe's
    scene, size, view counts, spp and seed; a dataset made with other flags (layout, fov,
    noise, degradations) is refused by the generator as another recipe."""
    import nerfgauge.generate.views as views
    from nerfgauge.cli import main

    if out.exists():
        sys.exit(f"{out} exists")
    shutil.copytree(dataset, out)
    for path in (out / "test").glob("r_*"):
        path.unlink()
    recipe = json.loads((dataset / "config.json").read_text())["config"]
    original = views.view_seed
    views.view_seed = lambda seed, split, index: (original(seed, split, index) + SECOND_DRAW_SEED_OFFSET) % 2 ** 32
    sys.argv = ["nerfgauge", "generate", recipe["scene"], "--out", str(out), "--res", f"{recipe['width']}x{recipe['height']}",
                "--views", str(recipe["views"]), "--val-views", str(recipe["val_views"]),
                "--test-views", str(recipe["test_views"]), "--spp", str(recipe["spp"]), "--seed", str(recipe["seed"])]
    main()


def neighbourhood(ids: np.ndarray) -> np.ndarray:
    """[9, H, W]: the instance ids [H, W] of each pixel's 3 x 3 neighbourhood (0 past the image)."""
    padded = np.pad(ids, 1)
    return np.stack([padded[1 + dy:1 + dy + ids.shape[0], 1 + dx:1 + dx + ids.shape[1]]
                     for dy in (-1, 0, 1) for dx in (-1, 0, 1)])


def cells(dataset: Path, predictions: Path) -> tuple[dict, int]:
    """{(instance name, class): [sum of squared error, pixels]} over the test views, and the
    number of pixels (every channel of premultiplied sRGB weighs a third of a pixel)."""
    names = ["background"] + json.loads((dataset / "scene.json").read_text())["instances"]["names"]
    table, pixels = {}, 0
    for truth_path in sorted((dataset / "test").glob("r_???.png")):
        truth = np.asarray(Image.open(truth_path), dtype=np.float64) / 255
        pred = np.asarray(Image.open(predictions / truth_path.name), dtype=np.float64) / 255
        ids = np.asarray(Image.open(truth_path.with_name(truth_path.stem + "_instance.png"))).astype(np.int64)
        around = neighbourhood(ids)
        nearest = around.max(0)
        lowest = np.where(around > 0, around, np.iinfo(np.int64).max).min(0)
        two = (nearest > 0) & (lowest != nearest)
        outline = outline_pixels(truth)
        edge = edge_pixels(truth, ids) & ~outline
        masks = {"outline": outline, "edge": edge, "interior": ~outline & ~edge}
        squared = ((pred[..., :3] * pred[..., 3:] - truth[..., :3] * truth[..., 3:]) ** 2).mean(-1)  # [H, W]
        pixels += squared.size
        for kind, mask in masks.items():
            for index, name in enumerate(names):
                chosen = mask & (nearest == index) & ~two
                cell = table.setdefault((name, kind), [0.0, 0])
                cell[0] += float(squared[chosen].sum())
                cell[1] += int(chosen.sum())
            cell = table.setdefault(("two instances", kind), [0.0, 0])
            cell[0] += float(squared[mask & two].sum())
            cell[1] += int((mask & two).sum())
    return table, pixels


def shares(dataset: Path, predictions: Path, second_draw: Path | None) -> None:
    table, pixels = cells(dataset, predictions)
    total = sum(value for value, _ in table.values())
    noise = cells(dataset, second_draw)[0] if second_draw is not None else None
    print(f"{predictions}: PSNR {10 * np.log10(pixels / total):.2f} dB over the test views")
    header = "| object | class | pixels | share of squared error | RMS |"
    if noise is not None:
        noise_total = sum(value for value, _ in noise.values()) / 2
        excess_total = total - noise_total
        print(f"one draw's noise: PSNR {10 * np.log10(pixels / noise_total):.2f} dB; the model's excess "
              f"over it: {10 * np.log10(pixels / excess_total):.2f} dB")
        header += " one draw's noise RMS | share of the excess |"
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    for (name, kind), (value, count) in sorted(table.items(), key=lambda item: -item[1][0]):
        if count == 0 or value < 0.005 * total:
            continue
        row = f"| {name} | {kind} | {count} | {value / total:.3f} | {np.sqrt(value / count):.4f} |"
        if noise is not None:
            half = noise[(name, kind)][0] / 2
            row += f" {np.sqrt(half / count):.4f} | {(value - half) / excess_total:.3f} |"
        print(row)


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "draw":
        draw(Path(sys.argv[2]), Path(sys.argv[3]))
    elif len(sys.argv) >= 4 and sys.argv[1] == "shares":
        reference = Path(sys.argv[4]) if len(sys.argv) > 4 else None
        shares(Path(sys.argv[2]), Path(sys.argv[3]), reference)
    else:
        sys.exit(__doc__)
