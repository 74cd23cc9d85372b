"""Where a model's outlines are wrong: its alpha against the ground truth's on the test pixels an
outline crosses (0.02 < alpha < 0.98 in the ground truth), and how much of that error one image
shift and zoom per view would explain (a camera that disagrees with Mitsuba's film would show as
one). docs/results.md, "Quality past 600 s":

    python docs/benchmarks/outline_error.py DATASET RUN/renders/test OUT.png [VIEWS, default 0,2]

Prints the partial pixels' alpha error (mean, RMS, by ground-truth alpha) and the shift's share;
OUT.png shows, per view, the ground truth on white, the alpha error (red: the model too opaque,
blue: too transparent, |error| > 0.03) and the colour error on white (green > 0.05, black > 0.15)."""
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from nerfgauge.eval.metrics import composite


def on_white(rgba):
    return composite(rgba, (1.0, 1.0, 1.0))


def shift_share(gt_alpha, error):
    """Squared alpha error left after the least-squares image shift (dx, dy) and zoom of one
    view, linearised as error = -(grad a) . displacement; returns (error^2, residual^2) sums."""
    gy, gx = np.gradient(gt_alpha)
    h, w = gt_alpha.shape
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    m = (np.abs(gx) + np.abs(gy)) > 0.02
    design = np.stack([-gx[m], -gy[m], -(gx[m] * (xx[m] - w / 2) + gy[m] * (yy[m] - h / 2))], 1)
    solution, *_ = np.linalg.lstsq(design, error[m], rcond=None)
    return float((error[m] ** 2).sum()), float(((error[m] - design @ solution) ** 2).sum())


def main(dataset: Path, renders: Path, out: str, views: list) -> None:
    frames = sorted(p.stem for p in (dataset / "test").glob("r_???.png"))
    errors, truths, tiles, before, after = [], [], [], 0.0, 0.0
    for number, frame in enumerate(frames):
        gt = np.asarray(Image.open(dataset / "test" / f"{frame}.png"), dtype=np.float64) / 255
        pred = np.asarray(Image.open(renders / f"{frame}.png"), dtype=np.float64) / 255
        error = pred[..., 3] - gt[..., 3]
        partial = (gt[..., 3] > 0.02) & (gt[..., 3] < 0.98)
        errors.append(error[partial]), truths.append(gt[..., 3][partial])
        total, left = shift_share(gt[..., 3], error)
        before, after = before + total, after + left
        if number in views:
            faded = 0.3 * on_white(gt).mean(-1, keepdims=True).repeat(3, -1) + 0.7
            alpha_map, colour_map = faded.copy(), faded.copy()
            alpha_map[error > 0.03], alpha_map[error < -0.03] = [1, 0, 0], [0, 0, 1]
            colour = np.abs(on_white(pred) - on_white(gt)).max(-1)
            colour_map[colour > 0.05], colour_map[colour > 0.15] = [0, 0.6, 0], [0, 0, 0]
            tiles.append(np.concatenate([on_white(gt), alpha_map, colour_map], 1))
    error, truth = np.concatenate(errors), np.concatenate(truths)
    print(f"{error.size} outline pixels in {len(frames)} views: alpha error mean {error.mean():+.4f}, "
          f"RMS {np.sqrt((error ** 2).mean()):.4f}; one shift and zoom per view explains "
          f"{1 - after / before:.0%} of the squared alpha error on the pixels an edge crosses")
    for low, high in ((0.02, 0.25), (0.25, 0.5), (0.5, 0.75), (0.75, 0.98)):
        part = (truth >= low) & (truth < high)
        print(f"  ground-truth alpha {low:.2f}-{high:.2f}: {part.sum()} pixels, mean {error[part].mean():+.4f}, "
              f"RMS {np.sqrt((error[part] ** 2).mean()):.4f}")
    image = np.clip(np.concatenate(tiles, 0), 0, 1)
    Image.fromarray((image * 255).astype(np.uint8)).resize((image.shape[1] * 3, image.shape[0] * 3),
                                                          Image.NEAREST).save(out)


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3],
         [int(v) for v in sys.argv[4].split(",")] if len(sys.argv) > 4 else [0, 2])
