"""The pose from three laser dots on the floor (Kara Mohamed, Patra and Lanzon, sections III-IV).

Frames and units: world LOCAL_NED (x north, y east, z down, metres; the floor is the plane
z = 0), body FRD (x forward, y right, z down, metres); a rotation is body FRD -> NED
(``v_ned = R @ v_body``); Euler angles are ZYX (roll, pitch, yaw) radians (companion/frames.py).
Floor dots are (3, 2) arrays of [north, east] metres, row i = the dot of beam i of the
:class:`~companion.laser_beams.BeamRig`; a beam's length is metres from its own origin.

Two solvers:

- ``closed_form``: the seed's eqs. 10-14 for beams at exactly 90 degrees from one point (the
  rig is taken as its nearest ideal 90-degree rig even when it is not: the uncalibrated
  comparison) and the attitude from the beam matrices (eqs. 15-28, :func:`attitude_from_beams`);
- ``general``: Grunert's P3P (the beam directions are bearing vectors, the dots world points)
  for any angles, each solution refined by Newton's method with the calibrated beam origins and
  directions, then the plausible one selected (:func:`select_candidate`).

At exactly 90 degrees Grunert's quartic is a perfect square, ``((k-1) v^2 + k+1)^2``: its two
roots are double and come out of a numeric root finder with a small imaginary part, and the
textbook back-substitution for the second length divides by ``cos(gamma) - v cos(alpha)`` = 0.
That is why general P3P solvers fail on many poses at 90 degrees (REFERENCE.md). Here roots
with a small imaginary part are kept (their real part), the second length comes from the
cosine rule of beams 1-2 instead of the division, and Newton's method polishes the result.

Also: the floor plane seen from the body (structured light, no markers: height, roll and pitch
from the beam lengths), covariances by numeric Jacobians, and the seed's field-of-view
constraint (eqs. 30-41) with a general check for a given camera.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from companion.frames import euler_from_rotation
from companion.laser_beams import BEAMS, BeamRig

Method = Literal["closed_form", "general"]

RIGHT_ANGLE_TOLERANCE_DEG = 5.0  # the closed form refuses a rig whose beams are further from 90 deg
SINGULAR_M2 = 1e-12  # |det A| of eq. 13 below this (m^2): the dots are collinear
ROOT_IMAG_TOLERANCE = 1e-4  # a quartic root with |imag| <= this * (1 + |real|) counts as real
NEWTON_ITERATIONS = 20
NEWTON_DONE_M = 1e-12  # Newton stops when every dot coordinate misses by less, m
CONVERGED_M = 1e-6  # a refined P3P candidate whose dots miss by more (m) is not a solution
SAME_POSE = 1e-6  # two candidates closer than this (m and rad) are one
AMBIGUOUS_RESIDUAL_M = 1e-3  # without a prior, two survivors whose residuals differ by less are equally good
JACOBIAN_STEP_M = 1e-3  # central-difference step of the covariances, m
FOV_AZIMUTH_STEP_DEG = 30.0  # tilt directions sampled by fov_problems


@dataclass(frozen=True, eq=False)
class PoseCandidate:
    """One pose that explains the dots."""

    rotation: np.ndarray  # (3, 3) body FRD -> NED
    position_ned: np.ndarray  # (3,) body origin, m
    lengths: np.ndarray  # (3,) beam i's length from its origin to its dot, m
    residual_m: float  # largest distance between a dot and where this pose puts it, m


@dataclass(frozen=True, eq=False)
class PoseSolution:
    """The selected pose and how it was found."""

    rotation: np.ndarray  # (3, 3) body FRD -> NED
    position_ned: np.ndarray  # (3,) body origin, m
    lengths: np.ndarray  # (3,) beam lengths, m
    euler_rad: np.ndarray  # (3,) roll, pitch, yaw (ZYX of body -> NED), rad
    candidates: list[PoseCandidate]  # every solution of the dots before selection
    cross_check_deg: float  # beam-matrix attitude vs the Kabsch alignment of the same beams, deg
    reason: str  # why this candidate was chosen


# --- small helpers (leading batch dimensions allowed where the shapes say "...") ----------------

def floor_points(dots: np.ndarray) -> np.ndarray:
    """(..., 3, 3) NED points (m) of (..., 3, 2) floor dots [north, east] (m): z = 0."""
    d = np.asarray(dots, dtype=float)
    return np.concatenate((d, np.zeros_like(d[..., :1])), axis=-1)


def dots_in_body(rig: BeamRig, lengths: np.ndarray) -> np.ndarray:
    """(..., 3, 3) body FRD points (m) of the dots, ``origin_i + l_i * direction_i``, for
    (..., 3) beam lengths (m)."""
    return rig.origins + np.asarray(lengths, dtype=float)[..., None] * rig.directions


def rotation_angle(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (rad) of the rotation between two rotation matrices, from ``|a - b|_F = 2 sqrt(2)
    sin(angle / 2)`` (accurate for small angles, unlike the arccosine of the trace)."""
    return 2.0 * math.asin(min(1.0, float(np.linalg.norm(a - b)) / (2.0 * math.sqrt(2.0))))


