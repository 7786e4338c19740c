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

Mapping error model (:meth:`FloorMapper.floor_covariance`): a corner's floor residual has a
1-sigma per axis ``s`` = the larger of the fit's residual estimate ``sqrt(SSR / (2n - 8))`` (n
corners, 8 parameters; none for one marker) and ``corner_sigma_px`` times the floor metres per
pixel. The homography's 8 parameters then have the covariance ``s^2 (A^T A)^-1`` (A: the
Jacobian of the 2n corner mappings with respect to them), and a point maps with the covariance
``J s^2 (A^T A)^-1 J^T`` (J: its mapping's Jacobian with respect to the parameters). This grows
as a point lies farther outside the markers' hull: a dot mapped through markers all on one side
of the image (extrapolation) is as uncertain as it is, not as a point among them.
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
TRACKED_MIN_PERIMETER_RATE = 0.6  # of a tracking box's larger side: a marker of side >= 15 % of it


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
    # Tracking: given the camera pose expected for an image (the previous frame's), each marker is
    # looked for only in its predicted box grown by the larger of these (px; fraction of the box's
    # size), at most ``max_tracked_markers`` of them (the nearest the image centre); fewer than
    # ``min_tracked_markers`` found there: the whole image is searched.
    track_margin_px: int = 25
    track_margin_fraction: float = 0.5
    min_tracked_markers: int = 2
    max_tracked_markers: int = 6


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


def homography_jacobian(homography: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 2, 8) derivatives of the images of (N, 2) points under ``homography`` (scaled to
    h33 = 1) with respect to its other 8 entries, row by row."""
    h = homography / homography[2, 2]
    x, y = points[:, 0], points[:, 1]
    w = h[2, 0] * x + h[2, 1] * y + 1.0
    mapped = apply_homography(h, points)
    zero = np.zeros_like(x)
    row_x = np.column_stack((x / w, y / w, 1.0 / w, zero, zero, zero, -mapped[:, 0] * x / w, -mapped[:, 0] * y / w))
    row_y = np.column_stack((zero, zero, zero, x / w, y / w, 1.0 / w, -mapped[:, 1] * x / w, -mapped[:, 1] * y / w))
    return np.stack((row_x, row_y), axis=1)


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
        self._marker_ids = tuple(self.markers)
        self._floor_corners = {i: m.corners() for i, m in self.markers.items()}  # (4, 2) north, east m
        corners = [np.column_stack((c, np.zeros(4))) for c in self._floor_corners.values()]
        self._corners_ned = np.concatenate(corners) if corners else np.zeros((0, 3))  # (4M, 3), for tracking
        self.params = params
        detector_params = cv2.aruco.DetectorParameters()
        detector_params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        detector_params.cornerRefinementWinSize = params.subpix_window_px
        detector_params.adaptiveThreshWinSizeStep = params.threshold_window_step_px
        self.detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(dictionary), detector_params)
        # In a tracking box the marker is most of the crop: contours smaller than 15 % of the
        # box's side (the floor's texture) are not candidates, which is most of the search's cost.
        detector_params.minMarkerPerimeterRate = TRACKED_MIN_PERIMETER_RATE
        self.box_detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(dictionary), detector_params)

    def find(self, image: np.ndarray, predicted: tuple[np.ndarray, np.ndarray] | None = None) -> FloorView | None:
        """The floor view of ``image`` ((H, W) grey or (H, W, 3) BGR uint8), or None if no marker of
        the world is seen once. ``predicted``: the camera pose (rotation optical -> NED, centre NED
        m) expected for this image, e.g. the previous frame's: markers are then looked for around
        where it puts them (``FloorParams``' tracking), which costs a fraction of a whole-image search."""
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        found = None if predicted is None else self.tracked_markers(grey, *predicted)
        if found is None or len(found[0]) < self.params.min_tracked_markers:
            found = self.known_markers(grey)
        marker_ids, pixels, ignored = found
        if not marker_ids:
            return None
        normalised = self.calibration.undistort_points(pixels.reshape(-1, 2))
        floor = np.concatenate([self._floor_corners[i] for i in marker_ids])
        homography, _ = cv2.findHomography(normalised, floor, 0)
        if homography is None:
            return None
        residuals = apply_homography(homography, normalised) - floor
        _, jacobian = map_pixels(self.calibration, homography, pixels.reshape(-1, 2))
        return FloorView(homography, marker_ids, pixels, normalised.reshape(-1, 4, 2), len(floor),
                         float(np.sqrt(np.mean(np.sum(residuals ** 2, axis=1)))),
                         float(np.mean(np.sqrt(np.abs(np.linalg.det(jacobian))))), ignored)

    def predicted_boxes(self, optical_to_ned: np.ndarray, centre_ned: np.ndarray) -> dict[int, tuple[slice, slice]]:
        """{marker id: (rows, columns)} of the image where a camera at this pose (rotation optical ->
        NED, centre NED m) sees each world marker whole, each box grown by the tracking margin and
        clipped to the image; at most ``max_tracked_markers``, the nearest the image centre."""
        p, cal = self.params, self.calibration
        pixels = cal.project((self._corners_ned - centre_ned) @ optical_to_ned).reshape(-1, 4, 2)
        size = np.array([cal.width - 1, cal.height - 1])
        whole = np.all(np.isfinite(pixels) & (pixels >= 0) & (pixels <= size), axis=(1, 2))
        low, high = pixels[whole].min(axis=1), pixels[whole].max(axis=1)
        margin = np.maximum(p.track_margin_px, p.track_margin_fraction * (high - low).max(axis=1))[:, None]
        lo, hi = np.floor(low - margin).astype(int), np.ceil(high + margin).astype(int) + 1
        offset = np.linalg.norm((low + high) / 2 - size / 2, axis=1)
        ids = np.array(self._marker_ids)[whole]
        return {int(ids[k]): (slice(max(lo[k, 1], 0), min(hi[k, 1], cal.height)),
                              slice(max(lo[k, 0], 0), min(hi[k, 0], cal.width)))
                for k in np.argsort(offset, kind="stable")[:p.max_tracked_markers]}

    def tracked_markers(self, grey: np.ndarray, optical_to_ned: np.ndarray,
                        centre_ned: np.ndarray) -> tuple[tuple[int, ...], np.ndarray, int]:
        """As :meth:`known_markers`, each marker looked for only in its predicted box
        (:meth:`predicted_boxes`); a detection of another id in a box is not counted."""
        ids, pixels = [], []
        for marker_id, (rows, cols) in self.predicted_boxes(optical_to_ned, centre_ned).items():
            corners, found, _ = self.box_detector.detectMarkers(np.ascontiguousarray(grey[rows, cols]))
            hits = [] if found is None else [k for k, i in enumerate(found.ravel()) if int(i) == marker_id]
            if len(hits) == 1:
                ids.append(marker_id)
                pixels.append(corners[hits[0]].reshape(4, 2) + [cols.start, rows.start])
        return tuple(ids), np.array(pixels, dtype=float).reshape(-1, 4, 2), 0

    def known_markers(self, grey: np.ndarray) -> tuple[tuple[int, ...], np.ndarray, int]:
        """(ids, (M, 4, 2) corner pixels, count of the other detections) of the world's markers
        detected exactly once in the whole (H, W) grey image."""
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

    def floor_covariance(self, view: FloorView, pixels: np.ndarray) -> np.ndarray:
        """(N, 2, 2) covariance (m^2, [north, east]) of the homography's mapping of the (N, 2)
        pixels (the model of the module docstring; NaN rows give NaN)."""
        dof = 2 * view.n_points - HOMOGRAPHY_PARAMETERS
        residual_sigma = math.sqrt(view.n_points * view.rms_m ** 2 / dof) if dof > 0 else 0.0
        corner_sigma = max(residual_sigma, self.params.corner_sigma_px * view.metres_per_px)
        corners = homography_jacobian(view.homography, view.corner_normalised.reshape(-1, 2)).reshape(-1, HOMOGRAPHY_PARAMETERS)
        parameters = corner_sigma ** 2 * np.linalg.pinv(corners.T @ corners)
        points = homography_jacobian(view.homography, self.calibration.undistort_points(pixels))
        return points @ parameters @ points.transpose(0, 2, 1)

    def camera_pose(self, view: FloorView) -> tuple[np.ndarray, np.ndarray] | None:
        """(rotation optical -> NED (3x3), camera centre NED (3,) m) from the markers alone, or
        None if solvePnP fails: cv2.SOLVEPNP_IPPE_SQUARE on a single marker, cv2.SOLVEPNP_ITERATIVE
        on all the corners of several (both on the undistorted corners)."""
        if len(view.marker_ids) == 1:
            return self._single_marker_pose(view)
        floor = np.concatenate([self._floor_corners[i] for i in view.marker_ids])
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
