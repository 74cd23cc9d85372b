"""Exact distance from points to triangles, pair by pair, in float64.

One definition for the two sides that measure to a mesh: the evaluator's nearest-triangle
search (eval.geometry.TriangleSearch, which keeps `triangle_table` columns per triangle)
and the distance of the COLMAP export's initial points to the ground-truth surface
(generate.points).
"""

from __future__ import annotations

import numpy as np


def point_triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Exact distance from points p [n, 3] to triangles (a, b, c) [n, 3] each, row by row
    (`triangle_squared_distance`). [n]."""
    p, a, b, c = (np.asarray(x, np.float64) for x in (p, a, b, c))
    return np.sqrt(triangle_squared_distance(np.ascontiguousarray((p - a).T), triangle_table(a, b, c)))


FLAT_SINE = 1e-8  # a triangle whose corner angle at a has a smaller sine counts as its edges

# rows of triangle_table: what triangle_squared_distance reads of each triangle
AB, AC, BC, NORMAL = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12)
INV_AB2, INV_AC2, INV_BC2, AB_AC, AB2, AC2, FLAT = 12, 13, 14, 15, 16, 17, 18


def triangle_table(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """[19, m]: per triangle (corners a, b, c [m, 3]) its edges ab, ac, bc, unit normal,
    1 / |ab|^2, 1 / |ac|^2, 1 / |bc|^2 (0 for a zero-length edge), ab . ac, |ab|^2, |ac|^2,
    and 1.0 if it is flat (area 0, within FLAT_SINE: the union of its edges), else 0.0."""
    ab, ac, bc = b - a, c - a, c - b
    cross = np.cross(ab, ac)
    area = np.linalg.norm(cross, axis=1)
    squares = [np.einsum("ij,ij->i", e, e) for e in (ab, ac, bc)]
    flat = area <= FLAT_SINE * np.sqrt(squares[0] * squares[1])
    inverse = [np.divide(1.0, s, out=np.zeros_like(s), where=s > 0) for s in squares]
    normal = cross / np.where(flat, 1.0, area)[:, None]
    return np.ascontiguousarray(np.concatenate([ab.T, ac.T, bc.T, normal.T, inverse,
                                                [np.einsum("ij,ij->i", ab, ac), squares[0], squares[1], flat]]))


def triangle_squared_distance(ap: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Squared distance [n] from points to triangles, pair by pair, in float64: ap = p - a
    [3, n] (a a triangle's first corner), table [19, n] its `triangle_table` columns.

    p's projection onto the triangle's plane is inside the triangle when its barycentric
    weights of b and c, vb = (|ac|^2 d1 - (ab.ac) d2) / D and vc = (|ab|^2 d2 - (ab.ac) d1) / D
    (d1 = ab.ap, d2 = ac.ap, D = |ab|^2 |ac|^2 - (ab.ac)^2 > 0), and 1 - vb - vc are all
    non-negative: the distance is then the one to the plane, (n . ap)^2. Otherwise the
    closest point is on the boundary: the nearest of the three edges, each the segment's
    clamped projection (Ericson, Real-Time Collision Detection 5.1.2, 5.1.5). A flat
    triangle is the union of its edges."""
    ab, ac, bc, normal = table[AB], table[AC], table[BC], table[NORMAL]
    d1 = ab[0] * ap[0] + ab[1] * ap[1] + ab[2] * ap[2]
    d2 = ac[0] * ap[0] + ac[1] * ap[1] + ac[2] * ap[2]
    vb = table[AC2] * d1 - table[AB_AC] * d2  # D vb
    vc = table[AB2] * d2 - table[AB_AC] * d1  # D vc
    inside = (vb >= 0) & (vc >= 0) & (vb + vc <= table[AB2] * table[AC2] - table[AB_AC] ** 2) & (table[FLAT] == 0)
    edges = None
    bp = ap - ab
    for start, edge, along, inverse in ((ap, ab, d1, INV_AB2), (ap, ac, d2, INV_AC2),
                                        (bp, bc, d2 - d1 - table[AB_AC] + table[AB2], INV_BC2)):  # bp . bc
        t = np.clip(along * table[inverse], 0.0, 1.0)  # the clamped projection onto the edge
        squared = (start[0] - t * edge[0]) ** 2 + (start[1] - t * edge[1]) ** 2 + (start[2] - t * edge[2]) ** 2
        edges = squared if edges is None else np.minimum(edges, squared, out=edges)
    plane = normal[0] * ap[0] + normal[1] * ap[1] + normal[2] * ap[2]
    squared = np.where(inside, plane * plane, edges)
    return squared
