"""Rendering through a lens distortion (docs/conventions.md, "Lens distortion").

A distorted camera is rendered exactly, not resampled: each sample keeps the film position
Mitsuba's sampler draws for it (a uniform position in its pixel, the box filter), and that
position (u, v), a point of the *distorted* pixel grid, is replaced by the pinhole film
position of the same ray, (fx x + cx, fy y + cy) with (x, y) the undistorted normalised
coordinates of (u, v) (core.distortion.Distortion.pixels_to_film, Newton's method). The
perspective (or thin-lens) sensor then makes the ray of that film position, which need not
lie inside the film: barrel distortion sees past the pinhole image's edges.

- JIT variants (llvm, cuda): render.render_samples with `film_map`: the positions are drawn
  on the device, mapped in numpy (float64, cast back to float32) and the rest of the sample
  (aperture, integrator) proceeds as for a pinhole; the same fixed-order sums, so the image
  is byte-identical from run to run.
- scalar_rgb: mi.render cannot take custom film positions, so the same estimator is run here
  sample by sample in Python (`render_scalar`): one sampler seeded per pixel (pixel p of a
  call with seed s: (s + p * PIXEL_SEED_STRIDE) mod 2^32), the pixel's spp samples drawn in Mitsuba's order
  (position, aperture, integrator; sampler.advance() after each), summed in order in float64.
  It is the same estimator (same expectation and per-pixel stratification), not the same
  random numbers as the llvm image, and slow: about 0.1 ms per sample (32x32 px at 8 spp,
  ~1 s), meant for tests and small datasets.

Ray differentials are those the sensor gives at the mapped film position (scaled by
1/sqrt(spp) as in render_samples): the pinhole's pixel footprint there, which differs from
the distorted pixel's footprint by the local magnification of the map; they only choose
texture filter widths.
"""

from __future__ import annotations

import math

import numpy as np

PIXEL_SEED_STRIDE = 0x85EBCA6B  # odd; render.BAND_SEED_STRIDE's constant, here per pixel


def film_map(distortion, intrinsics):
    """The function render.render_samples maps its film positions with: distorted pixel
    positions (u, v) [n] -> the pinhole film positions of their rays [n] each."""

    def mapped(u, v):
        return distortion.pixels_to_film(u, v, intrinsics)

    return mapped


def render_scalar(mi, scene, integrator, sensor, intrinsics, distortion, spp: int, seed: int,
                  ray_map=None) -> np.ndarray:
    """`spp` samples per pixel of `sensor` seen through `distortion` on a scalar variant
    (module docstring); with `ray_map` (render.render_samples') each sample takes that ray
    instead (weight 1, no differentials). Returns [H, W, 4 + AOVs] float32: RGB, alpha (share
    of samples whose ray hit), then the integrator's AOVs, as render.render_samples."""
    to_film = film_map(distortion, intrinsics) if ray_map is None else None
    integrator = integrator if integrator is not None else scene.integrator()
    width, height = intrinsics.width, intrinsics.height
    sampler = sensor.sampler().clone()
    sampler.set_sample_count(int(spp))
    medium = sensor.get_medium()
    needs_aperture = sensor.needs_aperture_sample()
    shutter_open, shutter_time = sensor.shutter_open(), sensor.shutter_open_time()
    rows = []
    for i in range(height):
        for j in range(width):
            sampler.seed((int(seed) + (i * width + j) * PIXEL_SEED_STRIDE) % (2**32))
            total = None
            for _ in range(int(spp)):
                sample = sampler.next_2d()
                aperture = sampler.next_2d() if needs_aperture else mi.Point2f(0.5)
                time = shutter_open + (sampler.next_1d() * shutter_time if shutter_time > 0 else 0.0)
                if ray_map is not None:
                    origin, direction = ray_map(np.array([j + sample[0]]), np.array([i + sample[1]]))
                    ray = mi.RayDifferential3f(mi.Ray3f(mi.Point3f(*origin[0]), mi.Vector3f(*direction[0])))
                    weight = 1.0
                else:
                    u, v = to_film(np.array([j + sample[0]]), np.array([i + sample[1]]))
                    position = mi.Point2f(float(u[0]) / width, float(v[0]) / height)
                    ray, weight = sensor.sample_ray_differential(time, 0.0, position, aperture)
                    ray.scale_differential(1.0 / math.sqrt(spp))
                radiance, valid, aovs = integrator.sample(scene, sampler, ray, medium)
                rgb = weight * radiance
                values = np.array([rgb[0], rgb[1], rgb[2], 1.0 if valid else 0.0] + [float(a) for a in aovs])
                total = values if total is None else total + values
                sampler.advance()
            rows.append(total / spp)
    return np.asarray(rows).reshape(height, width, -1).astype(np.float32)
