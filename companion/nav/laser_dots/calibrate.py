"""Beam calibration: each beam's origin and direction in the body frame from frames at known poses.

A frame at a known pose (rotation body FRD -> NED, NED position m: motion capture, or the
vehicle set on surveyed blocks at several heights and headings) with its dots on the floor
([north, east] m, through the floor markers) puts every seen dot in the body frame,
``R^T (dot - position)`` (FRD, m). The points of one beam lie on its line: a 3-D line fit
(centroid and principal direction by SVD) gives the beam's direction, oriented like the nominal
one, and its origin, taken as the point of the line nearest the nominal origin (where along its
line a beam starts does not change any dot: only the lengths, which the solver finds).

The direction is only as good as the spread of the points along the line: frames from a single
height give a blob, not a line, so a beam needs at least 3 frames whose heights span 0.3 m.
Attitude errors of the known poses weigh most (0.1 deg moves a dot 5 mm at 3 m): with poses
known to 1 mm and 0.03 deg (motion capture) and dots to 1 mm, 30 frames over 0.6-1.8 m give
the directions to ~0.04 deg (0.1 deg at worst) and the origins to 1-4 mm (simulated).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from companion.laser_beams import BEAMS, BeamRig

MIN_OBSERVATIONS = 3  # frames that saw a beam's dot
MIN_HEIGHT_SPAN_M = 0.3  # between the lowest and the highest of those frames, m
PAIRS = ((0, 1), (1, 2), (0, 2))  # the order of BeamCalibration.angles_deg (the seed's a1, a2, a3)

Observation = tuple[np.ndarray, np.ndarray, np.ndarray]  # rotation body -> NED, NED position m, (3, 2) dots m


@dataclass(frozen=True, eq=False)
class BeamCalibration:
    """The calibrated rig and how well its lines fit."""

    rig: BeamRig  # origins and unit directions, body FRD, m
    rms_m: np.ndarray  # (3,) RMS distance of each beam's points from its fitted line, m
    count: np.ndarray  # (3,) frames that saw each beam's dot
    angles_deg: np.ndarray  # (3,) angles between beams 0-1, 1-2, 0-2, degrees


def _beam_points(observations: Sequence[Observation], beam: int) -> tuple[np.ndarray, np.ndarray]:
    """Beam ``beam``'s dots in body FRD (N, 3) m and the heights (N,) m of the frames that saw it
    (a NaN dot row: not seen)."""
    points, heights = [], []
    for rotation, position_ned, dots in observations:
        dot = np.asarray(dots, dtype=float).reshape(BEAMS, 2)[beam]
        if np.all(np.isfinite(dot)):
            position = np.asarray(position_ned, dtype=float)
            points.append(np.asarray(rotation, dtype=float).T @ (np.append(dot, 0.0) - position))
            heights.append(-position[2])
    return np.array(points).reshape(-1, 3), np.array(heights)


def fit_line(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares 3-D line through (N, 3) points (m): (centroid, unit direction, RMS distance
    of the points from the line m)."""
    centroid = points.mean(axis=0)
    centred = points - centroid
    direction = np.linalg.svd(centred, full_matrices=False)[2][0]
    across = centred - np.outer(centred @ direction, direction)
    return centroid, direction, float(np.sqrt(np.mean(np.sum(across ** 2, axis=1))))


def _check_spread(beam: int, heights: np.ndarray) -> None:
    """ValueError unless enough frames at different enough heights saw the beam."""
    if len(heights) < MIN_OBSERVATIONS:
        raise ValueError(f"beam {beam}: {len(heights)} frames saw its dot, at least {MIN_OBSERVATIONS} are needed")
    span = float(np.ptp(heights))
    if span < MIN_HEIGHT_SPAN_M:
        raise ValueError(f"beam {beam}: the frames that saw its dot span {span:.2f} m of height, at least "
                         f"{MIN_HEIGHT_SPAN_M} m is needed (the beam's direction would be ill-conditioned): "
                         "add frames nearer to and further from the floor")


def calibrate_beams(observations: Sequence[Observation], nominal: BeamRig) -> BeamCalibration:
    """Each beam's line fitted to its dots seen from known poses.

    ``observations``: (rotation body FRD -> NED, NED position (3,) m, (3, 2) floor dots
    [north, east] m with a NaN row where a dot was not seen). ``nominal``: the rig as designed,
    which orients the directions and places the origins (the point of each fitted line nearest
    the nominal origin). ValueError when a beam was seen fewer than 3 times or from heights
    spanning less than 0.3 m."""
    origins, directions, rms, count = [], [], [], []
    for beam in range(BEAMS):
        points, heights = _beam_points(observations, beam)
        _check_spread(beam, heights)
        centroid, direction, beam_rms = fit_line(points)
        if direction @ nominal.directions[beam] < 0.0:
            direction = -direction
        origins.append(centroid + ((nominal.origins[beam] - centroid) @ direction) * direction)
        directions.append(direction)
        rms.append(beam_rms)
        count.append(len(points))
    rig = BeamRig(np.array(origins), np.array(directions))
    return BeamCalibration(rig, np.array(rms), np.array(count), np.array([rig.angle_deg(i, j) for i, j in PAIRS]))


def rig_to_yaml(rig: BeamRig) -> str:
    """The ``beams:`` section of a config (:class:`~companion.laser_beams.BeamRigConfig`)
    for a calibrated rig: ``origins_m`` (body FRD, m) and ``directions`` rows, 6 decimals."""
    def rows(values: np.ndarray) -> list[str]:
        return ["    - [" + ", ".join(f"{round(float(v), 6) + 0.0:.6f}" for v in row) + "]" for row in values]
    return "\n".join(["beams:", "  origins_m:", *rows(rig.origins), "  directions:", *rows(rig.directions)]) + "\n"
