"""One camera frame -> the laser-dot pose, or the height and tilt, or an honest "no".

:class:`FramePoser` chains the parts for one frame: the dots (:mod:`.detect`), the floor markers
(:mod:`.floor`), the dots on the floor with their covariance (pixel noise through the mapping's
Jacobian plus the homography's own error), the pose and its covariance (:mod:`.geometry`), and
the checks that refuse a confident wrong pose:

- a dot whose structured-light length (triangulated from the camera) differs from the length the
  floor solution needs by more than ``length_gate_sigmas``: that dot is not on the floor plane
  the markers define (a table, a step, a box);
- the beam-matrix attitude and the P3P / Kabsch rotation differing by more than ``max_cross_check_deg``;
- a solution outside ``height_range_m`` or tilted beyond ``max_tilt_deg``;
- a dot whose length cannot be triangulated at all (the check above could not run).

Without a floor marker in view the triangulated dots still give the floor plane in the body
frame: the height of the body origin and roll and pitch (yaw is unobservable).

Frames: world LOCAL_NED (the floor is z = 0), body FRD, metres and radians. No I/O, no state
besides the detector's and mapper's precomputed tables: the caller keeps the previous frame's
pixels and pose (its priors).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from companion.calibration import CameraCalibration
from companion.frames import euler_from_rotation, rotation_from_euler
from companion.laser_beams import BeamRig
from companion.nav.laser_dots import geometry
from companion.nav.laser_dots.detect import DotDetector, Dots
from companion.nav.laser_dots.floor import FloorMapper, FloorView
from companion.world import FloorMarker


UNTRIANGULATED = "a dot's beam length cannot be triangulated (its camera ray runs along the beam)"
REST_TOLERANCE_M = 0.05  # a height this far below height_range_m's low end still passes (resting on the floor: +/- mm)


@dataclass(frozen=True)
class FramePoseParams:
    """The checks and noise model of :class:`FramePoser` (see the module docstring)."""

    method: geometry.Method = "general"
    height_range_m: tuple[float, float] = (0.0, 2.5)  # of the body origin above the floor, m
    max_tilt_deg: float = 15.0
    dot_sigma_px: float = 0.5  # 1-sigma centroid error per axis, px
    length_gate_sigmas: float = 5.0
    max_cross_check_deg: float = 2.0


@dataclass(frozen=True)
class FrameResult:
    """What one frame gave. ``kind``: "pose" (6-DOF: ``solution``, ``covariance`` over north,
    east, down m, roll, pitch, yaw rad), "tilt" (no marker: ``tilt`` = height m, roll, pitch rad
    with ``tilt_covariance``), or "none" (``reason`` says why)."""

    kind: Literal["pose", "tilt", "none"]
    reason: str
    dots: Dots
    markers: tuple[int, ...] = ()
    marker_corners_px: np.ndarray | None = None  # (M, 4, 2) the markers' corner pixels, ArUco order
    floor_dots: np.ndarray | None = None  # (3, 2) [north, east] m
    solution: geometry.PoseSolution | None = None
    covariance: np.ndarray | None = None  # (6, 6)
    tilt: tuple[float, float, float] | None = None
    tilt_covariance: np.ndarray | None = None  # (3, 3)


class FramePoser:
    """The per-frame pose of a rig seen by a camera (``optical_to_body`` 3x3 rotation, camera
    centre ``camera_origin_body`` m in body FRD) over a floor with ``markers``."""

    def __init__(self, rig: BeamRig, calibration: CameraCalibration, optical_to_body: np.ndarray,
                 camera_origin_body: np.ndarray, markers: tuple[FloorMarker, ...],
                 params: FramePoseParams = FramePoseParams()) -> None:
        self.rig = rig
        self.params = params
        self.detector = DotDetector(calibration, optical_to_body, camera_origin_body, rig)
        self.mapper = FloorMapper(calibration, markers)

    def process(self, image: np.ndarray, prior_rotation: np.ndarray | None = None,
                previous_pose: tuple[np.ndarray, np.ndarray] | None = None,
                previous_pixels: np.ndarray | None = None) -> FrameResult:
        """The frame's result; ``prior_rotation`` (body -> NED, e.g. the autopilot's attitude),
        ``previous_pose`` ((rotation, NED position m) of the last pose) and ``previous_pixels``
        ((3, 2) dot pixels of the last frame, NaN rows unknown) pick among ambiguous answers; the
        previous pose also says where to look for the floor markers (floor.py, tracking)."""
        dots = self.detector.detect(image, previous_pixels)
        if dots.reason is not None or not dots.found.all():
            return FrameResult("none", dots.reason or f"{int(dots.found.sum())} of 3 dots seen", dots)
        view = self.mapper.find(image, self._predicted_camera(prior_rotation, previous_pose))
        if view is None:
            return self._tilt(dots)
        return self._pose(dots, view, prior_rotation, previous_pose)

    def _predicted_camera(self, prior_rotation: np.ndarray | None,
                          previous_pose: tuple[np.ndarray, np.ndarray] | None) -> tuple[np.ndarray, np.ndarray] | None:
        """Where the camera should be for this frame (to track the markers): the previous pose's
        position and yaw with the prior's roll and pitch (the autopilot's attitude now; its yaw may
        be offset from the map's), or None without a previous pose."""
        if previous_pose is None:
            return None
        rotation, position = previous_pose
        if prior_rotation is not None:
            roll, pitch, _ = euler_from_rotation(prior_rotation)
            rotation = rotation_from_euler(roll, pitch, euler_from_rotation(rotation)[2])
        return self.camera_pose(rotation, position)

    def camera_pose(self, body_to_ned: np.ndarray, position_ned: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rotation optical -> NED, camera centre NED m) of the camera for a body pose (rotation
        body FRD -> NED, body origin NED m)."""
        return (body_to_ned @ self.detector.optical_to_body,
                position_ned + body_to_ned @ self.detector.camera_origin_body)

    def _pose(self, dots: Dots, view: FloorView, prior_rotation: np.ndarray | None,
              previous_pose: tuple[np.ndarray, np.ndarray] | None) -> FrameResult:
        p = self.params
        markers, corners = tuple(view.marker_ids), view.corner_pixels
        floor, jacobian = self.mapper.to_floor(view, dots.pixels)
        dots_cov = (p.dot_sigma_px ** 2 * jacobian @ jacobian.transpose(0, 2, 1)
                    + self.mapper.floor_covariance(view, dots.pixels))
        solution = geometry.solve(self.rig, floor, p.method, prior_rotation=prior_rotation, previous=previous_pose,
                                  max_tilt_deg=p.max_tilt_deg)
        problem = self._refusal(solution, dots)
        if problem is not None:
            return FrameResult("none", problem, dots, markers, corners, floor, solution)
        assert solution is not None  # _refusal() names a missing one
        cov = geometry.pose_covariance(self.rig, floor, dots_cov, p.method, solution)
        if not np.all(np.isfinite(cov)):
            return FrameResult("none", "no covariance: the solver fails next to these dots", dots, markers, corners, floor,
                               solution)
        return FrameResult("pose", f"3 dots, {len(markers)} markers", dots, markers, corners, floor, solution, cov)

    def _refusal(self, solution: geometry.PoseSolution | None, dots: Dots) -> str | None:
        """Why a solution must not be trusted, or None."""
        p = self.params
        if solution is None:
            return "no plausible pose from the dots (or two equally plausible)"
        height = -float(solution.position_ned[2])
        if not _in_range(height, p.height_range_m):
            return f"height {height:.2f} m outside height_range_m"
        if solution.cross_check_deg > p.max_cross_check_deg:
            return f"beam-matrix attitude and P3P differ by {solution.cross_check_deg:.1f} deg"
        sigma = self.detector.length_sigma_m(dots.pixels, p.dot_sigma_px)
        with np.errstate(divide="ignore", invalid="ignore"):
            mismatch = np.abs(dots.lengths_m - solution.lengths) / sigma
        if not np.all(np.isfinite(mismatch)):  # the off-floor check cannot run: no fix rather than an unchecked one
            return UNTRIANGULATED
        worst = int(np.argmax(mismatch))
        if mismatch[worst] > p.length_gate_sigmas:
            return (f"beam {worst}'s dot is off the floor: {dots.lengths_m[worst]:.2f} m by triangulation, "
                    f"{solution.lengths[worst]:.2f} m to the floor")
        return None

    def _tilt(self, dots: Dots) -> FrameResult:
        """No marker in view: the floor plane from the triangulated dots."""
        p = self.params
        if not np.all(np.isfinite(dots.lengths_m)):
            return FrameResult("none", UNTRIANGULATED, dots)
        try:
            height, roll, pitch = geometry.plane_from_body_points(geometry.dots_in_body(self.rig, dots.lengths_m),
                                                                  self.rig.origins.mean(axis=0))
        except ValueError as exc:  # the three points are collinear: no floor plane
            return FrameResult("none", str(exc), dots)
        if not _in_range(height, p.height_range_m):
            return FrameResult("none", f"height {height:.2f} m outside height_range_m (no marker in view)", dots)
        sigma = self.detector.length_sigma_m(dots.pixels, p.dot_sigma_px)
        cov = geometry.height_covariance(self.rig, dots.lengths_m, sigma ** 2)
        if not np.all(np.isfinite(cov)):
            return FrameResult("none", "no covariance: the floor plane fails next to these lengths", dots)
        return FrameResult("tilt", "no floor marker in view: height and tilt only", dots,
                           tilt=(height, roll, pitch), tilt_covariance=cov)


def _in_range(height_m: float, height_range_m: tuple[float, float]) -> bool:
    """``height_m`` within ``height_range_m``, its low end lowered by REST_TOLERANCE_M."""
    return height_range_m[0] - REST_TOLERANCE_M <= height_m <= height_range_m[1]
