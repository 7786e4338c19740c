"""Heading tracking from wall directions modulo the constant wall angle (Wang et al. eqs. 2-4).

Frames: the lines are in a levelled frame fixed to the body (x forward, y right, yaw-only
rotation from the world); yaw is the world heading from north towards east, radians. A line
with normal angle ``a`` in that frame has the world normal angle ``yaw + a`` (angles add: both
are measured from x towards y). Every wall runs at a multiple of the wall angle ``A`` (90, 45
or 30 degrees), and so does its normal because 90 degrees is itself a multiple of ``A``. Hence
``yaw + a = n A`` and, from the predicted heading ``yaw_p``, the correction of one line is

    c = -[(yaw_p + a) % A]                       (eq. 2, normals instead of directions)

with the paper's ``%`` (eq. 3) mapping into (-A/2, A/2], and ``yaw = yaw_p + c`` (eq. 4).
A building need not be aligned with north (the map frame is the autopilot's NED): its walls
run at ``offset + n A``, and ``offset`` is subtracted before the modulo.

Deviations from the paper, all for robustness:

* every reliable line votes (the paper takes the longest), weighted by the inverse variance of
  its direction (``LineSet.alpha_var``: grows with the fit residual, shrinks with the number of
  points and the square of the length);
* the consensus is found like an exhaustive RANSAC: each line's correction is a candidate,
  its support is the weight of the lines agreeing within ``inlier_tolerance_deg`` (differences
  wrapped modulo A, so +A/2 and -A/2 are neighbours); the best-supported candidate's inliers
  are averaged as residuals around it, which is the circular mean modulo A without the wrap
  problem at +/-A/2. Too little support (clutter at arbitrary angles) is reported ``ambiguous``;
* with a trusted prediction (``prediction_sigma_deg`` finite: a gyro) the candidates are ranked
  by their support times a Gaussian prior on their correction: when two wall families compete (clutter at 15 degrees outweighing
  the building's walls) the one the predicted heading expects is chosen, and if it lacks the
  consensus the heading is reported ``ambiguous`` rather than flipped to the other family; a
  winning correction beyond ``max_correction_sigmas`` prediction sigmas is ``ambiguous`` too
  (the walls agree among themselves but not with the gyro: a wrong family, clutter at an angle);
* ``predicted_delta`` (e.g. the gyro's integrated yaw change since the last scan) moves the
  prediction, so the inter-frame limit of A/2 applies to the unpredicted rotation only;
* the limit itself is in every result (``limit_rad`` = A/2). A rotation beyond it aliases by a
  multiple of A and cannot be seen in the lines alone: a correction beyond
  ``warn_fraction * A/2`` is reported ``near_limit`` (it may be an aliased larger rotation),
  and the planar localizer then lets the corner association decide between the aliases.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from companion.frames import wrap_pi
from companion.nav.lines import LineSet

HeadingStatus = Literal["ok", "near_limit", "ambiguous", "no_lines"]


@dataclass(frozen=True)
class HeadingParams:
    """Thresholds of the heading tracker."""

    min_length_m: float = 0.4  # shorter lines do not vote, metres
    inlier_tolerance_deg: float = 2.0  # a line agrees with a candidate within this, degrees
    min_consensus: float = 0.6  # the inliers must carry this fraction of the weight
    warn_fraction: float = 0.5  # |correction| beyond this fraction of A/2 is near_limit
    # 1-sigma of the predicted heading for ranking wall families, degrees; inf: no prior (without a
    # gyro the prediction is only the previous heading). The lidar pipeline, predicting with the
    # autopilot's gyro, uses 5.
    prediction_sigma_deg: float = math.inf
    # A correction beyond this many prediction sigmas is refused (the walls seen are not the
    # family the gyro says: clutter at an angle, a wrong family's consensus); unbounded without one.
    max_correction_sigmas: float = 4.0
    variance_floor_rad2: float = math.radians(0.05) ** 2  # floor: map walls may be 0.1 deg off


@dataclass(frozen=True)
class HeadingResult:
    """One heading update. Angles in radians; yaw from north towards east, in [-pi, pi)."""

    yaw: float  # the tracked heading (the prediction when no usable lines)
    correction: float  # yaw - predicted yaw, in (-A/2, A/2]
    variance: float  # rad^2 of the heading measurement (pi^2 when not measured)
    status: HeadingStatus
    reason: str
    lines_used: int  # inlier lines
    consensus: float  # weight fraction of the inliers, 0..1
    limit_rad: float  # the inter-frame rotation limit A/2 beyond which the heading aliases
    # (K,) d yaw / d alpha of every line of the LineSet (rad/rad): minus each inlier's weight
    # fraction, 0 for the others; empty when not measured. ``variance`` without the residual
    # scaling and the floor is sum(alpha_gain^2 alpha_var).
    alpha_gain: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def measured(self) -> bool:
        """Whether the lines gave a heading (ok or near_limit)."""
        return self.status in ("ok", "near_limit")


UNMEASURED_VARIANCE_RAD2 = math.pi ** 2  # reported when the lines give no heading


def wall_mod(a: np.ndarray | float, b: float) -> np.ndarray:
    """The paper's ``a % b`` (eq. 3): ``a mod b`` folded into (-b/2, b/2]."""
    r = np.mod(a, b)
    return np.where(r > b / 2, r - b, r)