def tilt_rad(rotation: np.ndarray) -> float:
    """Angle (rad) between body z (down) and NED down for a rotation body FRD -> NED."""
    return math.acos(max(-1.0, min(1.0, float(rotation[2, 2]))))


def _proper(u: np.ndarray, vt: np.ndarray) -> np.ndarray:
    """``u diag(1, 1, +-1) vt``, the sign making the (..., 3, 3) product a rotation (det +1)."""
    fix = np.ones(u.shape[:-1])
    fix[..., 2] = np.where(np.linalg.det(u @ vt) < 0.0, -1.0, 1.0)
    return (u * fix[..., None, :]) @ vt


def nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """The rotation (det +1) nearest to a (..., 3, 3) matrix in the Frobenius norm (SVD)."""
    u, _, vt = np.linalg.svd(matrix)
    return _proper(u, vt)


def kabsch(body_points: np.ndarray, world_points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rigid motion (rotation body -> world (..., 3, 3), translation m (..., 3)) that best maps
    (..., N, 3) body points onto (..., N, 3) world points (least squares, Kabsch/Horn):
    ``world ~ t + R @ body``."""
    cb, cw = body_points.mean(axis=-2), world_points.mean(axis=-2)
    h = np.swapaxes(body_points - cb[..., None, :], -1, -2) @ (world_points - cw[..., None, :])
    u, _, vt = np.linalg.svd(h)
    rotation = _proper(np.swapaxes(vt, -1, -2), np.swapaxes(u, -1, -2))
    return rotation, cw - (rotation @ cb[..., None])[..., 0]


def _skew_rows(v: np.ndarray) -> np.ndarray:
    """(N, 3, 3) cross-product matrices of (N, 3) vectors: ``skew(v) @ x = v x x``."""
    s = np.zeros((len(v), 3, 3))
    s[:, 0, 1], s[:, 0, 2], s[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    return s - s.transpose(0, 2, 1)


def _exp_rotations(w: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices of (N, 3) rotation vectors (rad), Rodrigues' formula."""
    theta = np.linalg.norm(w, axis=1)
    small = theta < 1e-8
    t = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta ** 2 / 6.0, np.sin(t) / t)
    b = np.where(small, 0.5 - theta ** 2 / 24.0, (1.0 - np.cos(t)) / t ** 2)
    k = _skew_rows(w)
    return np.eye(3) + a[:, None, None] * k + b[:, None, None] * (k @ k)


def _candidate(rig: BeamRig, dots: np.ndarray, rotation: np.ndarray, position_ned: np.ndarray,
               lengths: np.ndarray) -> PoseCandidate:
    """A candidate with its residual: the largest distance (m) between a dot and its beam's end."""
    ends = position_ned + dots_in_body(rig, lengths) @ rotation.T
    residual = float(np.linalg.norm(ends - floor_points(dots), axis=1).max())
    return PoseCandidate(rotation, position_ned, lengths, residual)


# --- the seed's closed form (alpha = 90 deg) --------------------------------------------------

