"""Lens distortion: OpenCV's radial-tangential model and its fisheye (Kannala-Brandt)
model, as pure numpy (docs/conventions.md, "Lens distortion").

Coordinates. A camera-space point (X, Y, Z) in **OpenCV axes** (+x right, +y down, looking
along +z; our OpenGL camera axes with y and z negated) has the normalised coordinates
x = X / Z, y = Y / Z. The lens moves them to (xd, yd) = distort(x, y), and the pixel is

    u = fx xd + cx,   v = fy yd + cy

in our pixel convention (pixel (row i, col j) covers [j, j + 1) x [i, i + 1); its centre is
(j + 0.5, i + 0.5), as COLMAP has it; OpenCV's own functions put pixel centres on integers,
so an OpenCV user's principal point is cx - 0.5, cy - 0.5).

    opencv:  r2 = x^2 + y^2,  radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3
             xd = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
             yd = y radial + p1 (r2 + 2 y^2) + 2 p2 x y
    fisheye: r = sqrt(x^2 + y^2),  theta = atan(r),
             theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
             xd = (theta_d / r) x,  yd = (theta_d / r) y

(cv2.projectPoints with distCoeffs (k1, k2, p1, p2, k3) and cv2.fisheye.projectPoints with
D = (k1, k2, k3, k4); tests/test_distortion.py compares them.) The inverse (a distorted
pixel -> its ray) is solved by Newton's method with a convergence check (`undistort`).

A distortion is usable for an image only if the map is one-to-one over it: the radial map
(r -> r radial(r) for opencv, theta -> theta_d for fisheye) must increase over every radius
the image reaches (`check_image`); a fisheye must also keep every pixel within 90 degrees
of the optical axis (its rays are rendered through a perspective sensor's film plane).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np

from nerfgauge.core.errors import InputError, NumericalError

# model -> the coefficients, in the order the command line and OpenCV take them
PARAMETERS = {"opencv": ("k1", "k2", "p1", "p2", "k3"), "fisheye": ("k1", "k2", "k3", "k4")}
NERFSTUDIO_MODEL = {"opencv": "OPENCV", "fisheye": "OPENCV_FISHEYE"}  # transforms' camera_model
MODEL_OF_NERFSTUDIO = {name: model for model, name in NERFSTUDIO_MODEL.items()}
NEWTON_TOLERANCE = 1e-12  # normalised units (1e-10 px at a focal length of 100 px)
NEWTON_ITERATIONS = 60
MAX_FISHEYE_THETA = math.pi / 2 - 1e-3  # radians: a pixel's ray must stay in front of the film plane


@dataclass(frozen=True)
class Distortion:
    """One lens distortion. model: "opencv" (k1, k2, p1, p2, k3) or "fisheye" (k1..k4,
    cv2.fisheye's Kannala-Brandt). Coefficients unused by the model are 0."""

    model: str
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    def __post_init__(self):
        if self.model not in PARAMETERS:
            raise InputError(f"distortion model must be one of {', '.join(PARAMETERS)}, got {self.model!r}")
        for name in ("k1", "k2", "k3", "k4", "p1", "p2"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
                raise InputError(f"distortion coefficient {name} must be a finite number, got {value!r}")
            if name not in PARAMETERS[self.model] and value != 0:
                raise InputError(f"the {self.model} distortion model has no coefficient {name} (got {value!r})")

    # --- text and files ----------------------------------------------------------------

    @classmethod
    def parse(cls, text: str) -> "Distortion":
        """"opencv:k1,k2,p1,p2[,k3]" or "fisheye:k1,k2,k3,k4" (the --distortion flag)."""
        usage = "--distortion must be opencv:K1,K2,P1,P2[,K3] or fisheye:K1,K2,K3,K4"
        model, _, rest = str(text).partition(":")
        model = model.strip().lower()
        if model not in PARAMETERS or not rest.strip():
            raise InputError(f"{usage}, got {text!r}")
        try:
            values = [float(part) for part in rest.split(",")]
        except ValueError:
            raise InputError(f"{usage} (numbers), got {text!r}") from None
        names = PARAMETERS[model]
        allowed = (4, 5) if model == "opencv" else (4,)
        if len(values) not in allowed:
            raise InputError(f"{usage}: {model} takes {' or '.join(map(str, allowed))} coefficients, "
                             f"got {len(values)} in {text!r}")
        if not all(math.isfinite(v) for v in values):
            raise InputError(f"{usage}: coefficients must be finite, got {text!r}")
        return cls(model, **dict(zip(names, values)))

    def to_text(self) -> str:
        """The --distortion spelling (parse(to_text()) == self)."""
        return f"{self.model}:" + ",".join(repr(float(getattr(self, name))) for name in PARAMETERS[self.model])

    @property
    def is_identity(self) -> bool:
        """opencv with every coefficient 0 is the pinhole (a fisheye with zeros is not: it is
        the equidistant projection r = f theta)."""
        return self.model == "opencv" and not any(self.coefficients)

    @property
    def coefficients(self) -> np.ndarray:
        """In OpenCV's order: opencv (k1, k2, p1, p2, k3) as cv2's distCoeffs, fisheye
        (k1, k2, k3, k4) as cv2.fisheye's D. [5] or [4] float64."""
        return np.array([float(getattr(self, name)) for name in PARAMETERS[self.model]])

    def to_json(self) -> dict:
        """Transforms' keys: nerfstudio's camera_model and the coefficients by name."""
        return {"camera_model": NERFSTUDIO_MODEL[self.model],
                **{name: float(getattr(self, name)) for name in PARAMETERS[self.model]}}

    @classmethod
    def from_json(cls, meta: dict, where: str):
        """A Distortion from a transforms document's camera_model and k1.. keys; None for a
        pinhole (no camera_model, PINHOLE, or OPENCV with every coefficient 0)."""
        name = meta.get("camera_model")
        if name is None or name in ("PINHOLE", "SIMPLE_PINHOLE"):
            return None
        if name not in MODEL_OF_NERFSTUDIO:
            raise InputError(f"{where}: camera_model must be PINHOLE, OPENCV or OPENCV_FISHEYE, got {name!r}")
        model = MODEL_OF_NERFSTUDIO[name]
        stray = [key for key in ("k1", "k2", "k3", "k4", "p1", "p2") if key in meta and key not in PARAMETERS[model]
                 and meta[key] != 0]
        if stray:
            raise InputError(f"{where}: camera_model {name} has no coefficient {stray[0]} (got {meta[stray[0]]!r})")
        values = {}
        for key in PARAMETERS[model]:
            value = meta.get(key, 0.0)
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise InputError(f"{where}: {key} must be a number, got {value!r}")
            values[key] = float(value)
        try:
            distortion = cls(model, **values)
        except InputError as error:
            raise InputError(f"{where}: {error}") from None
        return None if distortion.is_identity else distortion

    # --- the maps ------------------------------------------------------------------------

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalised undistorted (x, y) [...] -> distorted (xd, yd) [...] (module docstring)."""
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        if self.model == "opencv":
            r2 = x * x + y * y
            radial = 1 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
            return (x * radial + 2 * self.p1 * x * y + self.p2 * (r2 + 2 * x * x),
                    y * radial + self.p1 * (r2 + 2 * y * y) + 2 * self.p2 * x * y)
        r = np.hypot(x, y)
        theta = np.arctan(r)
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = np.where(r > 0, self.radial(theta) / np.where(r > 0, r, 1.0), 1.0)
        return x * scale, y * scale

    def radial(self, r: np.ndarray) -> np.ndarray:
        """The radial map: opencv r -> r (1 + k1 r^2 + k2 r^4 + k3 r^6); fisheye theta -> theta_d."""
        s = np.asarray(r, np.float64) ** 2
        if self.model == "opencv":
            return r * (1 + s * (self.k1 + s * (self.k2 + s * self.k3)))
        return r * (1 + s * (self.k1 + s * (self.k2 + s * (self.k3 + s * self.k4))))

    def radial_derivative(self, r: np.ndarray) -> np.ndarray:
        """d radial / dr: opencv 1 + 3 k1 r^2 + 5 k2 r^4 + 7 k3 r^6; fisheye adds 9 k4 theta^8."""
        s = np.asarray(r, np.float64) ** 2
        return 1 + s * (3 * self.k1 + s * (5 * self.k2 + s * (7 * self.k3 + s * 9 * self.k4)))

    def _jacobian(self, x, y):
        """opencv: d(xd, yd) / d(x, y) as its four entries [...] each."""
        r2 = x * x + y * y
        radial = 1 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        d_radial = self.k1 + r2 * (2 * self.k2 + r2 * 3 * self.k3)  # d radial / d r2
        cross = 2 * x * y * d_radial + 2 * self.p1 * x + 2 * self.p2 * y
        return (radial + 2 * x * x * d_radial + 2 * self.p1 * y + 6 * self.p2 * x, cross,
                cross, radial + 2 * y * y * d_radial + 6 * self.p1 * y + 2 * self.p2 * x)

    def undistort(self, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distorted normalised (xd, yd) [...] -> undistorted (x, y) [...]: the inverse of
        `distort`, by Newton's method from (x, y) = (xd, yd) (opencv: on the 2D map with its
        Jacobian; fisheye: on theta_d(theta) = |(xd, yd)|, then x = tan(theta) xd / |(xd, yd)|).
        Every point must converge to NEWTON_TOLERANCE within NEWTON_ITERATIONS steps, with a
        positive Jacobian (fisheye: a positive derivative and theta < 90 degrees); otherwise
        NumericalError, naming the worst point."""
        xd, yd = np.asarray(xd, np.float64), np.asarray(yd, np.float64)
        if self.model == "fisheye":
            theta, rd = self._fisheye_theta(xd, yd)
            with np.errstate(divide="ignore", invalid="ignore"):
                scale = np.where(rd > 0, np.tan(theta) / np.where(rd > 0, rd, 1.0), 1.0)
            return xd * scale, yd * scale
        if self.is_identity:
            return xd.copy(), yd.copy()
        x, y = xd.copy(), yd.copy()
        for _ in range(NEWTON_ITERATIONS):
            ex, ey = self.distort(x, y)
            ex, ey = ex - xd, ey - yd
            error = np.hypot(ex, ey)
            if not (error > NEWTON_TOLERANCE).any():
                break
            a, b, c, d = self._jacobian(x, y)
            det = a * d - b * c
            if (det <= 0).any() or not np.isfinite(det).all():
                worst = np.unravel_index(np.argmin(np.where(np.isfinite(det), det, -np.inf)), det.shape)
                raise NumericalError(f"{self.to_text()}: the map folds (Jacobian determinant {float(det[worst]):.3g}) "
                                     f"near normalised ({float(x[worst]):.4g}, {float(y[worst]):.4g})")
            x = x - (d * ex - b * ey) / det
            y = y - (a * ey - c * ex) / det
        else:
            worst = np.unravel_index(np.argmax(error), error.shape)
            raise NumericalError(f"{self.to_text()}: undistortion did not converge within {NEWTON_ITERATIONS} Newton "
                                 f"steps at distorted ({float(xd[worst]):.4g}, {float(yd[worst]):.4g}) "
                                 f"(residual {float(error[worst]):.3g})")
        return x, y

    def _fisheye_theta(self, xd, yd):
        """Newton on theta_d(theta) = rd from theta = rd. Returns theta, rd [...]."""
        rd = np.hypot(xd, yd)
        theta = rd.copy()
        for _ in range(NEWTON_ITERATIONS):
            error = self.radial(theta) - rd
            if not (np.abs(error) > NEWTON_TOLERANCE).any():
                break
            slope = self.radial_derivative(theta)
            if (slope <= 0).any() or not np.isfinite(slope).all():
                worst = np.unravel_index(np.argmin(np.where(np.isfinite(slope), slope, -np.inf)), slope.shape)
                raise NumericalError(f"{self.to_text()}: theta_d(theta) stops increasing at theta "
                                     f"{float(theta[worst]):.4g} rad (distorted radius {float(rd[worst]):.4g})")
            theta = theta - error / slope
        else:
            worst = np.unravel_index(np.argmax(np.abs(error)), error.shape)
            raise NumericalError(f"{self.to_text()}: undistortion did not converge within {NEWTON_ITERATIONS} Newton "
                                 f"steps at distorted radius {float(rd[worst]):.4g}")
        if (theta >= MAX_FISHEYE_THETA).any() or (theta < 0).any():
            raise NumericalError(f"{self.to_text()}: a distorted radius {float(rd.max()):.4g} maps to theta "
                                 f"{math.degrees(float(theta.max())):.2f} degrees, at or beyond 90")
        return theta, rd

    # --- pixels and rays -----------------------------------------------------------------

    def pixels_to_film(self, u: np.ndarray, v: np.ndarray, intrinsics) -> tuple[np.ndarray, np.ndarray]:
        """Distorted pixel positions (u, v) [...] -> the pinhole film positions of the same
        rays: (fx x + cx, fy y + cy) with (x, y) = undistort((u - cx) / fx, (v - cy) / fy)."""
        x, y = self.undistort((np.asarray(u, np.float64) - intrinsics.cx) / intrinsics.fx,
                              (np.asarray(v, np.float64) - intrinsics.cy) / intrinsics.fy)
        return intrinsics.fx * x + intrinsics.cx, intrinsics.fy * y + intrinsics.cy

    def camera_directions(self, intrinsics) -> np.ndarray:
        """Camera-space (OpenGL axes) directions of every pixel centre's ray, with z = -1 as
        camera.camera_directions has them: (x, -y, -1) for the undistorted (x, y) of the
        pixel centre. Returns [H, W, 3] float64."""
        cols = np.arange(intrinsics.width) + 0.5
        rows = np.arange(intrinsics.height) + 0.5
        u, v = np.meshgrid(cols, rows)  # [H, W] each
        x, y = self.undistort((u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy)
        return np.stack([x, -y, -np.ones_like(x)], axis=-1)

    def project(self, x: np.ndarray, y: np.ndarray, z: np.ndarray, intrinsics) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates u, v [n] of points in OpenGL camera axes x, y, z [n] (as
        camera.pixel_coordinates, through the lens). NaN for points not in front."""
        ahead = -np.asarray(z, np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            inverse = np.where(ahead > 0, 1.0 / ahead, np.nan)
        xd, yd = self.distort(np.asarray(x, np.float64) * inverse, -np.asarray(y, np.float64) * inverse)
        return intrinsics.cx + intrinsics.fx * xd, intrinsics.cy + intrinsics.fy * yd

    # --- is it usable for this image? ------------------------------------------------------

    def check_image(self, intrinsics, what: str = "--distortion") -> None:
        """InputError (one line) unless the distortion maps the image one-to-one: the
        radial map must increase over every radius the image reaches (its corners'
        distorted radius, from the pixel edges), a fisheye must stay within 90 degrees of
        the axis, and Newton's inverse must converge on a grid over the image."""
        corners_u = np.array([0.0, intrinsics.width])
        corners_v = np.array([0.0, intrinsics.height])
        reach = float(np.max(np.hypot((corners_u[:, None] - intrinsics.cx) / intrinsics.fx,
                                      (corners_v[None, :] - intrinsics.cy) / intrinsics.fy)))
        fold = self.first_fold()
        limit = fold if self.model == "opencv" else min(fold, MAX_FISHEYE_THETA)
        name = "r" if self.model == "opencv" else "theta"
        if math.isfinite(limit) and float(self.radial(limit)) <= reach:
            why = (f"the radial map stops increasing at {name} = {limit:.4g} (d/d{name} = 0), distorted radius "
                   f"{float(self.radial(limit)):.4g}" if limit == fold
                   else f"the image reaches 90 degrees from the optical axis (theta_d(89.94 deg) = "
                        f"{float(self.radial(limit)):.4g})")
            raise InputError(f"{what} {self.to_text()} folds the {intrinsics.width}x{intrinsics.height} image: "
                             f"{why}, inside the image's largest distorted radius {reach:.4g} "
                             f"(normalised); use smaller coefficients or a narrower --fov")
        u, v = np.meshgrid(np.linspace(0, intrinsics.width, 33), np.linspace(0, intrinsics.height, 33))
        try:
            self.pixels_to_film(u, v, intrinsics)
        except NumericalError as error:
            raise InputError(f"{what}: {error} inside the {intrinsics.width}x{intrinsics.height} image") from None

    def first_fold(self) -> float:
        """The smallest r > 0 (theta for fisheye) where the radial map's derivative is 0;
        inf if it increases for every r."""
        # derivative in s = r^2: 1 + 3 k1 s + 5 k2 s^2 + 7 k3 s^3 + 9 k4 s^4
        coefficients = [9 * self.k4, 7 * self.k3, 5 * self.k2, 3 * self.k1, 1.0]
        while coefficients and coefficients[0] == 0:
            coefficients.pop(0)
        roots = np.roots(coefficients) if len(coefficients) > 1 else np.array([])
        positive = [r.real for r in roots if abs(r.imag) <= 1e-12 * max(1.0, abs(r)) and r.real > 0]
        return math.sqrt(min(positive)) if positive else math.inf


def parse_distortion(text) -> "Distortion | None":
    """The --distortion flag: None or "none" for no distortion, else Distortion.parse."""
    if text is None or str(text).strip().lower() == "none":
        return None
    return Distortion.parse(text)