def track_heading(lines: LineSet, previous_yaw: float, wall_angle_rad: float,
                  predicted_delta: float = 0.0, params: HeadingParams = HeadingParams(),
                  wall_offset_rad: float = 0.0) -> HeadingResult:
    """Heading now, from the previous heading (plus ``predicted_delta``, rad) and the lines; the
    map's walls run at ``wall_offset_rad`` plus multiples of ``wall_angle_rad``."""
    predicted = previous_yaw + predicted_delta
    limit = wall_angle_rad / 2
    use = lines.length >= params.min_length_m
    if not use.any():
        return HeadingResult(wrap_pi(predicted), 0.0, UNMEASURED_VARIANCE_RAD2, "no_lines",
                             f"no line of {params.min_length_m:g} m or longer", 0, 0.0, limit)
    corr = -wall_mod(predicted + lines.alpha[use] - wall_offset_rad, wall_angle_rad)  # eq. 2 per line
    weight = 1.0 / lines.alpha_var[use]
    diff = wall_mod(corr[:, None] - corr[None, :], wall_angle_rad)  # candidate row - line column
    agree = np.abs(diff) <= math.radians(params.inlier_tolerance_deg)
    support = agree @ weight
    best = int(np.argmax(support * np.exp(-0.5 * (corr / math.radians(params.prediction_sigma_deg)) ** 2)))
    consensus = float(support[best] / weight.sum())
    inl = agree[best]
    if consensus < params.min_consensus:
        return HeadingResult(wrap_pi(predicted), 0.0, UNMEASURED_VARIANCE_RAD2, "ambiguous",
                             f"wall directions disagree: best consensus {consensus:.2f} < "
                             f"{params.min_consensus:g}", int(inl.sum()), consensus, limit)
    w = weight[inl]
    resid = -diff[best, inl]  # line correction minus the candidate, wrapped
    mean_resid = float(w @ resid / w.sum())
    gain = np.zeros(lines.count)
    gain[np.flatnonzero(use)[inl]] = -w / w.sum()  # the correction is the inliers' weighted mean of -alpha
    correction = float(wall_mod(corr[best] + mean_resid, wall_angle_rad))
    variance = max(_variance(w, resid - mean_resid), params.variance_floor_rad2)
    yaw = wrap_pi(predicted + correction)
    if abs(correction) > params.max_correction_sigmas * math.radians(params.prediction_sigma_deg):
        return HeadingResult(wrap_pi(predicted), 0.0, UNMEASURED_VARIANCE_RAD2, "ambiguous",
                             f"the walls' heading is {math.degrees(correction):+.1f} deg off the gyro's prediction "
                             f"(more than {params.max_correction_sigmas:g} x {params.prediction_sigma_deg:g} deg)",
                             int(inl.sum()), consensus, limit)
    if abs(correction) > params.warn_fraction * limit:
        return HeadingResult(yaw, correction, variance, "near_limit",
                             f"correction {math.degrees(correction):.1f} deg approaches the inter-frame "
                             f"limit A/2 = {math.degrees(limit):.1f} deg: a faster turn aliases by "
                             f"{math.degrees(wall_angle_rad):g} deg", int(inl.sum()), consensus, limit, gain)
    return HeadingResult(yaw, correction, variance, "ok", "", int(inl.sum()), consensus, limit, gain)


def _variance(weight: np.ndarray, resid: np.ndarray) -> float:
    """Variance of the weighted mean: 1 / sum(w), scaled up by the residual chi-square per
    degree of freedom when the lines scatter more than their fits predict."""
    formal = 1.0 / float(weight.sum())
    if weight.size < 2:
        return formal
    chi2_dof = float(weight @ resid ** 2) / (weight.size - 1)
    return formal * max(1.0, chi2_dof)


def heading_hypotheses(lines: LineSet, wall_angle_rad: float, params: HeadingParams = HeadingParams(),
                       wall_offset_rad: float = 0.0) -> tuple[np.ndarray, HeadingResult]:
    """All headings compatible with the observed wall directions (for global relocalization):
    the heading modulo A from the lines' consensus, plus every multiple of A, in [-pi, pi).
    Empty when the lines give no heading; the HeadingResult says why and carries the variance."""
    base = track_heading(lines, 0.0, wall_angle_rad, 0.0, replace(params, warn_fraction=1.0, prediction_sigma_deg=math.inf),
                         wall_offset_rad)
    if not base.measured:
        return np.zeros(0), base
    count = int(round(2 * math.pi / wall_angle_rad))
    yaws = (base.yaw + wall_angle_rad * np.arange(count) + math.pi) % (2 * math.pi) - math.pi
    return yaws, base
