"""The floor in an image, from its ArUco markers: the mapping from image pixels to floor
coordinates (for the laser dots) and the camera pose from the markers alone (for comparison and
for the beam calibration).

Frames and units: pixels (u, v) = (column, row), integer values at pixel centres; normalised image
coordinates (x/z, y/z) of OpenCV's optical frame (x right, y down, z along the axis); the floor
[north, east] in metres, the plane z = 0 of LOCAL_NED (companion/world.py). A world point X (NED,
m) is ``R.T @ (X - c)`` in the optical frame of a camera with rotation R (optical -> NED) and
centre c (NED, m).

The markers' corners are undistorted first, so one homography H maps normalised image
coordinates to the floor (a plane seen by a pinhole): fitted by least squares (cv2.findHomography
without RANSAC) to the 4 corners of every visible marker of the world, with distinct ids.

Mapping error model (:meth:`FloorMapper.floor_uncertainty_m`): a corner's floor residual has a
1-sigma per axis ``s`` = the larger of the fit's residual estimate ``sqrt(SSR / (2n - 8))`` (n
corners, 8 parameters; none for one marker) and ``corner_sigma_px`` times the floor metres per
pixel; the mapping of a point among the markers then errs by ``s * sqrt(8 / (2n))`` per axis (the
mean leverage of a least-squares fit of 8 parameters to 2n values). Points far outside the
markers' hull err more (extrapolation): the model does not cover that.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from companion.calibration import CameraCalibration
from companion.world import ARUCO_DICTIONARY, FloorMarker

HOMOGRAPHY_PARAMETERS = 8
JACOBIAN_STEP_PX = 0.01  # central differences of the pixel -> floor mapping, pixels


@dataclass(frozen=True)
class FloorParams:
    """Settings of the floor mapper."""

    corner_sigma_px: float = 0.2  # 1-sigma of a refined ArUco corner per axis, pixels (the model's lower bound)
    subpix_window_px: int = 5  # half-size of the corner refinement window, pixels
    # Two adaptive-threshold windows (3 and 23 px) instead of OpenCV's three: 7.2 -> 5.7 ms on 640x480
    # frames of the fig4 hall here, the same markers found. (OpenCV's ArUco 3 mode, candidates on a
    # downscaled image, reaches 4.0 ms but its corners are worse: a one-marker camera pose 3.5 deg off
    # instead of 0.3 deg.)
    threshold_window_step_px: int = 20


@dataclass(frozen=True)
class FloorView:
    """The floor as seen in one image."""

    homography: np.ndarray  # (3, 3) normalised image coordinates -> floor [north, east], m
    marker_ids: tuple[int, ...]  # the world's markers used, in the order of the corners
    corner_pixels: np.ndarray  # (M, 4, 2) their corners, pixels, ArUco order (TL, TR, BR, BL)
    corner_normalised: np.ndarray  # (M, 4, 2) the same, undistorted: normalised image coordinates
    n_points: int  # corners fitted (4 M)
    rms_m: float  # RMS distance on the floor between the corners mapped by H and their survey, m
    metres_per_px: float  # mean floor distance per image pixel at the corners, m
    ignored: int  # markers detected but not used: id not in the world, or detected more than once


def apply_homography(homography: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 2) images of (N, 2) points under the 3x3 ``homography``; NaN stays NaN (unlike
    cv2.perspectiveTransform, which gives 0)."""
    mapped = np.column_stack((points, np.ones(len(points)))) @ homography.T
    return mapped[:, :2] / mapped[:, 2:]


