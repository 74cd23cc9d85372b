"""Geometry against the exact ground-truth meshes: `nerfgauge geometry`.

    nerfgauge geometry DATASET (--pred-mesh FILE | --pred-depth DIR) [-o geometry.json]
                       [--tau T ...] [--samples N] [--seed S] [--whole-surface] [--run RUN]

The prediction is any mesh or point cloud trimesh reads (PLY, OBJ, ...; a PLY or OBJ
without faces is a point cloud), or a method's rendered depth of a split's views
(`r_007_depth.exr` ray distance, found as `nerfgauge evaluate` finds it), back-projected
along the dataset's pixel rays. The ground truth is the union of DATASET/meshes/*.ply.

Both surfaces are read and sampled by core.surface: a mesh uniformly by area (`samples` points, an explicit numpy
Generator seeded with `seed`), each sample carrying its face's normal; a point cloud is
used as given (a random subset of `samples` if larger). The samples are the queries (a
Monte Carlo estimate of a mean over the surface); each is scored by its exact distance,
in world units, to the other side:

    to a mesh         point to surface: the closest point of any triangle (exact
                      point-triangle queries, `SurfaceDistance`: Open3D's RaycastingScene,
                      or `TriangleSearch`, a bounding-volume hierarchy in numpy, when Open3D
                      is not installed; either in memory that does not grow with the
                      number of samples times the number of triangles)
    to a point cloud  point to point: the nearest point (scipy cKDTree, exact); a cloud has
                      no surface between its points

    accuracy      mean over predicted samples of the distance to the ground-truth meshes
    completeness  mean over (visible) ground-truth samples of the distance to the prediction
    chamfer_l1    (accuracy + completeness) / 2
    precision(t)  share of predicted samples within t of the ground truth
    recall(t)     share of (visible) ground-truth samples within t of the prediction
    fscore(t)     2 P R / (P + R)  (0 when both are 0)
    normal_consistency  mean |n . n_closest| over both directions, n_closest the normal of
                  the closest triangle (or of the nearest point of a cloud; orientation-free;
                  null for a prediction without normals)

t runs over fractions of the ground-truth bounding-box diagonal (0.5% and 1%) and any
world-unit values given with --tau. Distances between samples of two meshes (what this
module did before issue 34) overestimate point-to-surface ones: a mesh displaced by 0.5% of
the diagonal scored accuracy and completeness about 3% high at 200k samples (BENCHMARKS.md,
"Exact geometry scores"); a cloud's completeness keeps that sampling bias, as it must.

Visibility. Only ground truth that some camera saw can be asked of a method: by default a
ground-truth sample counts for completeness and recall only if it is visible in some view
of the reference split (train for meshes; the predicted views' split for --pred-depth),
by the exact depth test of core.visibility (the sample projects into the image and its
distance from the camera matches the view's ray-distance depth at that pixel within half
a pixel's footprint, tilted by the surface's angle to the ray up to 80 degrees).
--whole-surface counts every ground-truth sample. Accuracy and
precision always compare against the whole ground truth (a correct guess at a hidden
surface is not an error).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Optional

import numpy as np

from nerfgauge.core.dataset import Dataset
from nerfgauge.core.errors import InputError
from nerfgauge.core.outputs import stamp
from nerfgauge.core.surface import PointSet, Surface, ground_truth_surface, point_set, read_surface, sample_surface
from nerfgauge.core.triangle_distance import triangle_squared_distance, triangle_table
from nerfgauge.core.visibility import visible_in_views
from nerfgauge.eval.predictions import DEPTH_SUFFIXES, read_plane

SCHEMA = 2  # 2: distances to a mesh are exact point to surface (issue 34); "distances" says which
DEFAULT_TAU_FRACTIONS = (0.005, 0.01)
DEFAULT_SAMPLES = 1_000_000
DEFAULT_SEED = 0


# --- prediction from depth -----------------------------------------------------------


def depth_points(ds: Dataset, pred_dir, split: str = "test") -> tuple[np.ndarray, list[str]]:
    """Back-project a method's ray-distance depth of every view of `split` (files as
    `nerfgauge evaluate` finds them: DIR/<split>/r_007_depth.exr or DIR/r_007_depth.exr,
    .exr or .npy, or _distance). Pixels with depth 0 are misses. Returns points [n, 3]
    and the files read."""
    pred_dir = Path(pred_dir)
    if not pred_dir.is_dir():
        raise InputError(f"prediction folder not found: {pred_dir}")
    cameras = ds.cameras(split)
    if not cameras.stems:
        raise InputError(f"dataset {ds.root} has no {split} views")
    points, used = [], []
    for index, stem in enumerate(cameras.stems):
        name = Path(stem).name
        candidates = [folder / (name + suffix + ext) for folder in (pred_dir / split, pred_dir)
                      for suffix in DEPTH_SUFFIXES["distance"] for ext in (".exr", ".npy")]
        path = next((p for p in candidates if p.is_file()), None)
        if path is None:
            raise InputError(f"no predicted depth for frame {stem} (looked for {candidates[0]} and {candidates[2]})")
        depth = read_plane(path, cameras.intrinsics, "distance")
        if not np.isfinite(depth).all():
            raise InputError(f"{path} holds NaN or inf depth")
        if (depth < 0).any():
            raise InputError(f"{path} holds negative depth")
        origins, directions = cameras.rays(index)
        hit = depth > 0
        points.append(origins[hit] + depth[hit][:, None] * directions[hit])
        used.append(str(path))
    cloud = np.concatenate(points)
    if not len(cloud):
        raise InputError(f"the predicted depth in {pred_dir} hits nothing (every pixel is 0)")
    return cloud, used


# --- scoring -------------------------------------------------------------------------


def fscores(accuracy_distances: np.ndarray, completeness_distances: np.ndarray, taus, diagonal: float) -> list[dict]:
    """[{"tau", "tau_fraction", "precision", "recall", "fscore"}] per tau (world units)."""
    rows = []
    for tau in taus:
        precision = float((accuracy_distances < tau).mean())
        recall = float((completeness_distances < tau).mean())
        total = precision + recall
        rows.append({"tau": float(tau), "tau_fraction": float(tau / diagonal), "precision": precision,
                     "recall": recall, "fscore": 2 * precision * recall / total if total > 0 else 0.0})
    return rows


# cKDTree settings for surface samples, measured in CPU seconds for 100k spatially ordered
# queries into 1M samples of the demo model's mesh (pred -> GT, GT -> pred): scipy's
# defaults (leafsize 16, balanced, compact nodes) 3.0 / 0.5 s; midpoint splits, uncompacted
# cells and leaves of 64 points 0.64 / 0.24 s (128: the same, 256: slower). Same answers.
TREE_OPTIONS = {"balanced_tree": False, "compact_nodes": False, "leafsize": 64}


def spatial_order(points: np.ndarray) -> np.ndarray:
    """A permutation [n] of points [n, 3] that puts neighbours next to each other (the
    leaf order of a k-d tree)."""
    from scipy.spatial import cKDTree  # scipy: only when distances are computed

    return cKDTree(points, **TREE_OPTIONS).indices


class NearestNeighbours:
    """Exact nearest reference point of query points: a cKDTree over reference points
    [n_ref, 3] stored in spatial order.

    Exact. A k-d tree query for a point at distance d from a surface sampled with spacing s
    inspects every sample in a cap of the surface around the nearest one (~ d / s samples
    when the tree's cells are of the order of s), so a prediction with floaters far from
    the truth costs time; answering those from a subsample instead (tried) overestimated
    the primitives CI model's completeness by 6.5% and single distances by up to 0.077, so
    the scores stay exact. What makes it fast is memory order: the references and the
    queries both in spatial order, so consecutive queries walk the same cells (measured on
    a loaded machine, 100k of the demo mesh's samples into 1M ground-truth ones, one
    thread: 3.9 s in sampling order, 1.0 s with both sets in spatial order)."""

    def __init__(self, reference: np.ndarray, order: Optional[np.ndarray] = None):
        from scipy.spatial import cKDTree  # scipy, as above

        self.order = spatial_order(reference) if order is None else order  # [n_ref]
        self.tree = cKDTree(reference[self.order], **TREE_OPTIONS)

    def query(self, queries: np.ndarray, query_order: Optional[np.ndarray] = None) -> tuple[np.ndarray, np.ndarray]:
        """Distance [n] and reference index [n] (the caller's numbering) of the nearest
        reference point of every query [n, 3]; query_order [n]: a spatial order of the
        queries if the caller has one."""
        query_order = spatial_order(queries) if query_order is None else query_order
        distance, index = np.empty(len(queries)), np.empty(len(queries), np.int64)
        sorted_distance, sorted_index = self.tree.query(queries[query_order], workers=-1)
        distance[query_order], index[query_order] = sorted_distance, self.order[sorted_index]
        return distance, index


def nearest(reference: np.ndarray, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance and index of the nearest reference point [n_ref, 3] of every query [n, 3]
    (exact; see NearestNeighbours)."""
    return NearestNeighbours(reference).query(queries)


class TriangleSearch:
    """Exact closest triangle of query points, in memory bounded by PAIR_BLOCK and
    QUERY_BLOCK, not by the number of queries times the number of triangles: the "bvh"
    backend of SurfaceDistance (float64, numpy only).

    A bounding-volume hierarchy: the triangles are split at the median of their centroids
    along the longest side of each node's box, level by level, into a complete binary tree
    whose leaves hold LEAF triangles each (stored leaf by leaf); every node keeps the box of
    its triangles and one point of its surface (a corner of its middle triangle). No
    triangle under a node is nearer to p than the node's box, and the nearest triangle is
    no farther than any surface point, so a query
    1. descends greedily (into the child whose box is nearer) to one leaf: the exact
       distance to its triangles bounds the answer from above;
    2. goes down the tree again, level by level, keeping only the nodes whose box is nearer
       than the best distance so far, which each level lowers to the distance of the kept
       nodes' surface points (for a point 50 units from a mesh of size 1, a node of size s
       offset sideways puts its point within s^2 / 100 of the answer);
    3. takes the exact distance (`triangle_squared_distance`) to the triangles of every
       leaf reached.
    Queries go in the order of their greedy leaf, QUERY_BLOCK at a time, so that neighbours
    read the same part of the tree; (query, node) and (query, triangle) pairs go PAIR_BLOCK
    at a time (a level's pairs beyond that wait on a stack, at most one block per level).
    A point far from a small mesh reaches the few leaves whose boxes face it; even a point
    at the centre of a sphere, to which every triangle is as near as the nearest, takes
    them all, a block at a time.

    Memory: ~200 bytes a triangle kept (its table and the boxes; ~800 while building: 1.3M
    triangles took 976 MB), ~300 bytes a pair in a block, ~40 bytes a query."""

    LEAF = 8  # triangles per leaf
    PAIR_BLOCK = 1 << 16  # (query, node) or (query, triangle) pairs handled at once: ~20 MB
    QUERY_BLOCK = 1 << 14  # queries traversed together

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        corners = np.asarray(vertices, np.float64)[faces]  # [m, 3, 3]
        count = len(corners)
        if not count:
            raise ValueError("a mesh without faces has no surface to measure to")
        self.depth = max(0, math.ceil(math.log2(max(1, -(-count // self.LEAF)))))
        leaves = 1 << self.depth
        slots = np.full(leaves * self.LEAF, -1, np.int64)  # triangle of each slot; -1: empty
        slots[:count] = np.arange(count)
        centroid = corners.mean(axis=1)  # [m, 3]
        for level in range(self.depth):  # split every node of this level at its median
            blocks = slots.reshape(1 << level, -1)  # [nodes, slots per node]
            filled = blocks >= 0
            spans = []
            for axis in range(3):
                values = centroid[blocks, axis]
                spans.append(np.where(filled, values, -np.inf).max(axis=1) - np.where(filled, values, np.inf).min(axis=1))
            axis = np.argmax(np.stack(spans), axis=0)  # [nodes]: the longest side
            key = np.where(filled, centroid[blocks, axis[:, None]], np.inf)  # empty slots go last
            half = blocks.shape[1] // 2
            slots = np.take_along_axis(blocks, np.argpartition(key, half - 1, axis=1), axis=1).ravel()
        del centroid
        # empty slots repeat the filled slot before them (the first slot is always filled):
        # a duplicate only repeats a distance, and empty leaves are never reached (no box)
        empty = slots < 0
        self.triangle_of_slot = slots.copy()
        self.triangle_of_slot[empty] = slots[np.maximum.accumulate(np.where(empty, 0, np.arange(len(slots))))][empty]
        # node n's children are 2n and 2n + 1: the root is 1, the leaves are leaves .. 2 leaves - 1
        self.low, self.high = np.full((3, 2 * leaves), np.inf), np.full((3, 2 * leaves), -np.inf)
        filled = (~empty).reshape(leaves, self.LEAF)
        leaf_corners = corners[self.triangle_of_slot].reshape(leaves, self.LEAF, 3, 3)
        self.low[:, leaves:] = np.where(filled[..., None], leaf_corners.min(axis=2), np.inf).min(axis=1).T
        self.high[:, leaves:] = np.where(filled[..., None], leaf_corners.max(axis=2), -np.inf).max(axis=1).T
        del leaf_corners
        for level in range(self.depth - 1, -1, -1):
            children = slice(2 << level, 4 << level)
            self.low[:, 1 << level:2 << level] = np.minimum(self.low[:, children][:, 0::2], self.low[:, children][:, 1::2])
            self.high[:, 1 << level:2 << level] = np.maximum(self.high[:, children][:, 0::2],
                                                            self.high[:, children][:, 1::2])
        # per slot: its triangle_table column and its first corner a (rows CORNER), [22, slots]
        corners = corners[self.triangle_of_slot]
        self.table = np.concatenate([triangle_table(corners[:, 0], corners[:, 1], corners[:, 2]),
                                     corners[:, 0].T])
        # per node, a point on the surface: the first corner of the middle slot under it; its
        # distance bounds the answer from above, ever closer as a query descends
        self.sample_slot = np.zeros(2 * leaves, np.int64)
        for level in range(self.depth + 1):
            width = (leaves >> level) * self.LEAF  # slots under one node of this level
            self.sample_slot[1 << level:2 << level] = np.arange(1 << level) * width + width // 2
        self.sample = np.ascontiguousarray(self.table[self.CORNER][:, self.sample_slot])  # [3, nodes]

    CORNER = slice(19, 22)

    def squared_distance(self, points: np.ndarray, slots: np.ndarray) -> np.ndarray:
        """Squared distance [n] of points [3, n] to the triangles in slots [n], pair by pair."""
        row = np.take(self.table, slots, axis=1)  # [22, n]
        return triangle_squared_distance(points - row[self.CORNER], row)

    def box_squared_distance(self, points: np.ndarray, nodes: np.ndarray) -> np.ndarray:
        """Squared distance [n] of points [3, n] to the boxes of nodes [n] (inf: an empty node)."""
        total = np.zeros(points.shape[1])
        for axis in range(3):
            x = points[axis]
            gap = np.maximum(np.maximum(self.low[axis, nodes] - x, x - self.high[axis, nodes]), 0.0)
            total += gap * gap
        return total

    def query(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance [n] and closest triangle [n] int64 of points [n, 3] (class docstring)."""
        xyz = np.ascontiguousarray(np.asarray(points, np.float64).T)  # [3, n]
        leaf = np.empty(xyz.shape[1], np.int64)
        for start in range(0, xyz.shape[1], self.QUERY_BLOCK):  # 1. greedy descent
            node = np.ones(min(self.QUERY_BLOCK, xyz.shape[1] - start), np.int64)
            part = xyz[:, start:start + len(node)]
            for _ in range(self.depth):
                left = 2 * node
                node = np.where(self.box_squared_distance(part, left) <= self.box_squared_distance(part, left + 1),
                                left, left + 1)
            leaf[start:start + len(node)] = node
        best, slot = np.full(xyz.shape[1], np.inf), np.zeros(xyz.shape[1], np.int64)
        order = np.argsort(leaf, kind="stable")  # neighbours together
        for start in range(0, len(order), self.QUERY_BLOCK):
            which = order[start:start + self.QUERY_BLOCK]
            part = np.ascontiguousarray(xyz[:, which])
            best[which], slot[which] = self._exact(part, leaf[which])
        return np.sqrt(best), self.triangle_of_slot[slot]

    def _exact(self, xyz: np.ndarray, greedy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Squared distance [q] and closest slot [q] of points xyz [3, q] whose greedy leaf is
        greedy [q] (step 2 of the class docstring)."""
        count = xyz.shape[1]
        best, slot = np.full(count, np.inf), np.zeros(count, np.int64)
        everyone = np.arange(count)
        self._visit_leaves(xyz, everyone, greedy, best, slot)
        stack = [(0, everyone, np.ones(count, np.int64), np.zeros(count))]
        while stack:
            level, which, node, bound = stack.pop()
            near = bound < best[which]  # the best may have dropped since this was pushed
            which, node = which[near], node[near]
            if level == self.depth:
                fresh = node != greedy[which]  # that leaf is done
                self._visit_leaves(xyz, which[fresh], node[fresh], best, slot)
                continue
            which = np.repeat(which, 2)
            node = 2 * np.repeat(node, 2) + np.tile(np.array([0, 1]), len(node))
            bound = self.box_squared_distance(xyz[:, which], node)
            near = bound < best[which]
            which, node, bound = which[near], node[near], bound[near]
            self._lower_by_samples(xyz, which, node, best, slot)
            for start in range(0, len(which), self.PAIR_BLOCK):
                block = slice(start, start + self.PAIR_BLOCK)
                stack.append((level + 1, which[block], node[block], bound[block]))
        return best, slot

    def _lower_by_samples(self, xyz: np.ndarray, which: np.ndarray, node: np.ndarray, best: np.ndarray,
                          slot: np.ndarray) -> None:
        """Lower best (squared) of the queries `which` [k] to their distance from the surface
        sample of `node` [k]: a corner of the triangle in slot sample_slot, which is at least
        as near (so the slot recorded with it is right whenever the value is final)."""
        offset = xyz[:, which] - self.sample[:, node]
        squared = offset[0] * offset[0] + offset[1] * offset[1] + offset[2] * offset[2]
        np.minimum.at(best, which, squared)
        won = squared <= best[which]
        slot[which[won]] = self.sample_slot[node[won]]

    def _visit_leaves(self, xyz: np.ndarray, which: np.ndarray, leaf: np.ndarray, best: np.ndarray,
                      slot: np.ndarray) -> None:
        """Lower best (squared) and slot of the queries `which` [k] (columns of xyz [3, q]) by
        the exact distances to the triangles of their leaves `leaf` [k] (node numbers),
        PAIR_BLOCK pairs at a time."""
        rows = max(1, self.PAIR_BLOCK // self.LEAF)
        first_leaf = len(self.low[0]) // 2
        for start in range(0, len(which), rows):
            part = which[start:start + rows]
            slots = ((leaf[start:start + rows] - first_leaf) * self.LEAF)[:, None] + np.arange(self.LEAF)  # [r, LEAF]
            squared = self.squared_distance(np.repeat(xyz[:, part], self.LEAF, axis=1),
                                            slots.ravel()).reshape(len(part), self.LEAF)
            pick = squared.argmin(axis=1)
            low = squared[np.arange(len(part)), pick]
            np.minimum.at(best, part, low)
            won = low <= best[part]
            slot[part[won]] = slots[won, pick[won]]


class SurfaceDistance:
    """Exact distance from query points to a triangle mesh (vertices [n, 3], faces [m, 3]),
    with the closest triangle of each query, in memory that does not grow with the number
    of queries times the number of triangles.

    Backends, both exact point-triangle queries: "open3d"
    (`o3d.t.geometry.RaycastingScene.compute_closest_points`, a bounding-volume hierarchy,
    the `geometry` extra; float32 inside, so coordinates are taken relative to the mesh's
    centre first: relative error ~1e-7 of the scene's size; queries in chunks of CHUNK) or
    "bvh" (`TriangleSearch`: float64, numpy only, the fallback without Open3D).
    trimesh's `proximity.closest_point`, the fallback before issue 47, gathered every
    candidate triangle of a whole chunk of queries at once (26 GiB for depth-range)."""

    CHUNK = 1 << 18  # queries handed to Open3D at once

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, backend: Optional[str] = None):
        self.vertices = np.asarray(vertices, np.float64)
        self.faces = np.asarray(faces, np.int64)
        self.backend = backend or distance_backend()
        self.shift = (self.vertices.min(axis=0) + self.vertices.max(axis=0)) / 2
        if self.backend == "open3d":
            import open3d as o3d  # open3d: an optional extra, ~900 MB, loaded only to score geometry

            self._scene = o3d.t.geometry.RaycastingScene()
            self._scene.add_triangles(o3d.core.Tensor((self.vertices - self.shift).astype(np.float32)),
                                      o3d.core.Tensor(self.faces.astype(np.uint32)))
        elif self.backend == "bvh":
            self._search = TriangleSearch(self.vertices - self.shift, self.faces)
        else:
            raise ValueError(f"unknown distance backend {self.backend!r}")

    def query(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance [n] (float64, world units) and closest triangle [n] int64 of points [n, 3]."""
        local = np.asarray(points, np.float64) - self.shift
        if self.backend == "bvh":
            return self._search.query(local)
        import open3d as o3d  # open3d: as above

        distance, triangle = np.empty(len(local)), np.empty(len(local), np.int64)
        for start in range(0, len(local), self.CHUNK):
            part = local[start:start + self.CHUNK]
            found = self._scene.compute_closest_points(o3d.core.Tensor(part.astype(np.float32)))
            closest = found["points"].numpy().astype(np.float64)
            triangle[start:start + len(part)] = found["primitive_ids"].numpy().astype(np.int64)
            # the distance to the returned closest point, in float64 (the query's own precision)
            distance[start:start + len(part)] = np.linalg.norm(part - closest, axis=1)
        return distance, triangle

    @staticmethod
    def normals_of(mesh: "Surface", faces: np.ndarray) -> np.ndarray:
        """Unit normals [k, 3] of the triangles `faces` [k] of `mesh`."""
        tri = mesh.vertices[mesh.faces[faces]]  # [k, 3, 3]
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        return cross / np.maximum(np.linalg.norm(cross, axis=1, keepdims=True), 1e-300)


def distance_backend() -> str:
    """"open3d" when it imports, else "bvh" (TriangleSearch: scipy and numpy)."""
    global _BACKEND
    if _BACKEND is None:
        try:
            import open3d  # noqa: F401  (open3d: optional; its wheel also needs the system's libusb-1.0)

            _BACKEND = "open3d"
        except Exception:  # not installed, or a shared library missing
            _BACKEND = "bvh"
    return _BACKEND


_BACKEND = None  # found once per process (an import attempt of open3d costs a second)


def compare(pred: PointSet, gt_all: PointSet, gt_mask: np.ndarray, taus, diagonal: float,
            gt_mesh: Optional[Surface] = None, pred_mesh: Optional[Surface] = None) -> tuple[dict, dict]:
    """Scores of `pred` against ground-truth samples (all of them for accuracy, those in
    gt_mask [n] for completeness). gt_mesh / pred_mesh: the meshes the samples were drawn
    from; given, distances to that side are exact point to surface (`SurfaceDistance`),
    else point to point (to a cloud). Returns (scores, {"accuracy": d [n_pred],
    "completeness": d [n_visible]} distances)."""
    gt_points = gt_all.points[gt_mask]
    if not len(gt_points):
        raise InputError("no ground-truth surface is visible from the reference cameras; pass --whole-surface")
    gt_order = pred_order = None
    if gt_mesh is None or pred_mesh is None:
        # each point set in spatial order once: as the reference of one direction and the
        # queries of the other (the visible ground truth keeps the whole set's order)
        gt_order, pred_order = spatial_order(gt_all.points), spatial_order(pred.points)
    if gt_mesh is not None:
        to_gt, gt_face = SurfaceDistance(gt_mesh.vertices, gt_mesh.faces).query(pred.points)
        gt_normal_of_pred = SurfaceDistance.normals_of(gt_mesh, gt_face)
    else:
        to_gt, gt_index = NearestNeighbours(gt_all.points, gt_order).query(pred.points, pred_order)
        gt_normal_of_pred = None if gt_all.normals is None else gt_all.normals[gt_index]
    if pred_mesh is not None:
        to_pred, pred_face = SurfaceDistance(pred_mesh.vertices, pred_mesh.faces).query(gt_points)
        pred_normal_of_gt = SurfaceDistance.normals_of(pred_mesh, pred_face)
    else:
        visible_rank = np.cumsum(gt_mask) - 1  # index of a visible sample within gt_points
        to_pred, pred_index = NearestNeighbours(pred.points, pred_order).query(
            gt_points, visible_rank[gt_order[gt_mask[gt_order]]])
        pred_normal_of_gt = None if pred.normals is None else pred.normals[pred_index]
    accuracy, completeness = float(to_gt.mean()), float(to_pred.mean())
    consistency = None
    if pred.normals is not None and gt_all.normals is not None and gt_normal_of_pred is not None \
            and pred_normal_of_gt is not None:
        forward = np.abs(np.einsum("ij,ij->i", pred.normals, gt_normal_of_pred)).mean()
        backward = np.abs(np.einsum("ij,ij->i", gt_all.normals[gt_mask], pred_normal_of_gt)).mean()
        consistency = float((forward + backward) / 2)
    scores = {"accuracy": accuracy, "completeness": completeness, "chamfer_l1": (accuracy + completeness) / 2,
              "normal_consistency": consistency, "at_tau": fscores(to_gt, to_pred, taus, diagonal)}
    return scores, {"accuracy": to_gt, "completeness": to_pred}


def check_in_bounds(points: np.ndarray, box: np.ndarray, name: str) -> None:
    inside = ((points >= box[0]) & (points <= box[1])).all(axis=1)
    if not inside.any():
        lo, hi = points.min(axis=0), points.max(axis=0)
        raise InputError(f"{name} lies entirely outside the scene bounds {np.round(box, 4).tolist()} "
                         f"(its points span {np.round(lo, 4).tolist()} to {np.round(hi, 4).tolist()})")


def score_geometry(root, pred_mesh=None, pred_depth=None, *, split: str = "test", taus=(), samples: int = DEFAULT_SAMPLES,
                   seed: int = DEFAULT_SEED, whole_surface: bool = False) -> tuple[dict, dict]:
    """Score a mesh or point cloud file (pred_mesh) or a folder of depth maps (pred_depth)
    against the dataset's meshes. Returns (document, distances) (see `compare`)."""
    start = time.perf_counter()
    if (pred_mesh is None) == (pred_depth is None):
        raise InputError("give exactly one of --pred-mesh FILE or --pred-depth DIR")
    if not (isinstance(samples, int) and samples > 0):
        raise InputError(f"--samples must be a positive integer, got {samples!r}")
    for tau in taus:
        if not (isinstance(tau, (int, float)) and math.isfinite(tau) and tau > 0):
            raise InputError(f"--tau must be a positive distance, got {tau!r}")
    ds = Dataset(root)
    gt_surface = ground_truth_surface(ds)
    rng = np.random.default_rng(seed)
    if pred_mesh is not None:
        surface, name, kind, reference = read_surface(pred_mesh), str(pred_mesh), None, "train"
        kind = "mesh" if surface.faces is not None else "points"
    else:
        cloud, _ = depth_points(ds, pred_depth, split)
        surface, name, kind, reference = Surface(cloud, None), str(pred_depth), "depth", split
    gt_box = np.stack([gt_surface.vertices.min(axis=0), gt_surface.vertices.max(axis=0)])
    box = ds.bounds if ds.bounds is not None else gt_box
    check_in_bounds(surface.vertices, box, name)
    diagonal = float(np.linalg.norm(gt_box[1] - gt_box[0]))
    pred = point_set(surface, samples, rng, name)
    gt = sample_surface(gt_surface.vertices, gt_surface.faces, samples, rng, "the ground-truth meshes")
    visible = np.ones(len(gt.points), bool) if whole_surface else visible_in_views(gt.points, gt.normals, ds, reference)
    all_taus = sorted({*(f * diagonal for f in DEFAULT_TAU_FRACTIONS), *(float(t) for t in taus)})
    scores, distances = compare(pred, gt, visible, all_taus, diagonal, gt_mesh=gt_surface,
                                pred_mesh=surface if surface.faces is not None else None)
    to_mesh = f"point to surface (exact, {distance_backend()})"
    method = {"accuracy": to_mesh, "completeness": to_mesh if surface.faces is not None else
              "point to point (the prediction is a point cloud)"}
    scene = ds.scene.get("recipe") if isinstance(ds.scene.get("recipe"), str) else ds.root.name
    document = {"schema": SCHEMA, "scene": scene, "prediction": {"source": name, "kind": kind,
                                                                  "points": int(len(pred.points))},
                "ground_truth": {"diagonal": diagonal, "samples": int(len(gt.points)),
                                 "scored_samples": int(visible.sum()), "scored_fraction": float(visible.mean()),
                                 "whole_surface": bool(whole_surface),
                                 "visibility_split": None if whole_surface else reference},
                "samples": samples, "seed": seed, "distances": method, **scores,
                "seconds": time.perf_counter() - start}
    return stamp(document, "geometry"), distances


def summary(document: Optional[dict]) -> dict:
    """Flat numbers for the run's metrics.json `geometry` section (gated by `nerfgauge check`).
    None (the field had no surface to score): every figure null, so its bounds fail."""
    if document is None:
        return dict.fromkeys(SUMMARY_NAMES)
    flat = {}
    if "chamfer_l1" in document:
        flat.update({"geometry_accuracy": document["accuracy"], "geometry_completeness": document["completeness"],
                     "geometry_chamfer_l1": document["chamfer_l1"],
                     "geometry_normal_consistency": document["normal_consistency"]})
        for row in document["at_tau"]:
            for fraction, label in ((0.005, "0p5pct"), (0.01, "1pct")):
                if math.isclose(row["tau_fraction"], fraction, rel_tol=1e-9):
                    flat[f"geometry_fscore_{label}"] = row["fscore"]
    normals = document.get("normals")
    if normals:
        flat.update({"normal_angle_mean": normals["mean_degrees"], "normal_angle_median": normals["median_degrees"],
                     "normal_within_11_25": normals["within"]["11.25"],
                     "normal_within_22_5": normals["within"]["22.5"], "normal_within_30": normals["within"]["30"]})
    return flat


SUMMARY_NAMES = ("geometry_accuracy", "geometry_completeness", "geometry_chamfer_l1", "geometry_normal_consistency",
                 "geometry_fscore_0p5pct", "geometry_fscore_1pct", "normal_angle_mean", "normal_angle_median",
                 "normal_within_11_25", "normal_within_22_5", "normal_within_30")


def format_geometry(document: dict) -> str:
    """A few plain-text lines of the scores."""
    lines = []
    if "chamfer_l1" in document:
        gt = document["ground_truth"]
        nc = document["normal_consistency"]
        lines.append(f"accuracy {document['accuracy']:.5f}  completeness {document['completeness']:.5f}  "
                     f"chamfer-L1 {document['chamfer_l1']:.5f}  normal consistency {'-' if nc is None else f'{nc:.4f}'}"
                     f"  (ground truth scored: {100 * gt['scored_fraction']:.1f}% of its surface)")
        for row in document["at_tau"]:
            lines.append(f"tau {row['tau']:.5f} ({100 * row['tau_fraction']:.2f}% of the diagonal): precision "
                         f"{row['precision']:.4f}  recall {row['recall']:.4f}  F-score {row['fscore']:.4f}")
    normals = document.get("normals")
    if normals:
        within = normals["within"]
        lines.append(f"normals: mean {normals['mean_degrees']:.2f} deg, median {normals['median_degrees']:.2f} deg; "
                     f"within 11.25/22.5/30 deg: {within['11.25']:.3f}/{within['22.5']:.3f}/{within['30']:.3f} "
                     f"({normals['pixels']} pixels)")
    return "\n".join(lines)
