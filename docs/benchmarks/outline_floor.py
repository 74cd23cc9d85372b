"""How well can a render through a fixed pattern of points in a pixel reproduce the box
coverage of a straight edge, when each point's ray returns a learned profile f(d) of its
signed distance d to the edge (the skin a model grows in front of a surface, with surface
opacity the same for every ray that passes at the same distance)?

Random straight edges through a unit pixel (angle uniform, offset uniform where the edge
crosses the pixel); true coverage by 128 x 128 midpoint supersampling; predicted coverage
the mean over the points of f(d_i), f piecewise linear on 33 knots over [-0.8, 0.8] px
(0 below, 1 above), fitted by least squares. Prints, per pattern, the alpha RMS of the best
profile and of a sharp edge (f a step): docs/results.md, "The outline's floor".

One skin in 3D is seen by cameras at different distances, so its width in pixels differs
between views: the second table fits one profile for views whose pixel spans s world units,
s uniform in [1, spread] (f in units of the mean pixel), and prints its RMS per spread
(the primitives' cameras see content 3.4-4.9 units away: a spread of 1.45).

    python docs/benchmarks/outline_floor.py
"""

from __future__ import annotations

import numpy as np

LINES = 20000
KNOTS = np.linspace(-0.8, 0.8, 33)


def random_edges(rng: np.random.Generator):
    """(normals [N, 2], offsets [N], coverage [N]) of edges n.x = c crossing the pixel,
    coverage the share of the pixel with n.x < c, strictly between 0.001 and 0.999."""
    theta = rng.uniform(0, np.pi, LINES)
    normals = np.stack([np.cos(theta), np.sin(theta)], 1)
    offsets = rng.uniform(-0.75, 0.75, LINES)
    centres = (np.arange(128) + 0.5) / 128 - 0.5
    x, y = np.meshgrid(centres, centres)
    fine = np.stack([x.ravel(), y.ravel()], 1)  # [F, 2]
    coverage = np.concatenate([((fine @ normals[i:i + 500].T) < offsets[i:i + 500]).mean(0)
                               for i in range(0, LINES, 500)])
    keep = (coverage > 0.001) & (coverage < 0.999)
    return normals[keep], offsets[keep], coverage[keep]


def profile_basis(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hat functions on KNOTS at the distances d [...]: ([..., K], above [...]); f(d) =
    basis @ values + above (f is 1 past the last knot, 0 before the first)."""
    width = KNOTS[1] - KNOTS[0]
    index = np.clip(np.searchsorted(KNOTS, d) - 1, 0, len(KNOTS) - 2)
    t = np.clip((d - KNOTS[index]) / width, 0, 1)
    basis = np.zeros(d.shape + (len(KNOTS),))
    np.put_along_axis(basis, index[..., None], (1 - t)[..., None], -1)
    upper = np.zeros_like(basis)
    np.put_along_axis(upper, (index + 1)[..., None], t[..., None], -1)
    basis += upper
    outside = (d < KNOTS[0]) | (d > KNOTS[-1])
    basis[outside] = 0
    return basis, (d > KNOTS[-1]).astype(float)


def floor(points: np.ndarray, edges, scales: np.ndarray | None = None) -> tuple[float, float]:
    """(best profile's RMS, sharp edge's RMS) of the equal-weight mean over `points` [S, 2].
    scales [N]: each edge's view's pixel in units of the profile's (None: all 1)."""
    normals, offsets, coverage = edges
    d = offsets[:, None] - normals @ points.T  # [N, S] pixels, > 0 on the covered side
    if scales is not None:
        d = d * scales[:, None]
    basis, above = profile_basis(d)
    design = basis.mean(1)
    target = coverage - above.mean(1)
    values, *_ = np.linalg.lstsq(design, target, rcond=None)
    best = float(np.sqrt(np.mean((design @ values - target) ** 2)))
    sharp = float(np.sqrt(np.mean(((d > 0).mean(1) - coverage) ** 2)))
    return best, sharp


def grid(k: int) -> np.ndarray:
    centres = (np.arange(k) + 0.5) / k - 0.5
    x, y = np.meshgrid(centres, centres)
    return np.stack([x.ravel(), y.ravel()], 1)


def main() -> None:
    edges = random_edges(np.random.default_rng(0))
    print(f"{len(edges[2])} edges crossing a pixel")
    for k in (1, 2, 3, 4, 6, 8):
        best, sharp = floor(grid(k), edges)
        print(f"{k} x {k} points: best skin {best:.4f} RMS, sharp edge {sharp:.4f}")
    rng = np.random.default_rng(1)
    for k in (3, 4):
        for spread in (1.0, 1.2, 1.45, 2.0):
            scales = rng.uniform(1.0, spread, len(edges[2])) / ((1 + spread) / 2)
            best, _ = floor(grid(k), edges, scales)
            print(f"{k} x {k} points, pixel widths spread {spread}: one skin for every view {best:.4f} RMS")


if __name__ == "__main__":
    main()
