"""Projection and colour fused in one compiled loop per Gaussian, with a hand-written backward.

The same maths as splat.projection (EWA) and splat.sh (spherical harmonics), which stay the
readable definition and the tests' oracle for this module (float64: 1e-12). The torch
versions build ~60 tensors of N elements per view and autograd walks them back; for the
CPU rasteriser that was the larger half of a training step (50,000 Gaussians at 128 px: ~180
of ~290 ms CPU), here it is one pass each way, parallel over Gaussians.

Backward, per Gaussian, with t the camera-space mean, J the projection's Jacobian, T = J W,
Sigma = M M^T (M = R(q) diag(s)), Sigma' = T Sigma T^T + 0.3 I and K = Sigma'^{-1} = conic:

    G_K      = [[g_a, g_b / 2], [g_b / 2, g_c]]         (conic gradient as a symmetric matrix)
    G_cov    = -K G_K K                                 (d K = -K dSigma' K)
    G_T      = 2 G_cov T Sigma,   G_Sigma = T^T G_cov T,   G_J = G_T W^T
    G_M      = 2 G_Sigma M,   g_s_j = sum_i G_M_ij R_ij,   G_R_ij = G_M_ij s_j
    g_q      = (g_qhat - qhat (qhat . g_qhat)) / |q|    (through the normalisation)
    g_t      from u, v, the depth and J (t_x/t_z, t_y/t_z clamped in J: no gradient there when clamped)
    g_mu     = W^T g_t + (g_d - dhat (dhat . g_d)) / |d|   (d = mu - camera centre, from the colour)
    g_sh_k   = Y_k(dhat) g_colour (0 where the colour is clamped at 0)
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from nerfgauge.splat.projection import FOV_CLAMP, LOW_PASS, NEAR, Camera, Projected
from nerfgauge.splat.sh import C0, C1, C2, C3

SH_C2_0, SH_C2_1, SH_C2_2, SH_C2_3, SH_C2_4 = C2
SH_C3_0, SH_C3_1, SH_C3_2, SH_C3_3, SH_C3_4, SH_C3_5, SH_C3_6 = C3
CHUNK = 1024  # Gaussians per parallel work item: scratch arrays are allocated once per chunk


@numba.njit(cache=True, inline="always")
def _basis(x, y, z, degree, out):
    """Y_k(x, y, z) for k < (degree + 1)^2 into out (splat.sh's order and signs)."""
    out[0] = C0
    if degree >= 1:
        out[1], out[2], out[3] = -C1 * y, C1 * z, -C1 * x
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out[4] = SH_C2_0 * x * y
        out[5] = SH_C2_1 * y * z
        out[6] = SH_C2_2 * (2 * zz - xx - yy)
        out[7] = SH_C2_3 * x * z
        out[8] = SH_C2_4 * (xx - yy)
    if degree >= 3:
        xx, yy, zz = x * x, y * y, z * z
        out[9] = SH_C3_0 * y * (3 * xx - yy)
        out[10] = SH_C3_1 * x * y * z
        out[11] = SH_C3_2 * y * (4 * zz - xx - yy)
        out[12] = SH_C3_3 * z * (2 * zz - 3 * xx - 3 * yy)
        out[13] = SH_C3_4 * x * (4 * zz - xx - yy)
        out[14] = SH_C3_5 * z * (xx - yy)
        out[15] = SH_C3_6 * x * (xx - 3 * yy)


@numba.njit(cache=True, inline="always")
def _basis_gradient(x, y, z, degree, dx, dy, dz):
    """dY_k/dx, dY_k/dy, dY_k/dz (x, y, z as independent variables) into dx, dy, dz."""
    for k in range(16):
        dx[k], dy[k], dz[k] = 0.0, 0.0, 0.0
    if degree >= 1:
        dy[1], dz[2], dx[3] = -C1, C1, -C1
    if degree >= 2:
        dx[4], dy[4] = SH_C2_0 * y, SH_C2_0 * x
        dy[5], dz[5] = SH_C2_1 * z, SH_C2_1 * y
        dx[6], dy[6], dz[6] = -2 * SH_C2_2 * x, -2 * SH_C2_2 * y, 4 * SH_C2_2 * z
        dx[7], dz[7] = SH_C2_3 * z, SH_C2_3 * x
        dx[8], dy[8] = 2 * SH_C2_4 * x, -2 * SH_C2_4 * y
    if degree >= 3:
        xx, yy, zz = x * x, y * y, z * z
        dx[9], dy[9] = SH_C3_0 * 6 * x * y, SH_C3_0 * (3 * xx - 3 * yy)
        dx[10], dy[10], dz[10] = SH_C3_1 * y * z, SH_C3_1 * x * z, SH_C3_1 * x * y
        dx[11], dy[11], dz[11] = -SH_C3_2 * 2 * x * y, SH_C3_2 * (4 * zz - xx - 3 * yy), SH_C3_2 * 8 * y * z
        dx[12], dy[12], dz[12] = -SH_C3_3 * 6 * x * z, -SH_C3_3 * 6 * y * z, SH_C3_3 * (6 * zz - 3 * xx - 3 * yy)
        dx[13], dy[13], dz[13] = SH_C3_4 * (4 * zz - 3 * xx - yy), -SH_C3_4 * 2 * x * y, SH_C3_4 * 8 * x * z
        dx[14], dy[14], dz[14] = SH_C3_5 * 2 * x * z, -SH_C3_5 * 2 * y * z, SH_C3_5 * (xx - yy)
        dx[15], dy[15] = SH_C3_6 * (3 * xx - 3 * yy), -SH_C3_6 * 6 * x * y


@numba.njit(cache=True, inline="always")
def _rotation(qw, qx, qy, qz, r):
    """R of the normalised quaternion into r [3, 3]; returns the normalised (w, x, y, z) and |q|."""
    norm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    w, x, y, z = qw / norm, qx / norm, qy / norm, qz / norm
    r[0, 0], r[0, 1], r[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    r[1, 0], r[1, 1], r[1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    r[2, 0], r[2, 1], r[2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    return w, x, y, z, norm


@numba.njit(cache=True, inline="always")
def _usable(means, scales, quats, view, translation, i, t):
    """Camera-space mean into t; whether Gaussian i is drawn at all (in front, finite, a rotation)."""
    finite = True
    for k in range(3):
        finite = finite and math.isfinite(means[i, k]) and math.isfinite(scales[i, k])
    q_sum = 0.0
    for k in range(4):
        finite = finite and math.isfinite(quats[i, k])
        q_sum += abs(quats[i, k])
    for r in range(3):
        t[r] = view[r, 0] * means[i, 0] + view[r, 1] * means[i, 1] + view[r, 2] * means[i, 2] + translation[r]
        finite = finite and math.isfinite(t[r])
    return finite and q_sum > 0.0 and t[2] > NEAR


@numba.njit(parallel=True, cache=True)
def _forward(means, scales, quats, sh, degree, view, translation, centre, intrinsics, means2d, conics, depths,
             cov_diagonal, colours, in_front):
    fx, fy, cx, cy, lxn, lxp, lyn, lyp = intrinsics
    count = (degree + 1) * (degree + 1)
    n = means.shape[0]
    for chunk in numba.prange((n + CHUNK - 1) // CHUNK):
        t, r, basis = np.empty(3), np.empty((3, 3)), np.empty(16)  # scratch, once per chunk
        t0, t1, a0, a1 = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
        for i in range(chunk * CHUNK, min(n, (chunk + 1) * CHUNK)):
            usable = _usable(means, scales, quats, view, translation, i, t)
            depths[i] = t[2]
            in_front[i] = False
            if not usable:
                means2d[i, 0], means2d[i, 1] = 0.0, 0.0
                conics[i, 0], conics[i, 1], conics[i, 2] = 0.0, 0.0, 0.0
                cov_diagonal[i, 0], cov_diagonal[i, 1] = LOW_PASS, LOW_PASS
                for c in range(3):
                    colours[i, c] = 0.0
                continue
            tx, ty, tz = t[0], t[1], t[2]
            means2d[i, 0], means2d[i, 1] = fx * tx / tz + cx, fy * ty / tz + cy
            jx = tz * min(max(tx / tz, -lxn), lxp)
            jy = tz * min(max(ty / tz, -lyn), lyp)
            j00, j02, j11, j12 = fx / tz, -fx * jx / (tz * tz), fy / tz, -fy * jy / (tz * tz)
            # T = J W (2 x 3)
            for k in range(3):
                t0[k] = j00 * view[0, k] + j02 * view[2, k]
                t1[k] = j11 * view[1, k] + j12 * view[2, k]
            _rotation(quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3], r)
            # T M (M = R diag(s)): cov = (T M)(T M)^T
            for k in range(3):
                a0[k] = (t0[0] * r[0, k] + t0[1] * r[1, k] + t0[2] * r[2, k]) * scales[i, k]
                a1[k] = (t1[0] * r[0, k] + t1[1] * r[1, k] + t1[2] * r[2, k]) * scales[i, k]
            sxx = a0[0] * a0[0] + a0[1] * a0[1] + a0[2] * a0[2] + LOW_PASS
            syy = a1[0] * a1[0] + a1[1] * a1[1] + a1[2] * a1[2] + LOW_PASS
            sxy = a0[0] * a1[0] + a0[1] * a1[1] + a0[2] * a1[2]
            det = sxx * syy - sxy * sxy
            conics[i, 0], conics[i, 1], conics[i, 2] = syy / det, -sxy / det, sxx / det
            cov_diagonal[i, 0], cov_diagonal[i, 1] = sxx, syy
            in_front[i] = det > 0.0 and math.isfinite(conics[i, 0] + conics[i, 1] + conics[i, 2] + sxx + syy)
            dx, dy, dz = means[i, 0] - centre[0], means[i, 1] - centre[1], means[i, 2] - centre[2]
            length = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
            _basis(dx / length, dy / length, dz / length, degree, basis)
            for c in range(3):
                value = 0.5
                for k in range(count):
                    value += basis[k] * sh[i, k, c]
                colours[i, c] = max(value, 0.0)
                if not math.isfinite(value):  # NaN in its colour: not drawn (splat.render's rule)
                    in_front[i] = False


@numba.njit(parallel=True, cache=True)
def _backward(means, scales, quats, sh, degree, view, translation, centre, intrinsics, conics, colours, in_front,
              g_means2d, g_conics, g_depths, g_colours, g_means, g_scales, g_quats, g_sh):
    fx, fy, cx, cy, lxn, lxp, lyn, lyp = intrinsics
    count = (degree + 1) * (degree + 1)
    n = means.shape[0]
    for chunk in numba.prange((n + CHUNK - 1) // CHUNK):
        t, r, g_t = np.empty(3), np.empty((3, 3)), np.empty(3)  # scratch, once per chunk
        basis, bx, by, bz = np.empty(16), np.empty(16), np.empty(16), np.empty(16)
        tm, ts, g_tm = np.empty((2, 3)), np.empty((2, 3)), np.empty((2, 3))
        m, sigma, g_sigma, g_m, g_r = (np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)),
                                         np.empty((3, 3)))
        g_cov = np.empty((2, 2))
        for i in range(chunk * CHUNK, min(n, (chunk + 1) * CHUNK)):
            if not in_front[i]:
                continue
            _usable(means, scales, quats, view, translation, i, t)
            tx, ty, tz = t[0], t[1], t[2]
            g_t[0], g_t[1], g_t[2] = 0.0, 0.0, g_depths[i]
            # means2d: u = fx tx / tz + cx, v = fy ty / tz + cy
            g_t[0] += g_means2d[i, 0] * fx / tz
            g_t[1] += g_means2d[i, 1] * fy / tz
            g_t[2] -= (g_means2d[i, 0] * fx * tx + g_means2d[i, 1] * fy * ty) / (tz * tz)
            # recompute the forward's intermediates
            ratio_x, ratio_y = tx / tz, ty / tz
            jx = tz * min(max(ratio_x, -lxn), lxp)
            jy = tz * min(max(ratio_y, -lyn), lyp)
            j00, j02, j11, j12 = fx / tz, -fx * jx / (tz * tz), fy / tz, -fy * jy / (tz * tz)
            for k in range(3):
                tm[0, k] = j00 * view[0, k] + j02 * view[2, k]
                tm[1, k] = j11 * view[1, k] + j12 * view[2, k]
            w, x, y, z, norm = _rotation(quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3], r)
            for a in range(3):
                for b in range(3):
                    m[a, b] = r[a, b] * scales[i, b]
            for a in range(3):
                for b in range(3):
                    sigma[a, b] = m[a, 0] * m[b, 0] + m[a, 1] * m[b, 1] + m[a, 2] * m[b, 2]
            # G_cov = -K G_K K, K = [[ka, kb], [kb, kc]] the conic
            ka, kb, kc = conics[i, 0], conics[i, 1], conics[i, 2]
            ga, gb, gc = g_conics[i, 0], 0.5 * g_conics[i, 1], g_conics[i, 2]
            p00, p01 = ga * ka + gb * kb, ga * kb + gb * kc  # G_K K
            p10, p11 = gb * ka + gc * kb, gb * kb + gc * kc
            c00 = -(ka * p00 + kb * p10)
            c01 = -(ka * p01 + kb * p11)
            c11 = -(kb * p01 + kc * p11)
            g_cov[0, 0], g_cov[0, 1], g_cov[1, 0], g_cov[1, 1] = c00, c01, c01, c11
            # G_T = 2 G_cov T Sigma, G_Sigma = T^T G_cov T
            for a in range(2):
                for b in range(3):
                    ts[a, b] = tm[a, 0] * sigma[0, b] + tm[a, 1] * sigma[1, b] + tm[a, 2] * sigma[2, b]
            for a in range(2):
                for b in range(3):
                    g_tm[a, b] = 2 * (g_cov[a, 0] * ts[0, b] + g_cov[a, 1] * ts[1, b])
            for a in range(3):
                for b in range(3):
                    g_sigma[a, b] = (tm[0, a] * (c00 * tm[0, b] + c01 * tm[1, b])
                                     + tm[1, a] * (c01 * tm[0, b] + c11 * tm[1, b]))
            # G_J = G_T W^T: entries J00, J02, J11, J12 (J01 = J10 = 0)
            g_j00 = g_tm[0, 0] * view[0, 0] + g_tm[0, 1] * view[0, 1] + g_tm[0, 2] * view[0, 2]
            g_j02 = g_tm[0, 0] * view[2, 0] + g_tm[0, 1] * view[2, 1] + g_tm[0, 2] * view[2, 2]
            g_j11 = g_tm[1, 0] * view[1, 0] + g_tm[1, 1] * view[1, 1] + g_tm[1, 2] * view[1, 2]
            g_j12 = g_tm[1, 0] * view[2, 0] + g_tm[1, 1] * view[2, 1] + g_tm[1, 2] * view[2, 2]
            tz2, tz3 = tz * tz, tz * tz * tz
            g_t[2] += -g_j00 * fx / tz2 - g_j11 * fy / tz2 + 2 * g_j02 * fx * jx / tz3 + 2 * g_j12 * fy * jy / tz3
            g_jx, g_jy = -g_j02 * fx / tz2, -g_j12 * fy / tz2
            if -lxn < ratio_x < lxp:  # jx = tx
                g_t[0] += g_jx
            else:  # jx = tz x the limit
                g_t[2] += g_jx * (lxp if ratio_x >= lxp else -lxn)
            if -lyn < ratio_y < lyp:
                g_t[1] += g_jy
            else:
                g_t[2] += g_jy * (lyp if ratio_y >= lyp else -lyn)
            # t = W mu + w
            for k in range(3):
                g_means[i, k] = view[0, k] * g_t[0] + view[1, k] * g_t[1] + view[2, k] * g_t[2]
            # Sigma = M M^T: G_M = 2 G_Sigma M (G_Sigma symmetric); then M = R diag(s)
            for a in range(3):
                for b in range(3):
                    g_m[a, b] = 2 * (g_sigma[a, 0] * m[0, b] + g_sigma[a, 1] * m[1, b] + g_sigma[a, 2] * m[2, b])
                    g_r[a, b] = g_m[a, b] * scales[i, b]
            for b in range(3):
                g_scales[i, b] = g_m[0, b] * r[0, b] + g_m[1, b] * r[1, b] + g_m[2, b] * r[2, b]
            gw = 2 * (-z * g_r[0, 1] + y * g_r[0, 2] + z * g_r[1, 0] - x * g_r[1, 2] - y * g_r[2, 0] + x * g_r[2, 1])
            gx = 2 * (y * g_r[0, 1] + z * g_r[0, 2] + y * g_r[1, 0] - 2 * x * g_r[1, 1] - w * g_r[1, 2] + z * g_r[2, 0]
                      + w * g_r[2, 1] - 2 * x * g_r[2, 2])
            gy = 2 * (-2 * y * g_r[0, 0] + x * g_r[0, 1] + w * g_r[0, 2] + x * g_r[1, 0] + z * g_r[1, 2]
                      - w * g_r[2, 0] + z * g_r[2, 1] - 2 * y * g_r[2, 2])
            gz = 2 * (-2 * z * g_r[0, 0] - w * g_r[0, 1] + x * g_r[0, 2] + w * g_r[1, 0] - 2 * z * g_r[1, 1]
                      + y * g_r[1, 2] + x * g_r[2, 0] + y * g_r[2, 1])
            dot = w * gw + x * gx + y * gy + z * gz
            g_quats[i, 0], g_quats[i, 1] = (gw - w * dot) / norm, (gx - x * dot) / norm
            g_quats[i, 2], g_quats[i, 3] = (gy - y * dot) / norm, (gz - z * dot) / norm
            # colour: c = max(0, 0.5 + sum_k Y_k(dhat) sh_k)
            dx, dy, dz = means[i, 0] - centre[0], means[i, 1] - centre[1], means[i, 2] - centre[2]
            length = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
            ux, uy, uz = dx / length, dy / length, dz / length
            _basis(ux, uy, uz, degree, basis)
            _basis_gradient(ux, uy, uz, degree, bx, by, bz)
            gux, guy, guz = 0.0, 0.0, 0.0
            for c in range(3):
                if colours[i, c] <= 0.0:
                    continue  # clamped at 0 (the forward's max): no gradient
                g = g_colours[i, c]
                for k in range(count):
                    g_sh[i, k, c] = basis[k] * g
                    gux += bx[k] * sh[i, k, c] * g
                    guy += by[k] * sh[i, k, c] * g
                    guz += bz[k] * sh[i, k, c] * g
            along = ux * gux + uy * guy + uz * guz
            g_means[i, 0] += (gux - ux * along) / length
            g_means[i, 1] += (guy - uy * along) / length
            g_means[i, 2] += (guz - uz * along) / length


def _intrinsics(camera: Camera) -> np.ndarray:
    """fx, fy, cx, cy and the Jacobian's clamp limits (splat.projection's rule)."""
    margin_x = (FOV_CLAMP - 1) * 0.5 * camera.width / camera.fx
    margin_y = (FOV_CLAMP - 1) * 0.5 * camera.height / camera.fy
    return np.array([camera.fx, camera.fy, camera.cx, camera.cy, camera.cx / camera.fx + margin_x,
                     (camera.width - camera.cx) / camera.fx + margin_x, camera.cy / camera.fy + margin_y,
                     (camera.height - camera.cy) / camera.fy + margin_y])


def _numpy(tensor: torch.Tensor) -> np.ndarray:
    return tensor.detach().contiguous().numpy()


class ProjectAndColour(torch.autograd.Function):
    """(means [N, 3], scales [N, 3], quats [N, 4], sh [N, K, 3]) -> (means2d [N, 2], conics
    [N, 3], depths [N], colours [N, 3]) for one camera and SH degree, plus (not
    differentiable) the 2D covariance's diagonal [N, 2] and in_front [N]."""

    @staticmethod
    def forward(ctx, means, scales, quats, sh, degree, camera):
        n, dtype = means.shape[0], means.dtype
        arrays = [_numpy(t) for t in (means, scales, quats, sh)]
        view, translation, centre = (_numpy(t).astype(np.float64) for t in (camera.rotation, camera.translation,
                                                                              camera.centre))
        intrinsics = _intrinsics(camera)
        out = [np.empty((n, 2)), np.empty((n, 3)), np.empty(n), np.empty((n, 2)), np.empty((n, 3)),
               np.empty(n, np.bool_)]
        if n:
            _forward(*arrays, int(degree), view, translation, centre, intrinsics, *out)
        means2d, conics, depths, cov_diagonal, colours, in_front = out
        ctx.save_for_backward(means, scales, quats, sh)
        ctx.kept = (int(degree), view, translation, centre, intrinsics, conics, colours, in_front)
        results = [torch.from_numpy(a).to(dtype) for a in (means2d, conics, depths, colours, cov_diagonal)]
        results.append(torch.from_numpy(in_front))
        ctx.mark_non_differentiable(results[4], results[5])
        return tuple(results)

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, g_colours, _g_cov, _g_in_front):
        means, scales, quats, sh = ctx.saved_tensors
        degree, view, translation, centre, intrinsics, conics, colours, in_front = ctx.kept
        n = means.shape[0]
        as_array = lambda g, shape: np.zeros(shape) if g is None else _numpy(g).astype(np.float64)  # noqa: E731
        grads = [np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 4)), np.zeros(sh.shape)]
        if n:
            _backward(*(_numpy(t) for t in (means, scales, quats, sh)), degree, view, translation, centre, intrinsics,
                      conics, colours, in_front, as_array(g_means2d, (n, 2)), as_array(g_conics, (n, 3)),
                      as_array(g_depths, n), as_array(g_colours, (n, 3)), *grads)
        return (*(torch.from_numpy(g).to(means.dtype) for g in grads), None, None)


def project_and_colour(means: torch.Tensor, scales: torch.Tensor, quats: torch.Tensor, sh: torch.Tensor,
                       degree: int, camera: Camera) -> tuple[Projected, torch.Tensor]:
    """splat.projection.project and splat.sh.sh_colour (direction mu - camera centre) of all
    N Gaussians, in one compiled pass each way. Returns (Projected, colours [N, 3]); the
    colour of a Gaussian not in front is 0, and one whose colour is not finite is not in front."""
    means2d, conics, depths, colours, cov_diagonal, in_front = ProjectAndColour.apply(means, scales, quats, sh,
                                                                                      degree, camera)
    return Projected(means2d, conics, depths, cov_diagonal, in_front), colours
