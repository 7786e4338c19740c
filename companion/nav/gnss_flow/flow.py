"""Optic flow for GNSS + vision attitude (Roberts, Walker and O'Shea 2005, issue 15;
../shared/seeds/gnss-optic-flow-attitude.txt): grid flow, derotation, focus of expansion, depth
and height above ground. Plain numpy/OpenCV, no I/O.

Frames and units:

- pixels (u, v) = (column, row) of the camera's image (companion/calibration.py);
- the camera's optical frame: x right, y down in the image, z forward along the optical axis;
  normalised image coordinates (x, y) = (X/Z, Y/Z) of a point (X, Y, Z) in that frame;
- body FRD (x forward, y right, z down); a camera mount is the rotation ``cam_to_body``
  (``v_body = cam_to_body @ v_cam``; for the seed's camera along body x with the image upright
  it is ``drivers.mount.OPTICAL_TO_SENSOR``);
- a level frame (NED or any frame whose third axis points down): ``cam_to_level``;
- flows are displacements over one frame interval ``dt`` (seconds) from the earlier image to the
  later one, in pixels or normalised units; rates are rad/s; speeds m/s; depths and heights m.

The motion field (derived here; the seed gives none). A static point P seen from a camera that
moves with velocity T and turns with angular velocity w (both in the camera frame) moves in the
camera frame as dP/dt = -T - w x P, so for normalised coordinates

    dx/dt = (x Tz - Tx) / Z + x y wx - (1 + x^2) wy + y wz
    dy/dt = (y Tz - Ty) / Z + (1 + y^2) wx - x y wy - x wz

(the textbook form, its signs checked here for the right-handed optical frame). The rotational
part does not depend on depth; :func:`derotate` removes it exactly for a finite turn at constant body rates.
Every translational flow vector then lies on the line from the focus of expansion (FOE)
e = (Tx/Tz, Ty/Tz) through its point, exactly so for a finite translation.

The body rates are inputs here. The seed's eq. 8 (body rates from the pseudo Euler rates) is
garbled in the text (its rate vector reads phi-dot twice, and its matrix is not the usual
Euler-rate transform p = phi' - psi' sin(theta), ...) and is not used by this module.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from companion.calibration import CameraCalibration

LK_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 10, 0.03)  # at most 10 iterations, or a step < 0.03 px
MIN_DIRECTION_SIGMA = 1e-3  # floor of a flow vector's modelled direction noise, rad (where its measured flow is ~0)
LK_MIN_EIGEN = 1e-3  # OpenCV's minEigThreshold (see grid_flow)


@dataclass(frozen=True)
class GridFlow:
    """Pyramidal Lucas-Kanade flow on a regular grid of the earlier image."""

    points_px: np.ndarray  # (N, 2) grid points (u, v) in the earlier image, pixels
    flows_px: np.ndarray  # (N, 2) displacement to the later image, pixels (NaN where not tracked)
    valid: np.ndarray  # (N,) bool: tracked both ways, forward-backward error below the threshold
    fb_error_px: np.ndarray  # (N,) |point - backward(forward(point))|, pixels (inf where not tracked)


def grid_flow(prev: np.ndarray, curr: np.ndarray, grid: tuple[int, int] = (45, 45), win: int = 16,
              levels: int = 3, fb_max_px: float = 0.5, min_eigen: float = LK_MIN_EIGEN,
              margin_px: float = 10.0) -> GridFlow:
    """Flow from ``prev`` to ``curr`` (grey uint8 images, same size) at ``grid`` = (columns, rows)
    points spread evenly over the image, ``margin_px`` pixels in from its edges: forward, then the
    forward-tracked points backward, each by ``cv2.calcOpticalFlowPyrLK`` (``win`` x ``win``
    pixel window, ``levels`` pyramid levels above the image, at most LK_CRITERIA iterations per
    level); valid where both track and the forward-backward error is below ``fb_max_px`` pixels
    (occluded or changed points do not come back to where they started).

    Points whose window has too little texture are not tracked: ``min_eigen`` is OpenCV's
    ``minEigThreshold``, the smallest eigenvalue of the window's gradient matrix over its pixel
    count (2 grey levels of pixel noise on a blank sky give about 4e-4; the textured ground of
    bench_flow.py about 1e-3 at its 1st percentile, 1.6e-2 at its median). Otherwise such points
    cost the full iterations at every level, both ways. OpenCV's tracker is fastest for window
    widths that are a multiple of 8 px: 16 costs as much as 12 and half as much as 15. The
    pyramids cannot be built once and shared between the passes from Python (OpenCV's binding
    takes no pyramid, opencv/opencv#4777); building them is about 0.3 ms of a call.
    """
    if prev.dtype != np.uint8 or curr.dtype != np.uint8 or prev.ndim != 2 or prev.shape != curr.shape:
        raise ValueError(f"need two grey uint8 images of one size, got {prev.dtype}{prev.shape} "
                         f"and {curr.dtype}{curr.shape}")
    height, width = prev.shape
    us = np.linspace(margin_px, width - 1 - margin_px, grid[0])
    vs = np.linspace(margin_px, height - 1 - margin_px, grid[1])
    points = np.stack(np.meshgrid(us, vs), axis=-1).reshape(-1, 1, 2).astype(np.float32)
    lk = {"winSize": (win, win), "maxLevel": levels, "criteria": LK_CRITERIA, "minEigThreshold": min_eigen}
    forward, st_f, _ = cv2.calcOpticalFlowPyrLK(prev, curr, points, None, **lk)
    tracked = st_f.ravel() == 1
    back = points.copy()
    if tracked.any():
        back[tracked], st_b, _ = cv2.calcOpticalFlowPyrLK(curr, prev, forward[tracked], None, **lk)
        tracked[tracked] = st_b.ravel() == 1
    fb = np.where(tracked, np.linalg.norm((back - points).reshape(-1, 2), axis=1), np.inf)
    flows = np.where(tracked[:, None], (forward - points).reshape(-1, 2).astype(np.float64), np.nan)
    return GridFlow(points.reshape(-1, 2).astype(np.float64), flows, fb < fb_max_px, fb)


def normalised_flow(points_px: np.ndarray, flows_px: np.ndarray,
                    calibration: CameraCalibration) -> tuple[np.ndarray, np.ndarray]:
    """(points, flows) in normalised image coordinates, (N, 2) each: both ends of every pixel
    flow vector undistorted with ``calibration`` (lens distortion removed)."""
    start = calibration.undistort_points(points_px)
    end = calibration.undistort_points(np.asarray(points_px) + np.asarray(flows_px))
    return start, end - start


def derotate(points_n: np.ndarray, flows_n: np.ndarray, rates: np.ndarray, dt: float,
             cam_to_body: np.ndarray | None = None) -> np.ndarray:
    """The translational flow, (N, 2) normalised: the flow ``flows_n`` from ``points_n`` (N, 2
    each, normalised) with the turn of ``rates`` (rad/s, (3,), constant over ``dt`` seconds)
    removed. ``rates`` are in the camera's optical frame, or in body FRD (p, q, r) when
    ``cam_to_body`` (3x3, ``v_body = cam_to_body @ v_cam``) is given.

    Each later point's ray is turned back by the rotation exp([w] dt) into the earlier camera's
    orientation, so the result is the flow a camera with the earlier attitude at the later
    position would see: exact for constant rates, and to first order in w dt it subtracts the
    motion-field terms of the module docstring (the tests check the signs against them). The
    first-order subtraction alone leaves a residual of order w dt times the flow, which on the
    distant points' small flows turns their directions by degrees.
    """
    w = np.asarray(rates, dtype=float)
    if cam_to_body is not None:
        w = np.asarray(cam_to_body, dtype=float).T @ w
    turn, _ = cv2.Rodrigues(w * dt)  # v_earlier_cam = turn @ v_later_cam
    points = np.asarray(points_n, dtype=float)
    later = np.column_stack((points + np.asarray(flows_n, dtype=float), np.ones(len(points)))) @ turn.T
    return later[:, :2] / later[:, 2:] - points


@dataclass(frozen=True)
class FocusOfExpansion:
    """Where the translational flow lines meet, and the direction of travel it gives."""

    point_n: np.ndarray  # (2,) the FOE (Tx/Tz, Ty/Tz), normalised image coordinates
    direction_cam: np.ndarray  # (3,) unit direction of travel T/|T| in the optical frame
    covariance_n: np.ndarray  # (2, 2) covariance of point_n, normalised units^2 (~rad^2 near the axis)
    inlier_fraction: float  # inliers / flows used (those at least min_flow long)
    inliers: np.ndarray  # (N,) bool over the input flows
    rms_angle_deg: float  # RMS angle between the inliers' flows and their lines from the FOE, degrees
    # (N,) 1-sigma of each flow's sine to its line from the FOE (its noise model scaled by the fit's
    # residuals), inf for flows not used
    sine_sigma: np.ndarray


def focus_of_expansion(points_n: np.ndarray, flows_n: np.ndarray, *, noise_n: np.ndarray | None = None,
                       ransac: bool = True, threshold_deg: float = 5.0, threshold_sigmas: float = 3.5,
                       max_threshold_deg: float = 45.0, iterations: int = 200, min_flow: float = 2e-4,
                       min_inliers: int = 20, min_inlier_fraction: float = 0.5, max_off_axis_deg: float = 80.0,
                       rng: np.random.Generator | None = None) -> FocusOfExpansion | None:
    """The FOE of translational flow (N, 2) at ``points_n`` (N, 2), normalised coordinates.

    Each flow vector at least ``min_flow`` long (normalised units; shorter ones have no reliable
    direction) defines a line through its point. ``noise_n`` (N,): each flow's 1-sigma noise,
    normalised units (isotropic: a tracker's pixel noise, or an angle noise times the measured
    flow's length before derotation), so its direction's noise is ``noise_n / |flow|``: a flow
    agrees with a candidate FOE within ``threshold_sigmas`` of that (at most ``max_threshold_deg``)
    and weighs by its inverse square (that noise at least MIN_DIRECTION_SIGMA: no vector is exact);
    None: every flow alike, agreeing within ``threshold_deg``. With ``ransac``, pairs of lines are
    intersected ``iterations`` times and the candidate with the most agreeing flows (pointing away
    from it, or all towards it) wins; without, every line is an inlier. Then weighted least squares
    on the inliers in the angle form: minimise sum(w_i ((n_i . (e - p_i)) / |e - p_i|)^2) (n_i the
    unit normal of flow i, so each term is the sine of the angle between the flow and its line from
    e), solved as perpendicular distances reweighted by 1/|e - p_i|^2; with RANSAC the inliers are
    then re-selected around the fit and refitted once. The seed's "weighted line intersection
    voting" is not specified further; this replaces it.

    The direction of travel is (e, 1) normalised, negated when the flow converges on e (moving
    backwards). None when fewer than ``min_inliers`` flows (or ``min_inlier_fraction`` of those
    used) agree, or the lines are (nearly) parallel, or the FOE is more than ``max_off_axis_deg``
    from the optical axis: travel (nearly) across the view, its FOE at or near infinity.
    ``rng`` draws the RANSAC pairs (seeded 0 when None: the same flow gives the same answer).
    """
    points = np.asarray(points_n, dtype=float)
    flows = np.asarray(flows_n, dtype=float)
    length = np.linalg.norm(flows, axis=1)
    used = np.isfinite(length) & (length >= min_flow)
    if used.sum() < min_inliers:
        return None
    unit = np.zeros_like(flows)
    unit[used] = flows[used] / length[used, None]
    normals = np.column_stack((-unit[:, 1], unit[:, 0]))
    if noise_n is None:
        sigma = np.ones(len(points))
        cos_thr = np.full(len(points), math.cos(math.radians(threshold_deg)))
    else:
        sigma = np.where(used, np.maximum(np.asarray(noise_n, dtype=float) / np.where(used, length, 1.0),
                                          MIN_DIRECTION_SIGMA), np.inf)
        cos_thr = np.cos(np.minimum(np.arcsin(np.minimum(threshold_sigmas * sigma, 1.0)),
                                    math.radians(max_threshold_deg)))
    weights = np.where(used, 1.0 / np.maximum(sigma, 1e-12) ** 2, 0.0)
    if ransac:
        candidate = _ransac_candidate(points, unit, normals, used, cos_thr, iterations,
                                      rng if rng is not None else np.random.default_rng(0))
        if candidate is None:
            return None
        inliers = _agreeing(points, unit, candidate, cos_thr) & used
    else:
        inliers = used.copy()
    fit = _least_squares(points[inliers], normals[inliers], weights[inliers])
    if fit is None:
        return None
    if ransac:
        inliers = _agreeing(points, unit, fit[0], cos_thr) & used
        fit = _least_squares(points[inliers], normals[inliers], weights[inliers])
        if fit is None:
            return None
    foe, cov, rms, scale = fit
    if (inliers.sum() < max(min_inliers, min_inlier_fraction * used.sum())
            or math.hypot(foe[0], foe[1]) > math.tan(math.radians(max_off_axis_deg))):
        return None
    away = np.einsum("ij,ij->i", points[inliers] - foe, unit[inliers])
    sign = 1.0 if np.sum(away > 0) >= np.sum(away < 0) else -1.0
    direction = sign * np.append(foe, 1.0) / math.hypot(foe[0], foe[1], 1.0)
    return FocusOfExpansion(foe, direction, cov, float(inliers.sum() / used.sum()), inliers,
                            math.degrees(math.asin(min(1.0, rms))), np.where(used, sigma * scale, np.inf))


def _agreeing(points: np.ndarray, unit: np.ndarray, foe: np.ndarray, cos_thr: np.ndarray) -> np.ndarray:
    """(N,) bool: flows within their threshold (``cos_thr`` (N,), cosines) of their line from
    ``foe``, all pointing away from it or all towards it (whichever more do)."""
    ray = points - foe
    cos = np.einsum("ij,ij->i", ray, unit) / np.maximum(np.linalg.norm(ray, axis=1), 1e-12)
    away, towards = cos > cos_thr, cos < -cos_thr
    return away if away.sum() >= towards.sum() else towards


def _ransac_candidate(points: np.ndarray, unit: np.ndarray, normals: np.ndarray, used: np.ndarray,
                      cos_thr: np.ndarray, iterations: int, rng: np.random.Generator) -> np.ndarray | None:
    """The intersection of two random flow lines that most flows agree with, or None."""
    idx = np.flatnonzero(used)
    pairs = idx[rng.integers(0, len(idx), size=(iterations, 2))]
    n1, n2 = normals[pairs[:, 0]], normals[pairs[:, 1]]
    det = n1[:, 0] * n2[:, 1] - n1[:, 1] * n2[:, 0]  # sine of the angle between the two lines
    ok = np.abs(det) > math.sin(math.radians(2.0))
    if not ok.any():
        return None
    c1 = np.einsum("ij,ij->i", n1, points[pairs[:, 0]])[ok]
    c2 = np.einsum("ij,ij->i", n2, points[pairs[:, 1]])[ok]
    n1, n2, det = n1[ok], n2[ok], det[ok]
    cands = np.column_stack(((c1 * n2[:, 1] - c2 * n1[:, 1]) / det, (n1[:, 0] * c2 - n2[:, 0] * c1) / det))
    ray = points[used][None, :, :] - cands[:, None, :]  # (K, M, 2)
    cos = np.einsum("kmj,mj->km", ray, unit[used]) / np.maximum(np.linalg.norm(ray, axis=2), 1e-12)
    thr = cos_thr[used]
    votes = np.maximum((cos > thr).sum(axis=1), (cos < -thr).sum(axis=1))
    return cands[int(np.argmax(votes))]


def _least_squares(points: np.ndarray, normals: np.ndarray, prior_weights: np.ndarray,
                   sweeps: int = 4) -> tuple[np.ndarray, np.ndarray, float, float] | None:
    """(FOE, its covariance, RMS sine residual, RMS of the sines in units of their modelled sigma)
    minimising the angle form weighted by ``prior_weights`` (1 / each sine's modelled variance, see
    :func:`focus_of_expansion`) by reweighted perpendicular distances; None if singular."""
    if len(points) < 3:
        return None
    c = np.einsum("ij,ij->i", normals, points)
    weights = prior_weights
    foe = np.zeros(2)
    for _ in range(sweeps):
        A = (normals * weights[:, None]).T @ normals
        if np.linalg.cond(A) > 1e8:
            return None
        foe = np.linalg.solve(A, (normals * weights[:, None]).T @ c)
        weights = prior_weights / np.maximum(np.sum((points - foe) ** 2, axis=1), 1e-6)
    A = (normals * weights[:, None]).T @ normals
    residual = (normals @ foe - c) * np.sqrt(weights)
    var = float(np.sum(residual ** 2) / max(len(points) - 2, 1))
    sines = residual / np.sqrt(prior_weights)
    return foe, var * np.linalg.inv(A), math.sqrt(float(np.mean(sines ** 2))), math.sqrt(var)


def velocity_offsets(direction_cam: np.ndarray, cam_to_body: np.ndarray) -> tuple[float, float]:
    """(pitch offset, yaw offset), radians, of the direction of travel (unit, optical frame) from
    body x: ``atan2(v_z, v_x)`` (the angle of attack when the air is still: positive with the
    travel below the nose) and ``asin(v_y)`` (sideslip / drift angle: positive with the travel to
    the right), v the direction in body FRD. Relative to the ground, so wind is included (seed,
    "Euler Angle Calculation")."""
    v = np.asarray(cam_to_body, dtype=float) @ np.asarray(direction_cam, dtype=float)
    return math.atan2(v[2], v[0]), math.asin(max(-1.0, min(1.0, v[1])))


def depths(points_n: np.ndarray, flows_n: np.ndarray, direction_cam: np.ndarray, speed_mps: float,
           dt: float, min_flow_factor: float = 0.02) -> np.ndarray:
    """Depth Z (metres along the optical axis), (N,), of each point from its translational flow.

    With travel direction t (unit, optical frame) and distance s = ``speed_mps`` * ``dt`` (GNSS
    speed, metres) the translational flow is (x tz - tx, y tz - ty) * s / Z (module docstring);
    Z is solved per point by least squares over both components. For a finite translation this is
    exact with Z the depth from the later position (along the optical axis of :func:`derotate`'s
    camera: earlier attitude). This is the seed's eqs. 9-11 (|D_LOS| = |V|
    sin(gamma) / Omega, angular flow on a sphere), re-derived for normalised image coordinates:
    the range along the ray is Z * sqrt(1 + x^2 + y^2). NaN where the flow is unobservable (point
    within ``min_flow_factor`` normalised units of the FOE, i.e. |(x tz - tx, y tz - ty)| below
    it) or points the wrong way (Z <= 0) or is missing.
    """
    t = np.asarray(direction_cam, dtype=float)
    points = np.asarray(points_n, dtype=float)
    a = points * t[2] - t[:2]
    aa = np.sum(a * a, axis=1)
    k = np.einsum("ij,ij->i", a, np.asarray(flows_n, dtype=float)) / np.maximum(aa, 1e-300)
    ok = (aa >= min_flow_factor ** 2) & (k > 0) & np.isfinite(k)
    return np.where(ok, speed_mps * dt / np.where(ok, k, 1.0), np.nan)


def height_above_ground(points_n: np.ndarray, depth_m: np.ndarray, cam_to_level: np.ndarray,
                        min_depression_deg: float = 5.0) -> float | None:
    """Height above flat ground, metres: the median over points at least ``min_depression_deg``
    below the horizon of Z * (down component of the ray (x, y, 1) in the level frame), which is
    the seed's eq. 12, AGL = |D_LOS| sin(lambda) (lambda the ray's angle below the horizon), since
    |D_LOS| = Z |(x, y, 1)|. ``points_n`` (N, 2) normalised and ``depth_m`` (N,) (NaN ignored)
    and the attitude ``cam_to_level`` (3x3, ``v_level = cam_to_level @ v_cam``, third axis down;
    heading does not matter) must be of one camera: for :func:`depths` of :func:`derotate`'s
    flow that is the camera at the later position with the earlier attitude, so pass points +
    translational flows and the earlier attitude. None without such a point."""
    rays = np.column_stack((np.asarray(points_n, dtype=float), np.ones(len(points_n))))
    down = rays @ np.asarray(cam_to_level, dtype=float)[2]
    sin_dep = down / np.linalg.norm(rays, axis=1)
    ok = (sin_dep >= math.sin(math.radians(min_depression_deg))) & np.isfinite(depth_m)
    if not ok.any():
        return None
    return float(np.median(np.asarray(depth_m)[ok] * down[ok]))