def closed_form_90(dots: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The seed's eqs. 10-14 for three beams at exactly 90 degrees from one origin.

    ``dots`` (3, 2) floor [north, east] m. Returns ((3,) beam lengths m, (3,) NED position m of
    the beams' common origin), or None when a square root's argument is not positive (no real
    solution: the dots cannot come from a 90-degree rig) or A of eq. 13 is singular (collinear
    dots). The seed's labelling: a1 = |d1 d2|, a2 = |d2 d3|, a3 = |d1 d3|. Lengths by the cosine
    rule (eqs. 10-12), north and east from the 2x2 system of eq. 13 (Cramer's rule), down from
    eq. 14 (negative: above the floor) averaged over the three dots instead of the seed's dot 1
    only (the same on exact dots, less noisy on real ones).
    """
    (x1, y1), (x2, y2), (x3, y3) = np.asarray(dots, dtype=float).reshape(BEAMS, 2).tolist()
    a1, a2, a3 = (x1 - x2) ** 2 + (y1 - y2) ** 2, (x2 - x3) ** 2 + (y2 - y3) ** 2, (x1 - x3) ** 2 + (y1 - y3) ** 2
    squares = ((a1 - a2 + a3) / 2.0, (a1 + a2 - a3) / 2.0, (-a1 + a2 + a3) / 2.0)
    det = (x2 - x1) * (y3 - y2) - (y2 - y1) * (x3 - x2)  # of A = [[x2 - x1, y2 - y1], [x3 - x2, y3 - y2]]
    if min(squares) <= 0.0 or abs(det) < SINGULAR_M2:
        return None
    b1 = squares[0] - squares[1] + x2 * x2 + y2 * y2 - x1 * x1 - y1 * y1
    b2 = squares[1] - squares[2] + x3 * x3 + y3 * y3 - x2 * x2 - y2 * y2
    north = ((y3 - y2) * b1 - (y2 - y1) * b2) / (2.0 * det)
    east = ((x2 - x1) * b2 - (x3 - x2) * b1) / (2.0 * det)
    heights_sq = [s - (x - north) ** 2 - (y - east) ** 2 for s, (x, y) in zip(squares, ((x1, y1), (x2, y2), (x3, y3)))]
    if min(heights_sq) <= 0.0:
        return None
    down = -sum(math.sqrt(h) for h in heights_sq) / BEAMS
    return np.sqrt(squares), np.array([north, east, down])


def _beam_matrix_attitude(world_vectors: np.ndarray, body_vectors: np.ndarray) -> np.ndarray:
    """Nearest rotation to ``U @ inv(U_b)``; U, U_b have the (..., 3, 3) rows given as columns."""
    return nearest_rotation(np.swapaxes(np.linalg.solve(body_vectors, world_vectors), -1, -2))


def attitude_from_beams(rig: BeamRig, lengths: np.ndarray, dots: np.ndarray,
                        position_ned: np.ndarray) -> np.ndarray:
    """Rotation body FRD -> NED from the beam matrices (the seed's eqs. 15-28, re-derived).

    ``lengths`` (3,) m, ``dots`` (3, 2) floor [north, east] m, ``position_ned`` (3,) body origin m.
    Each dot is ``position + R @ (origin_i + l_i d_i)``, so with U = [dot_i - position] (world,
    columns) and U_b = [origin_i + l_i d_i] (body, columns) U = R U_b and R = U U_b^-1; the
    nearest rotation (SVD, det +1) absorbs the noise. With the seed's rig (origins at the body
    origin) U_b = [l_i d_i] = R_r^b T_s^r U^s of eq. 18, so its eq. 19 R_b^e = U (R_r^b T_s^r
    U^s)^-1 is this with calibrated directions instead of the zero-time calibration of eq. 23
    (which reads R_r^b T_s^r off a level, zero-yaw frame: U_b = U_0 (U_0^s)^-1 U^s).

    Re-derived where the text is garbled: eq. 28 is R_e^b = (R_b^e)^-1, NED -> body, and eq.
    29's matrix (first row C_theta C_psi, C_theta S_psi, -S_theta; R(X, phi) R(Y, theta)
    R(Z, psi)) is that R_e^b of the ZYX sequence, so "matching R_b^e in eq. 28" must read R_e^b.
    This function returns R_b^e (body -> NED, the transpose of eq. 29's matrix); its angles
    (roll = atan2(R32, R33), pitch = -asin(R31), yaw = atan2(R21, R11)) are
    :func:`companion.frames.euler_from_rotation`.
    """
    world = floor_points(dots) - np.asarray(position_ned, dtype=float)
    return _beam_matrix_attitude(world, dots_in_body(rig, lengths))


def _closed_form_poses(ideal: BeamRig, dots: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The seed's poses on an ideal 90-degree rig (common origin) for (K, 3, 2) dot sets: closed-form
    lengths (K, 3) and beam origin, attitude (K, 3, 3) from the beam matrices, the body origin
    (K, 3) NED m behind the beam origin. None when one of the dot sets has no solution."""
    found = [f for f in (closed_form_90(d) for d in dots) if f is not None]
    if len(found) < len(dots):
        return None
    lengths, origin_ned = (np.array(x) for x in zip(*found))
    rotation = _beam_matrix_attitude(floor_points(dots) - origin_ned[:, None, :], lengths[..., None] * ideal.directions)
    return rotation, origin_ned - rotation @ ideal.origins[0], lengths


def ideal_90_rig(rig: BeamRig) -> BeamRig:
    """The ideal 90-degree rig nearest to ``rig``: its directions made orthonormal (the polar
    factor of the direction matrix, which keeps a symmetric rig's azimuths), all from the mean
    origin (body FRD, m). ValueError when a pair of beams is more than 5 deg from 90 deg."""
    cosines = (rig.directions @ rig.directions.T)[(0, 1, 0), (1, 2, 2)]
    angles = np.degrees(np.arccos(np.clip(cosines, -1.0, 1.0)))
    if np.abs(angles - 90.0).max() > RIGHT_ANGLE_TOLERANCE_DEG:
        shown = ", ".join(f"{a:.1f}" for a in angles)
        raise ValueError(f"the closed form needs beams at 90 deg (this rig has {shown} deg): use method='general'")
    u, _, vt = np.linalg.svd(rig.directions)
    return BeamRig(np.tile(rig.origins.mean(axis=0), (BEAMS, 1)), u @ vt)


# --- general angles: Grunert's P3P and Newton refinement --------------------------------------

def _grunert_quartic(a2: float, b2: float, c2: float, ca: float, cb: float, cg: float) -> np.ndarray:
    """Coefficients (v^4 first) of Grunert's quartic in v = s3 / s1 (Haralick et al. 1994):
    squared sides a2 = |P2 P3|^2, b2 = |P1 P3|^2, c2 = |P1 P2|^2, cosines ca (bearings 2-3),
    cb (1-3), cg (1-2)."""
    k, s = (a2 - c2) / b2, (a2 + c2) / b2
    return np.array([
        (k - 1.0) ** 2 - 4.0 * c2 / b2 * ca ** 2,
        4.0 * (k * (1.0 - k) * cb - (1.0 - s) * ca * cg + 2.0 * c2 / b2 * ca ** 2 * cb),
        2.0 * (k ** 2 - 1.0 + 2.0 * k ** 2 * cb ** 2 + 2.0 * (b2 - c2) / b2 * ca ** 2
               - 4.0 * s * ca * cb * cg + 2.0 * (b2 - a2) / b2 * cg ** 2),
        4.0 * (-k * (1.0 + k) * cb + 2.0 * a2 / b2 * cg ** 2 * cb - (1.0 - s) * ca * cg),
        (1.0 + k) ** 2 - 4.0 * a2 / b2 * cg ** 2,
    ])


def _positive_real_roots(coefficients: np.ndarray) -> list[float]:
    """Distinct positive roots of a polynomial, counting those with a small imaginary part as
    real (at 90 degrees the roots are double and pick up ~1e-8 imaginary noise)."""
    roots: list[float] = []
    for r in np.roots(coefficients):
        v = float(r.real)
        if v > 0.0 and abs(r.imag) <= ROOT_IMAG_TOLERANCE * (1.0 + v) \
                and all(abs(v - w) > 1e-9 * (1.0 + v) for w in roots):
            roots.append(v)
    return roots


def _grunert_lengths(directions: np.ndarray, world: np.ndarray) -> list[np.ndarray]:
    """Grunert's P3P: the (3,) distances (m) from one centre along unit bearings ``directions``
    (rows) to the (3, 3) ``world`` points; up to four solutions, all positive.

    s2 = u s1, s3 = v s1; v from the quartic, s1 from the cosine rule of beams 1-3, u from that of
    beams 1-2 (the sign that best fits beams 2-3), never dividing by cos(gamma) - v cos(alpha)."""
    a2, b2, c2 = (float(np.sum((world[i] - world[j]) ** 2)) for i, j in ((1, 2), (0, 2), (0, 1)))
    if min(a2, b2, c2) < SINGULAR_M2:
        return []
    j1, j2, j3 = directions
    ca, cb, cg = float(j2 @ j3), float(j1 @ j3), float(j1 @ j2)
    solutions = []
    for v in _positive_real_roots(_grunert_quartic(a2, b2, c2, ca, cb, cg)):
        s1_sq = b2 / (1.0 + v * v - 2.0 * v * cb)  # the denominator is (v - cb)^2 + 1 - cb^2 > 0
        disc = cg * cg - 1.0 + c2 / s1_sq
        if disc < 0.0:
            continue
        us = [u for u in (cg + math.sqrt(disc), cg - math.sqrt(disc)) if u > 0.0]
        if us:
            u = min(us, key=lambda u: abs(s1_sq * (u * u + v * v - 2.0 * u * v * ca) - a2))
            solutions.append(math.sqrt(s1_sq) * np.array([1.0, u, v]))
    return solutions


def _solve_each(matrices: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """(K, n) solutions of K linear systems; NaN rows for the singular ones."""
    try:
        return np.linalg.solve(matrices, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:  # one singular system: the others one by one
        out = np.full(rhs.shape, np.nan)
        for k, (m, b) in enumerate(zip(matrices, rhs)):
            try:
                out[k] = np.linalg.solve(m, b)
            except np.linalg.LinAlgError:
                pass
        return out


def _beam_ends(rig: BeamRig, rotation: np.ndarray, lengths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World beam directions and beam ends relative to the body origin, (K, 3, 3) each (m), of
    (K, 3, 3) rotations body -> NED and (K, 3) lengths m."""
    directions = rig.directions @ np.swapaxes(rotation, -1, -2)
    return directions, rig.origins @ np.swapaxes(rotation, -1, -2) + lengths[..., None] * directions


def _newton(rig: BeamRig, world: np.ndarray, rotation: np.ndarray, position_ned: np.ndarray,
            lengths: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Newton's method on K problems at once: (K, 3, 3) NED dots, start rotations (K, 3, 3),
    positions (K, 3) m, lengths (K, 3) m -> the refined three and each residual (K,) m (the
    largest dot miss; NaN where the iteration failed). See :func:`refine_pose`."""
    k = len(world)
    r, p, l = rotation, position_ned, lengths
    jac = np.zeros((k, 3 * BEAMS, 3 * BEAMS))
    jac[:, :, 3:6] = np.tile(np.eye(3), (BEAMS, 1))
    length_entries = (slice(None), np.arange(3 * BEAMS), 6 + np.repeat(np.arange(BEAMS), 3))
    for _ in range(NEWTON_ITERATIONS):
        directions, ends = _beam_ends(rig, r, l)
        miss = (p[:, None, :] + ends - world).reshape(k, 3 * BEAMS)
        if not np.any(np.abs(miss).max(axis=1) >= NEWTON_DONE_M):  # all converged (or NaN: failed)
            break
        jac[:, :, 0:3] = -_skew_rows(ends.reshape(-1, 3)).reshape(k, 3 * BEAMS, 3)
        jac[length_entries] = directions.reshape(k, 3 * BEAMS)
        step = _solve_each(jac, -miss)
        r, p, l = _exp_rotations(step[:, :3]) @ r, p + step[:, 3:6], l + step[:, 6:]
    _, ends = _beam_ends(rig, r, l)
    return r, p, l, np.linalg.norm(p[:, None, :] + ends - world, axis=2).max(axis=1)


def refine_pose(rig: BeamRig, dots: np.ndarray, rotation: np.ndarray, position_ned: np.ndarray,
                lengths: np.ndarray) -> PoseCandidate:
    """Newton's method on the exactly determined system: each dot (3 coordinates, z = 0) is the
    end of its beam, ``position + R @ (origin_i + l_i d_i) = dot_i`` (9 equations) in the pose
    (a small-angle rotation update ``R <- exp(w) R`` and the NED position, m) and the three
    lengths (m): 9 unknowns. Keeping the lengths as unknowns instead of eliminating them into
    dot-to-beam-line distances makes the Jacobian square, so Gauss-Newton is Newton and converges
    quadratically from a nearby start. ``dots`` (3, 2) [north, east] m; the start: rotation body
    FRD -> NED, position (3,) m, lengths (3,) m. The candidate's residual (m; NaN when the
    Jacobian went singular) says whether it converged."""
    r, p, l, residual = _newton(rig, floor_points(dots)[None], np.asarray(rotation, dtype=float)[None],
                                np.asarray(position_ned, dtype=float)[None], np.asarray(lengths, dtype=float)[None])
    return PoseCandidate(r[0], p[0], l[0], float(residual[0]))


def _same_pose(a: PoseCandidate, b: PoseCandidate) -> bool:
    return (float(np.linalg.norm(a.position_ned - b.position_ned)) < SAME_POSE
            and rotation_angle(a.rotation, b.rotation) < SAME_POSE)


def p3p_candidates(rig: BeamRig, dots: np.ndarray) -> list[PoseCandidate]:
    """Every pose of ``rig`` (calibrated, any angles, origins anywhere) that puts its beams' ends
    on the (3, 2) floor ``dots`` [north, east] m: up to four, distinct, positive lengths.

    Grunert's P3P on the beam directions from the mean beam origin gives the lengths; Kabsch
    aligns the body points to the dots; Newton (:func:`refine_pose`) makes the result exact for
    the real origins. Candidates whose refinement does not converge (residual > 1 um) are dropped."""
    world = floor_points(dots)
    starts = _grunert_lengths(rig.directions, world)
    if not starts:
        return []
    centre = rig.origins.mean(axis=0)
    s = np.array(starts)
    rotation, position = kabsch(centre + s[..., None] * rig.directions, world)
    offsets = np.einsum("ij,ij->i", rig.origins - centre, rig.directions)  # beam origin ahead of the centre, m
    r, p, l, residual = _newton(rig, np.broadcast_to(world, (len(s), BEAMS, 3)), rotation, position, s - offsets)
    candidates: list[PoseCandidate] = []
    for k in np.flatnonzero(residual < CONVERGED_M):
        candidate = PoseCandidate(r[k], p[k], l[k], float(residual[k]))
        if not any(_same_pose(candidate, c) for c in candidates):
            candidates.append(candidate)
    return candidates


# --- selection ---------------------------------------------------------------------------------

def _implausible(candidate: PoseCandidate, origins_body: np.ndarray, max_tilt_deg: float,
                 min_height_m: float) -> str | None:
    """Why a candidate cannot be the vehicle's pose, or None."""
    if np.any(candidate.lengths <= 0.0):
        return "with a beam pointing backwards"
    origins_ned = candidate.position_ned + origins_body @ candidate.rotation.T
    if np.any(origins_ned[:, 2] >= -min_height_m):
        return f"with a beam starting less than {min_height_m:g} m above the floor"
    if tilt_rad(candidate.rotation) > math.radians(max_tilt_deg):
        return f"tilted beyond {max_tilt_deg:g} deg"
    return None


def _prior_distance(candidate: PoseCandidate, prior_rotation: np.ndarray | None,
                    previous: tuple[np.ndarray, np.ndarray] | None) -> float:
    """Distance to the priors: the attitude angle (rad) to ``prior_rotation``, plus the attitude
    angle (rad) and position distance (m) to ``previous``; a radian counts as a metre."""
    score = 0.0
    if prior_rotation is not None:
        score += rotation_angle(candidate.rotation, prior_rotation)
    if previous is not None:
        score += rotation_angle(candidate.rotation, previous[0])
        score += float(np.linalg.norm(candidate.position_ned - previous[1]))
    return score


def select_candidate(candidates: Sequence[PoseCandidate], prior_rotation: np.ndarray | None = None,
                     previous: tuple[np.ndarray, np.ndarray] | None = None, max_tilt_deg: float = 45.0,
                     min_height_m: float = 0.05, origins_body: np.ndarray | None = None) -> tuple[PoseCandidate | None, str]:
    """The candidate that is the vehicle's pose, and why (or None and why not).

    Plausible: every length positive, every beam origin (``origins_body``, (3, 3) body FRD m;
    default the body origin) at least ``min_height_m`` above the floor (NED z < -min_height_m;
    the body origin itself may rest on the floor), the tilt (body z vs NED down) within ``max_tilt_deg`` (this also
    rejects upside-down poses). Among the plausible ones: with a prior (``prior_rotation``, e.g.
    the IMU attitude body -> NED, and/or ``previous`` = (rotation, NED position m) of the last
    pose) the closest to it (:func:`_prior_distance`); without one, the smallest residual, unless
    the runner-up's residual is within 1 mm of it: then both explain the dots and nothing tells
    them apart, (None, "ambiguous ...")."""
    survivors: list[PoseCandidate] = []
    rejected: Counter[str] = Counter()
    for candidate in candidates:
        problem = _implausible(candidate, np.zeros((1, 3)) if origins_body is None else origins_body,
                               max_tilt_deg, min_height_m)
        if problem is None:
            survivors.append(candidate)
        else:
            rejected[problem] += 1
    if not survivors:
        why = ", ".join(f"{n} {problem}" for problem, n in rejected.items()) or "the dots have no solution"
        return None, f"no plausible pose among {len(candidates)} candidates: {why}"
    if prior_rotation is not None or previous is not None:
        best = min(survivors, key=lambda c: _prior_distance(c, prior_rotation, previous))
        return best, f"closest to the prior among {len(survivors)} plausible candidates"
    ranked = sorted(survivors, key=lambda c: c.residual_m)
    if len(ranked) > 1 and ranked[1].residual_m - ranked[0].residual_m < AMBIGUOUS_RESIDUAL_M:
        return None, (f"ambiguous: {len(ranked)} plausible candidates explain the dots; "
                      "give an attitude prior or the previous pose")
    return ranked[0], "the only plausible candidate" if len(ranked) == 1 else "smallest residual"


# --- the solver --------------------------------------------------------------------------------

def _cross_check_deg(rig: BeamRig, candidate: PoseCandidate, dots: np.ndarray) -> float:
    """Angle (deg) between the beam-matrix attitude and the Kabsch alignment of the same beams."""
    beams = attitude_from_beams(rig, candidate.lengths, dots, candidate.position_ned)
    aligned, _ = kabsch(dots_in_body(rig, candidate.lengths), floor_points(dots))
    return math.degrees(rotation_angle(beams, aligned))


def solve(rig: BeamRig, dots: np.ndarray, method: Method = "general", prior_rotation: np.ndarray | None = None,
          previous: tuple[np.ndarray, np.ndarray] | None = None, max_tilt_deg: float = 45.0) -> PoseSolution | None:
    """The pose (body FRD -> NED, NED position m) from (3, 2) floor ``dots`` [north, east] m.

    ``method="closed_form"``: the seed's 90-degree equations on :func:`ideal_90_rig` (calibration
    ignored: the uncalibrated comparison); ``"general"``: :func:`p3p_candidates` on the calibrated
    ``rig``. Both then :func:`select_candidate` with the priors (``prior_rotation`` body -> NED,
    ``previous`` = (rotation, NED position m)). None when no candidate is plausible or the
    choice is ambiguous (call the two steps directly to see why)."""
    dots = np.asarray(dots, dtype=float).reshape(BEAMS, 2)
    if method == "closed_form":
        solver_rig = ideal_90_rig(rig)
        found = _closed_form_poses(solver_rig, dots[None])
        candidates = [] if found is None else [_candidate(solver_rig, dots, *(x[0] for x in found))]
    elif method == "general":
        solver_rig, candidates = rig, p3p_candidates(rig, dots)
    else:
        raise ValueError(f"unknown method {method!r}: 'closed_form' or 'general'")
    best, reason = select_candidate(candidates, prior_rotation, previous, max_tilt_deg, origins_body=solver_rig.origins)
    if best is None:
        return None
    return PoseSolution(best.rotation, best.position_ned, best.lengths, np.array(euler_from_rotation(best.rotation)),
                        candidates, _cross_check_deg(solver_rig, best, dots), reason)


# --- covariances -------------------------------------------------------------------------------

def _central_jacobian(function: Callable[[np.ndarray], np.ndarray | None], x: np.ndarray, angles: slice,
                      step: float = JACOBIAN_STEP_M) -> np.ndarray | None:
    """Central-difference Jacobian at (n,) ``x`` of a ``function`` mapping (K, n) inputs to (K, m)
    outputs (None when it fails); the outputs in ``angles`` are differenced modulo 2 pi."""
    shifts = step * np.eye(x.size)
    out = function(np.concatenate((x + shifts, x - shifts)))
    if out is None or not np.all(np.isfinite(out)):
        return None
    diff = out[:x.size] - out[x.size:]
    diff[:, angles] = np.mod(diff[:, angles] + math.pi, 2.0 * math.pi) - math.pi
    return diff.T / (2.0 * step)


def _pose_states(rotation: np.ndarray, position_ned: np.ndarray) -> np.ndarray:
    """(K, 6) (north, east, down m, roll, pitch, yaw rad) of (K, 3, 3) rotations and (K, 3) positions."""
    return np.column_stack((position_ned, [euler_from_rotation(r) for r in rotation]))


def _closed_form_states(rig: BeamRig) -> Callable[[np.ndarray], np.ndarray | None]:
    """(K, 6) dot coordinates -> (K, 6) pose states of the seed's closed form on the 90-degree
    rig (None on a failure)."""
    ideal = ideal_90_rig(rig)

    def states(x: np.ndarray) -> np.ndarray | None:
        found = _closed_form_poses(ideal, x.reshape(-1, BEAMS, 2))
        return None if found is None else _pose_states(found[0], found[1])
    return states


def _euler_rates(rotation: np.ndarray) -> np.ndarray:
    """(3, 3) d(roll, pitch, yaw) / dw (rad per rad) of a small rotation ``exp(w) R`` (w in NED)
    applied to ``rotation`` (body FRD -> NED, ZYX Euler): the inverse of the matrix whose columns
    are the NED axes each Euler angle turns about, w = Rz Ry e_x droll + Rz e_y dpitch + e_z dyaw."""
    _, pitch, yaw = euler_from_rotation(rotation)
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    axes = np.array([[cy * cp, -sy, 0.0], [sy * cp, cy, 0.0], [-sp, 0.0, 1.0]])
    return np.linalg.inv(axes)


def _general_jacobian(rig: BeamRig, solution: PoseSolution) -> np.ndarray | None:
    """(6, 6) d(north, east, down, roll, pitch, yaw) / d(dot coordinates [n0, e0, n1, e1, n2, e2])
    of the general solver at ``solution`` (m per m, rad per m), by the implicit function theorem
    on Newton's square system (:func:`refine_pose`): F(x, dots) = 0 with dF/dx = J (its 9 x 9
    Jacobian in w, position and lengths) and dF/d dots = -E (E picks each dot's north and east),
    so dx/d dots = J^-1 E, exactly what central differences of Newton converge to, in one solve.
    None when J is singular (the solver fails next to these dots)."""
    directions, ends = _beam_ends(rig, solution.rotation[None], solution.lengths[None])
    jac = np.zeros((3 * BEAMS, 3 * BEAMS))
    jac[:, 0:3] = -_skew_rows(ends.reshape(-1, 3)).reshape(3 * BEAMS, 3)
    jac[:, 3:6] = np.tile(np.eye(3), (BEAMS, 1))
    jac[np.arange(3 * BEAMS), 6 + np.repeat(np.arange(BEAMS), 3)] = directions.reshape(-1)
    picks = np.zeros((3 * BEAMS, 2 * BEAMS))
    picks[3 * np.arange(BEAMS), 2 * np.arange(BEAMS)] = 1.0
    picks[3 * np.arange(BEAMS) + 1, 2 * np.arange(BEAMS) + 1] = 1.0
    try:
        sensitivity = np.linalg.solve(jac, picks)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(sensitivity)):
        return None
    return np.vstack((sensitivity[3:6], _euler_rates(solution.rotation) @ sensitivity[0:3]))


def pose_covariance(rig: BeamRig, dots: np.ndarray, dots_cov: np.ndarray, method: Method,
                    solution: PoseSolution) -> np.ndarray:
    """(6, 6) covariance of (north, east, down m, roll, pitch, yaw rad) of ``solution`` given the
    (3, 2, 2) covariances (m^2, [north, east]) of the (3, 2) ``dots``: J Sigma J^T with J the
    solver's Jacobian with respect to the six dot coordinates (the general solver: analytic,
    :func:`_general_jacobian`; the closed form: central differences, 1 mm steps). All NaN
    (MAVLink's unknown) when the solver fails next to these dots."""
    sigma = np.zeros((2 * BEAMS, 2 * BEAMS))
    for i, block in enumerate(np.asarray(dots_cov, dtype=float).reshape(BEAMS, 2, 2)):
        sigma[2 * i:2 * i + 2, 2 * i:2 * i + 2] = block
    if method == "closed_form":
        jac = _central_jacobian(_closed_form_states(rig), np.asarray(dots, dtype=float).ravel(), slice(3, 6))
    else:
        jac = _general_jacobian(rig, solution)
    return np.full((6, 6), np.nan) if jac is None else jac @ sigma @ jac.T


# --- structured light: the floor seen from the body ---------------------------------------------

def plane_from_body_points(points_body: np.ndarray, viewpoint_body: np.ndarray | None = None) -> tuple[float, float, float]:
    """Height (m) of the body origin above the floor (along NED down) and roll, pitch (rad, ZYX of
    body FRD -> NED) from three floor points in body FRD (m, rows); yaw is unobservable. The
    plane's unit normal pointing away from ``viewpoint_body`` (where the beams start, body FRD m;
    default the body origin, which must then be off the plane) is NED down in the body frame,
    i.e. the third row of R (body -> NED) = (-sin pitch, sin roll cos pitch, cos roll cos pitch).
    The height is negative for a body origin below the floor plane. ValueError when the points
    are collinear."""
    p = np.asarray(points_body, dtype=float).reshape(BEAMS, 3)
    normal = np.cross(p[1] - p[0], p[2] - p[0])
    norm = float(np.linalg.norm(normal))
    if norm < SINGULAR_M2:
        raise ValueError("the three floor points are collinear: no plane")
    normal /= norm
    height = float(normal @ p[0])
    side = height if viewpoint_body is None else float(normal @ (p[0] - np.asarray(viewpoint_body, dtype=float)))
    if side < 0.0:
        normal, height = -normal, -height
    return height, math.atan2(normal[1], normal[2]), math.asin(max(-1.0, min(1.0, -normal[0])))


def height_covariance(rig: BeamRig, lengths: np.ndarray, length_var: np.ndarray) -> np.ndarray:
    """(3, 3) covariance of (height m, roll, pitch rad) of :func:`plane_from_body_points` on the
    rig's dots at (3,) ``lengths`` m, given independent length variances (3,) m^2: J diag(var) J^T
    with J the central-difference Jacobian (1 mm steps); all NaN when a length is not finite."""
    def planes(ls: np.ndarray) -> np.ndarray:
        return np.array([plane_from_body_points(dots_in_body(rig, l), rig.origins.mean(axis=0)) for l in ls])
    jac = _central_jacobian(planes, np.asarray(lengths, dtype=float), slice(1, 3))
    return np.full((3, 3), np.nan) if jac is None else jac @ np.diag(np.asarray(length_var, dtype=float)) @ jac.T


# --- field of view (the seed's eqs. 30-41 and a general check) -----------------------------------

def seed_max_beam_angle_deg(sensor_over_focal: float) -> float:
    """The seed's eq. 40: the largest angle (deg) between beams whose dots a level camera at the
    beams' origin with sensor size s over focal length f (same units) still sees:
    cos(alpha) >= (2 - r^2/4) / (2 + r^2/2), r = s/f (checked: it follows from eqs. 35-39)."""
    r2 = sensor_over_focal ** 2
    return math.degrees(math.acos(max(-1.0, min(1.0, (2.0 - r2 / 4.0) / (2.0 + r2 / 2.0)))))


def seed_min_sensor_ratio(angle_deg: float) -> float:
    """The seed's eq. 41 (eq. 40 solved for s/f, checked): the smallest sensor size over focal
    length that sees the dots of beams ``angle_deg`` apart, 2 sqrt(2) sqrt((1 - cos a) /
    (1 + 2 cos a)); 2 sqrt(2) at 90 deg. ValueError outside (0, 120) deg."""
    if not 0.0 < angle_deg < 120.0:
        raise ValueError("the angle between beams must be within (0, 120) deg")
    c = math.cos(math.radians(angle_deg))
    return 2.0 * math.sqrt(2.0) * math.sqrt((1.0 - c) / (1.0 + 2.0 * c))


def _leaning(tilt: float, towards: float) -> np.ndarray:
    """Rotation body FRD -> NED at zero yaw of a vehicle leaning ``tilt`` rad towards the azimuth
    ``towards`` (rad from north towards east): its up axis (body -z) tilts that way, as a
    multirotor accelerating towards it (0: nose down, pi/2: right side down)."""
    return _exp_rotations(tilt * np.array([[math.sin(towards), -math.cos(towards), 0.0]]))[0]


def fov_problems(rig: BeamRig, project: Callable[[np.ndarray], np.ndarray], width: int, height: int,
                 heights_m: Sequence[float], max_tilt_deg: float, margin_px: float = 5.0) -> list[str]:
    """Where the camera loses a dot over the flight envelope, as sentences; empty when every dot
    stays in view. Sampled: each height (m) in ``heights_m``, level and leaning by half and all
    of ``max_tilt_deg`` towards every 30 deg (the vehicle's up axis tilting towards that azimuth
    at zero yaw: 0 deg nose down, 90 deg right side down; yaw does not matter on a flat floor).
    Each beam's dot in body FRD (m) goes through ``project`` ((N, 3) body points -> (N, 2)
    pixels, NaN when not imaged: the caller's camera mount and lens); a beam missing the floor,
    a NaN pixel or one within ``margin_px`` of the border of the ``width`` x ``height`` image is
    a problem."""
    tilts = sorted({max_tilt_deg / 2.0, max_tilt_deg} - {0.0})
    poses = [(0.0, 0.0)] + [(t, az) for t in tilts for az in np.arange(0.0, 360.0, FOV_AZIMUTH_STEP_DEG)]
    problems: list[str] = []
    for h in heights_m:
        for tilt, towards in poses:
            _, lengths = rig.floor_hits(_leaning(math.radians(tilt), math.radians(towards)), np.array([0.0, 0.0, -h]))
            pixels = np.asarray(project(dots_in_body(rig, lengths)), dtype=float).reshape(BEAMS, 2)
            inside = ((pixels[:, 0] >= margin_px) & (pixels[:, 0] <= width - margin_px)
                      & (pixels[:, 1] >= margin_px) & (pixels[:, 1] <= height - margin_px))
            where = f"at {h:g} m height " + (f"and {tilt:g} deg tilt towards {towards:g} deg" if tilt else "and level")
            problems += [f"{where}, beam {i}{_lost_dot(lengths[i], pixels[i])}" for i in np.flatnonzero(~inside)]
    return problems


def _lost_dot(length: float, pixel: np.ndarray) -> str:
    """How a beam's dot is lost, for :func:`fov_problems`."""
    if np.isnan(length):
        return " misses the floor"
    if np.any(np.isnan(pixel)):
        return "'s dot is not imaged"
    return f"'s dot is outside the image (at {pixel[0]:.0f}, {pixel[1]:.0f} px)"
