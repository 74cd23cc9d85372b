"""Before/after of issue 34's displaced-mesh case: primitives' ground-truth meshes against
the same meshes with every vertex moved `offset` along its vertex normal, 200k samples a
side (seed 0), every sample scored (no visibility: no dataset)."""
import sys, time
import numpy as np
sys.path.insert(0, "tests")  # run from the repository root
from test_geometry import _closest_on_triangles, _displaced_primitives
from nerfgauge.core.surface import sample_surface
from nerfgauge.eval.geometry import SurfaceDistance, compare

for fraction in (0.005, 0.01):
    gt_mesh, _ = _displaced_primitives(0.0)
    diagonal = float(np.linalg.norm(gt_mesh.vertices.max(0) - gt_mesh.vertices.min(0)))
    gt_mesh, pred_mesh = _displaced_primitives(fraction * diagonal)
    rng = np.random.default_rng(0)
    gt = sample_surface(gt_mesh.vertices, gt_mesh.faces, 200_000, rng)
    pred = sample_surface(pred_mesh.vertices, pred_mesh.faces, 200_000, rng)
    mask = np.ones(200_000, bool)
    taus = [0.005 * diagonal, 0.01 * diagonal]
    t = time.perf_counter()
    old, _ = compare(pred, gt, mask, taus, diagonal)
    t_old = time.perf_counter() - t
    t = time.perf_counter()
    new, dist = compare(pred, gt, mask, taus, diagonal, gt_mesh=gt_mesh, pred_mesh=pred_mesh)
    t_new = time.perf_counter() - t
    # independent exact computation: the bvh backend (float64) on every sample, Ericson brute force on 2000
    t = time.perf_counter()
    acc_tm = SurfaceDistance(gt_mesh.vertices, gt_mesh.faces, "bvh").query(pred.points)[0]
    comp_tm = SurfaceDistance(pred_mesh.vertices, pred_mesh.faces, "bvh").query(gt.points)[0]
    t_tm = time.perf_counter() - t
    sub = rng.choice(200_000, 2000, replace=False)
    acc_bf = _closest_on_triangles(pred.points[sub], gt_mesh.vertices[gt_mesh.faces])[0]
    comp_bf = _closest_on_triangles(gt.points[sub], pred_mesh.vertices[pred_mesh.faces])[0]
    print(f"offset {fraction:.1%} of the diagonal {diagonal:.4f} = {fraction * diagonal:.5f}")
    print(f"  point to point (before): accuracy {old['accuracy']:.6f} completeness {old['completeness']:.6f} "
          f"F1% {old['at_tau'][1]['fscore']:.4f} F0.5% {old['at_tau'][0]['fscore']:.4f}  {t_old:.1f} s")
    print(f"  point to surface (now, {SurfaceDistance(gt_mesh.vertices, gt_mesh.faces).backend}): accuracy {new['accuracy']:.6f} "
          f"completeness {new['completeness']:.6f} F1% {new['at_tau'][1]['fscore']:.4f} F0.5% {new['at_tau'][0]['fscore']:.4f}  {t_new:.1f} s")
    print(f"  exact, bvh float64: accuracy {acc_tm.mean():.6f} completeness {comp_tm.mean():.6f}  {t_tm:.1f} s")
    print(f"  before / exact: {old['accuracy'] / acc_tm.mean():.4f} {old['completeness'] / comp_tm.mean():.4f};"
          f" now / exact: {new['accuracy'] / acc_tm.mean():.6f} {new['completeness'] / comp_tm.mean():.6f}")
    print(f"  brute-force Ericson on 2000 samples: max |now - oracle| "
          f"{max(np.abs(dist['accuracy'][sub] - acc_bf).max(), np.abs(dist['completeness'][sub] - comp_bf).max()):.2e}")
