"""Covariance of a position fix from matched corners, jointly with the heading from the same lines.

Frames: corners and lines in the levelled body frame (x forward, y right, metres); the fix in
the map's north / east (metres) and yaw (radians, from north towards east); ``rot`` = R(yaw)
takes the first to the second.

The planar localizer's fix is ``p = sum_k w_k (m_k - R(yaw) q_k)`` over the matched corners
(map corner ``m_k``, observed corner ``q_k``, weights ``w_k`` summing to 1), and the heading
comes from the directions of the same lines that make the corners. To first order in each
line's errors (``du_j``: its offset at the centroid, ``dalpha_j``: its direction; independent,
variances ``offset_var_j`` and ``alpha_var_j``):

    dq_k   = G_k [du_a - s_a dalpha_a, du_b - s_b dalpha_b]      (companion/nav/corners.py)
    dyaw   = sum_j g_j dalpha_j                                   (HeadingResult.alpha_gain)
    dp     = -sum_k w_k R dq_k - J R (sum_k w_k q_k) dyaw         (J: +90 degree rotation)

so ``(dp, dyaw) = A (du, dalpha)`` and the covariance is ``A diag(offset_var, alpha_var) A^T``.
Propagated this way, a heading error and the corner errors that come from the same line
directions partly cancel, and two corners on one line share its error. Summing the corners as
independent and adding the heading variance through the lever arm as if it were independent
counted those errors twice (replaying a clean SITL flight with the floors off: the fixes' NEES
0.78 north, 0.50 east; 1 when consistent).

Added as independent: each corner's floor (``Corners.floor_var``: the map's survey error, wall
roughness, beam width), and the part of the heading variance beyond the lines' formal one (its
residual scaling and floor: errors such as a map wall's angle, which turn the whole frame)
through the lever arm. ``position_scale`` (>= 1: the corners' residual scatter, the single
corner's inflation) scales the position block.
"""

from __future__ import annotations

import numpy as np

from companion.nav.corners import Corners
from companion.nav.heading import HeadingResult
from companion.nav.lines import LineSet


def corner_fix_covariance(lines: LineSet, corners: Corners, weights: np.ndarray, rot: np.ndarray,
                          heading: HeadingResult, position_scale: float = 1.0) -> np.ndarray:
    """3x3 covariance of (north m, east m, yaw rad) of the fix from ``corners`` (the matched ones,
    found in ``lines``) weighted by ``weights`` (K,), summing to 1, with the ``heading`` measured
    from ``lines`` and ``rot`` its 2x2 rotation body -> map."""
    n = lines.count
    if heading.alpha_gain.shape != (n,):
        raise ValueError(f"the heading was measured from {heading.alpha_gain.size} lines, the corners from {n}")
    k = corners.count
    # (2 axes, 2K): the fix's move per metre each corner's line (a then b) moves at the corner
    moves = (rot @ corners.gain * -weights[:, None, None]).transpose(1, 0, 2).reshape(2, 2 * k)
    which = np.zeros((2 * k, n))  # row j: the line of that move
    which[np.arange(2 * k), corners.lines.ravel()] = 1.0
    arm = weights @ (corners.xy @ rot.T)
    dp_dyaw = np.array([arm[1], -arm[0]])
    jac = np.empty((3, 2 * n))  # rows north, east, yaw; columns du (n), dalpha (n)
    jac[:2, :n] = moves @ which
    jac[:2, n:] = (moves * -corners.lever.ravel()) @ which + np.outer(dp_dyaw, heading.alpha_gain)
    jac[2, :n] = 0.0
    jac[2, n:] = heading.alpha_gain
    cov = (jac * np.concatenate((lines.offset_var, lines.alpha_var))) @ jac.T
    cov[:2, :2] += float(weights ** 2 @ corners.floor_var) * np.eye(2)
    cov[:2, :2] *= position_scale
    extra = max(heading.variance - cov[2, 2], 0.0)
    turn = np.array([dp_dyaw[0], dp_dyaw[1], 1.0])
    return cov + extra * np.outer(turn, turn)