def map_pixels(calibration: CameraCalibration, homography: np.ndarray,
               pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((N, 2) floor [north, east] m, (N, 2, 2) Jacobian d floor / d (u, v), m per pixel) of the
    (N, 2) pixels through the lens of ``calibration`` and ``homography`` (normalised -> floor).
    The Jacobian is by central differences of the whole mapping, lens included."""
    pixels = np.asarray(pixels, dtype=float).reshape(-1, 2)
    h = JACOBIAN_STEP_PX
    steps = np.array([[0.0, 0.0], [h, 0.0], [-h, 0.0], [0.0, h], [0.0, -h]])
    shifted = (pixels[:, None, :] + steps[None]).reshape(-1, 2)
    floor = apply_homography(homography, calibration.undistort_points(shifted)).reshape(-1, 5, 2)
    jacobian = np.stack(((floor[:, 1] - floor[:, 2]) / (2 * h), (floor[:, 3] - floor[:, 4]) / (2 * h)), axis=2)
    return floor[:, 0], jacobian


def marker_pose(marker: FloorMarker) -> tuple[np.ndarray, np.ndarray]:
    """(rotation marker frame -> NED (3x3), centre NED (3,) m) of a floor marker. The marker frame
    is the one cv2.SOLVEPNP_IPPE_SQUARE assumes: x to the marker's right, y to its top edge, z out
    of the floor (up), origin at the centre."""
    yaw = math.radians(marker.yaw_deg)
    top = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    right = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
    return np.column_stack((right, top, np.cross(right, top))), np.array([*marker.position, 0.0])


def square_object_points(size_m: float) -> np.ndarray:
    """(4, 3) corners (m) of a square marker of side ``size_m`` in its own frame, in the order
    cv2.SOLVEPNP_IPPE_SQUARE requires (ArUco's TL, TR, BR, BL)."""
    h = size_m / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def camera_from_pnp(rvec: np.ndarray, tvec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rotation optical -> object frame, camera centre in the object frame) of a solvePnP result
    (``X_optical = R(rvec) X_object + tvec``)."""
    rotation = cv2.Rodrigues(rvec)[0]
    return rotation.T, -rotation.T @ tvec.ravel()


class FloorMapper:
    """Finds the world's floor ``markers`` (ids in the ArUco ``dictionary``, an OpenCV DICT_
    constant) in the images of a camera of ``calibration``."""

    def __init__(self, calibration: CameraCalibration, markers: Sequence[FloorMarker],
                 dictionary: int = ARUCO_DICTIONARY, params: FloorParams = FloorParams()) -> None:
        self.calibration = calibration
        self.markers = {m.id: m for m in markers}
        self.params = params
        detector_params = cv2.aruco.DetectorParameters()
        detector_params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        detector_params.cornerRefinementWinSize = params.subpix_window_px
        detector_params.adaptiveThreshWinSizeStep = params.threshold_window_step_px
        self.detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(dictionary), detector_params)

    def find(self, image: np.ndarray) -> FloorView | None:
        """The floor view of ``image`` ((H, W) grey or (H, W, 3) BGR uint8), or None if no marker of
        the world is seen once."""
        marker_ids, pixels, ignored = self.known_markers(image)
        if not marker_ids:
            return None
        normalised = self.calibration.undistort_points(pixels.reshape(-1, 2))
        floor = np.concatenate([self.markers[i].corners() for i in marker_ids])
        homography, _ = cv2.findHomography(normalised, floor, 0)
        if homography is None:
            return None
        residuals = apply_homography(homography, normalised) - floor
        _, jacobian = map_pixels(self.calibration, homography, pixels.reshape(-1, 2))
        return FloorView(homography, marker_ids, pixels, normalised.reshape(-1, 4, 2), len(floor),
                         float(np.sqrt(np.mean(np.sum(residuals ** 2, axis=1)))),
                         float(np.mean(np.sqrt(np.abs(np.linalg.det(jacobian))))), ignored)

    def known_markers(self, image: np.ndarray) -> tuple[tuple[int, ...], np.ndarray, int]:
        """(ids, (M, 4, 2) corner pixels, count of the other detections) of the world's markers
        detected exactly once in ``image`` (grey or BGR)."""
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        corners, ids, _ = self.detector.detectMarkers(grey)
        detected = [] if ids is None else [int(i) for i in ids.ravel()]
        seen = Counter(detected)
        used = [k for k, i in enumerate(detected) if i in self.markers and seen[i] == 1]
        pixels = np.array([corners[k].reshape(4, 2) for k in used], dtype=float).reshape(-1, 4, 2)
        return tuple(detected[k] for k in used), pixels, len(detected) - len(used)

    def to_floor(self, view: FloorView, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """((N, 2) floor [north, east] m, (N, 2, 2) Jacobian d floor / d (u, v), m per pixel) of the
        (N, 2) pixels, assumed on the floor (NaN rows give NaN). The Jacobian carries pixel noise
        to the floor: ``cov_floor = J cov_px J.T``."""
        return map_pixels(self.calibration, view.homography, pixels)

    def floor_uncertainty_m(self, view: FloorView) -> float:
        """1-sigma per floor axis (m) of the homography's mapping error for points among the
        markers (the model of the module docstring)."""
        dof = 2 * view.n_points - HOMOGRAPHY_PARAMETERS
        residual_sigma = math.sqrt(view.n_points * view.rms_m ** 2 / dof) if dof > 0 else 0.0
        corner_sigma = max(residual_sigma, self.params.corner_sigma_px * view.metres_per_px)
        return corner_sigma * math.sqrt(HOMOGRAPHY_PARAMETERS / (2 * view.n_points))

    def camera_pose(self, view: FloorView) -> tuple[np.ndarray, np.ndarray] | None:
        """(rotation optical -> NED (3x3), camera centre NED (3,) m) from the markers alone, or
        None if solvePnP fails: cv2.SOLVEPNP_IPPE_SQUARE on a single marker, cv2.SOLVEPNP_ITERATIVE
        on all the corners of several (both on the undistorted corners)."""
        if len(view.marker_ids) == 1:
            return self._single_marker_pose(view)
        floor = np.concatenate([self.markers[i].corners() for i in view.marker_ids])
        ok, rvec, tvec = cv2.solvePnP(np.column_stack((floor, np.zeros(len(floor)))),
                                      view.corner_normalised.reshape(-1, 1, 2), np.eye(3), None,
                                      flags=cv2.SOLVEPNP_ITERATIVE)
        return camera_from_pnp(rvec, tvec) if ok else None

    def _single_marker_pose(self, view: FloorView) -> tuple[np.ndarray, np.ndarray] | None:
        """The camera pose from the one marker of ``view`` (IPPE_SQUARE in the marker's frame)."""
        marker = self.markers[view.marker_ids[0]]
        ok, rvec, tvec = cv2.solvePnP(square_object_points(marker.size_m), view.corner_normalised.reshape(4, 1, 2),
                                      np.eye(3), None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        if not ok:
            return None
        rotation, centre = camera_from_pnp(rvec, tvec)
        to_ned, marker_centre = marker_pose(marker)
        return to_ned @ rotation, marker_centre + to_ned @ centre
