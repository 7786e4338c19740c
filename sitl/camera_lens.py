"""The rays of a camera's pixels: OpenCV's lens models inverted, once per calibration.

Frame (OpenCV's optical frame, companion/calibration.py): x right, y down in the image, z along the
optical axis; pixels (u, v) = (column, row), integer values at pixel centres. A ray is (x, y, 1) in
normalised image coordinates. :func:`project` is OpenCV's projection (cv2.projectPoints for
plumb_bob, cv2.fisheye.projectPoints for equidistant) in numpy, over ten times faster on a whole
image; :func:`unproject` inverts it by Newton's method from cv2.undistortPoints' estimate, to 1e-9 px
where it converges. A pixel is *reached* if its ray reprojects within 1e-3 px and lies inside the
radius where the model first folds back (:func:`fold_radius`): beyond it a distortion polynomial
describes no real lens.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from companion.calibration import CameraCalibration

NEWTON_ITERATIONS = 8
CONVERGED_PX = 1e-9  # Newton's method stops for a pixel whose ray reprojects this close, px
REACHED_PX = 1e-3  # a pixel whose ray reprojects further away than this (px) is outside the lens model


def check_lens(calibration: CameraCalibration) -> CameraCalibration:
    """``calibration``, if the renderer models its lens; ValueError if not (the tilted-sensor model)."""
    if calibration.model == "plumb_bob" and calibration.D.size > 12:
        raise ValueError("the tilted-sensor distortion model (14 coefficients) is not simulated: give at most 12")
    return calibration


def project(calibration: CameraCalibration, xy: np.ndarray) -> np.ndarray:
    """(N, 2) pixels (u, v) of the optical-frame rays (x, y, 1) for (N, 2) normalised ``xy``."""
    x, y = xy[:, 0], xy[:, 1]
    D = np.zeros(12)
    D[:calibration.D.size] = calibration.D
    r2 = x * x + y * y
    if calibration.model == "equidistant":
        r = np.sqrt(r2)
        theta = np.arctan(r)
        t2 = theta * theta
        theta_d = theta * (1 + t2 * (D[0] + t2 * (D[1] + t2 * (D[2] + t2 * D[3]))))
        scale = np.divide(theta_d, r, out=np.ones_like(r), where=r > 0)
        xd, yd = x * scale, y * scale
    else:
        k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = D
        radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + r2 * (s1 + s2 * r2)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + r2 * (s3 + s4 * r2)
    K = calibration.K
    return np.column_stack((K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]))


@np.errstate(all="ignore")
def unproject(calibration: CameraCalibration, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(normalised xy (N, 2), reached (N,) bool) of (N, 2) pixels (u, v): the ray (x, y, 1) that
    :func:`project` maps onto each pixel, where the lens model reaches it (within 1e-3 px, inside
    :func:`fold_radius`)."""
    check_lens(calibration)
    start = pixels.reshape(-1, 1, 2).astype(np.float64)
    if calibration.model == "equidistant":
        xy = cv2.fisheye.undistortPoints(start, calibration.K, calibration.D).reshape(-1, 2)
    else:
        xy = cv2.undistortPoints(start, calibration.K, calibration.D).reshape(-1, 2)
    todo = np.arange(len(xy))  # points not converged yet
    eps = 1e-7
    for _ in range(NEWTON_ITERATIONS):  # points beyond the model's reach diverge (inf, nan): not reached
        p = project(calibration, xy[todo])
        moving = np.abs(p - pixels[todo]).max(axis=1) > CONVERGED_PX
        todo, p = todo[moving], p[moving]
        if todo.size == 0:
            break
        ju = (project(calibration, xy[todo] + [eps, 0.0]) - p) / eps  # d(u, v)/dx
        jv = (project(calibration, xy[todo] + [0.0, eps]) - p) / eps  # d(u, v)/dy
        det = ju[:, 0] * jv[:, 1] - jv[:, 0] * ju[:, 1]
        ru, rv = (p - pixels[todo]).T
        xy[todo] -= np.column_stack((jv[:, 1] * ru - jv[:, 0] * rv, ju[:, 0] * rv - ju[:, 1] * ru)) / det[:, None]
    reached = ((np.linalg.norm(project(calibration, xy) - pixels, axis=1) < REACHED_PX)
               & (np.hypot(xy[:, 0], xy[:, 1]) < fold_radius(calibration)))
    return xy, reached


def fold_radius(calibration: CameraCalibration) -> float:
    """The normalised radius (tan of the angle off the optical axis) where the lens model first
    folds back (the projected point stops moving away from the centre) in any direction; inf if
    it never does before 89.9 deg. Rays beyond it are not the camera's: its model is not valid there."""
    r = np.tan(np.radians(np.linspace(0.0, 89.9, 4000)))
    centre = project(calibration, np.zeros((1, 2)))
    radius = np.inf
    for a in np.linspace(0.0, 2 * np.pi, 16, endpoint=False):
        distance = np.linalg.norm(project(calibration, np.outer(r, (np.cos(a), np.sin(a)))) - centre, axis=1)
        folds = np.flatnonzero(np.diff(distance) <= 0)
        if folds.size:
            radius = min(radius, float(r[folds[0]]))
    return radius


@dataclass(frozen=True)
class PixelRays:
    """The ray through every pixel centre of one calibration, in the optical frame."""

    x: np.ndarray  # (H, W) float32: the ray is (x, y, z), normalised image coordinates
    y: np.ndarray
    z: np.ndarray  # (H, W) float32: 1, or 0 where the lens model does not reach the pixel (a zero ray meets nothing)
    reached: np.ndarray  # (H, W) bool: z == 1
    footprint_k: np.ndarray  # (H, W) float32: |ray|^2 times the pixel's angular size, rad
    min_angle_rad: float  # the smallest angular pixel size
    row_spans: np.ndarray  # (H, 4) min x, max x, min y, max y of each row's reached rays (empty: inf, -inf)
    col_spans: np.ndarray  # (W, 4) the same for each column

    @classmethod
    def make(cls, calibration: CameraCalibration) -> PixelRays:
        h, w = calibration.height, calibration.width
        v, u = np.mgrid[0:h, 0:w]
        xy, reached = unproject(calibration, np.column_stack((u.ravel(), v.ravel())).astype(np.float64))
        x, y = (np.where(reached, c, 0.0).reshape(h, w) for c in xy.T)
        norm2 = x * x + y * y + 1.0
        unit = np.stack((x, y, np.ones_like(x))) / np.sqrt(norm2)
        angle = np.maximum(*(np.linalg.norm(np.gradient(unit, axis=a), axis=0) for a in (1, 2)))
        reached = reached.reshape(h, w)
        if not reached.any():
            raise ValueError("the lens model reaches no pixel of the image")

        def spans(axis: int) -> np.ndarray:  # min x, max x, min y, max y of the reached rays along ``axis``
            return np.stack([f(c, axis=axis, where=reached, initial=empty) for c in (x, y)
                             for f, empty in ((np.min, np.inf), (np.max, -np.inf))], axis=1)

        return cls(x.astype(np.float32), y.astype(np.float32), reached.astype(np.float32), reached,
                   (norm2 * angle).astype(np.float32), float(angle[reached].min()), spans(1), spans(0))
