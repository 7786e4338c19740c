"""Fiducial markers seen by a calibrated camera as landmark sightings: the camera path of the
EKF-SLAM's observations (the simulated Table 1 sensor is the other, sitl/landmark_sensor.py).

Per frame (:meth:`MarkerSighter.sightings`): ArUco markers of one dictionary are detected
(``cv2.aruco.ArucoDetector``, sub-pixel corners); each marker's pose comes from its four corners,
undistorted with the calibration, by ``cv2.solvePnP`` with ``SOLVEPNP_IPPE_SQUARE`` for the known
side ``size_m`` (floor.py's ``square_object_points``: the object origin is the marker's centre, so
the solution's translation is the centre in the optical frame). The centre goes to body FRD by the
camera mount (rotation optical -> body, camera origin in body FRD, m: the vector then starts at the
body origin, the vehicle position the SLAM estimates), then to the *level heading frame* (NED turned
by the yaw only) by the roll and pitch at the frame's capture time, which the caller gives (the
autopilot's). Range, azimuth and elevation are :class:`companion.messages.LandmarkSightings`'s
(model.py's ``observe``): range m, azimuth rad clockwise from the heading seen from above,
elevation rad above the horizontal (a marker on the ground below: negative). The marker's id is
the landmark's id.

Skipped, and counted: markers whose id lies outside ``id_range`` (another use of the same
dictionary, e.g. the laser-dot floor's), ids detected more than once in a frame (which one is the
landmark?), and markers whose PnP fails or puts the centre behind the camera.

Noise (first-order, from ``pixel_sigma_px``, the 1-sigma error of a refined corner per axis):
the direction to the centre is taken as uncertain by ``pixel_sigma_px / f`` rad (f the focal
length, px; one corner's error, conservative for a centre fixed by four, and covering a
calibration's residual), so elevation sigma = that and azimuth sigma = that / cos(elevation)
(near the nadir the azimuth is poorly defined); the range follows the marker's apparent side s
(mean edge length, px) as ``r = f size / s``, and an edge between two corners has the error
``sqrt(2) pixel_sigma_px``, so range sigma = ``r * sqrt(2) * pixel_sigma_px / s``. The
attitude's own error (roll and pitch from the caller) is not included. The sightings carry each
marker's sigmas (``LandmarkSightings.sigmas``) and, as the frame's one ``sigma``, the largest of
them; an empty frame states zeros.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from companion.calibration import CameraCalibration
from companion.frames import rotation_from_euler
from companion.messages import Frame, LandmarkSightings
from companion.nav.ekf_slam.model import observe
from companion.nav.laser_dots.floor import square_object_points
from companion.world import ARUCO_DICTIONARY

SUBPIX_WINDOW_PX = 3  # half-size of the corner refinement window, px: a 4x4 marker 30 px across has 5 px cells
# Adaptive-threshold windows every 20 px (OpenCV: 10), as floor.py's: the same sightings of the
# rendered test frames (tests/test_ekf_slam_markers.py), 23 instead of 31 ms a 640x480 frame here.
# (CORNER_REFINE_APRILTAG removes the +0.5 % range bias of sub-pixel corners there, but it found a
# marker in the floor's texture in one of 24 such frames; SUBPIX none.)
THRESHOLD_WINDOW_STEP_PX = 20


@dataclass(frozen=True)
class MarkerParams:
    """What :class:`MarkerSighter` looks for and its noise model (module docstring)."""

    size_m: float  # side of a marker's black square, m
    dictionary: int = ARUCO_DICTIONARY  # OpenCV DICT_ constant
    id_range: tuple[int, int] = (0, 999999)  # lowest, highest id of a marker that is a landmark
    pixel_sigma_px: float = 0.5  # 1-sigma of a refined corner per axis, px


@dataclass(frozen=True)
class MarkerFrame:
    """What one frame gave: the ``sightings`` (level heading frame, body origin, each landmark's
    own 1-sigma in ``sightings.sigmas``; module docstring) and the markers skipped by reason."""

    sightings: LandmarkSightings
    outside_id_range: int = 0  # markers of ids outside MarkerParams.id_range
    ambiguous: int = 0  # markers of an id seen more than once in the frame
    failed: int = 0  # markers whose PnP failed (or put the centre behind the camera)


class MarkerSighter:
    """Landmark sightings from the markers in the frames of one camera of ``calibration``, mounted
    with ``optical_to_body`` (3x3 rotation, OpenCV optical frame -> body FRD) at
    ``camera_origin_body`` (m, body FRD); ``sensor_id`` names the sightings' sensor."""

    def __init__(self, calibration: CameraCalibration, optical_to_body: np.ndarray, camera_origin_body: np.ndarray,
                 params: MarkerParams, sensor_id: str) -> None:
        self.calibration = calibration
        self.optical_to_body = np.asarray(optical_to_body, dtype=float)
        self.camera_origin_body = np.asarray(camera_origin_body, dtype=float)
        self.params = params
        self.sensor_id = sensor_id
        self._object = square_object_points(params.size_m)
        self._focal_px = float(math.sqrt(calibration.K[0, 0] * calibration.K[1, 1]))
        detector_params = cv2.aruco.DetectorParameters()
        detector_params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        detector_params.cornerRefinementWinSize = SUBPIX_WINDOW_PX
        detector_params.adaptiveThreshWinSizeStep = THRESHOLD_WINDOW_STEP_PX
        self.detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(params.dictionary), detector_params)

    def sightings(self, frame: Frame, roll_rad: float, pitch_rad: float) -> MarkerFrame:
        """The landmarks ``frame`` shows, levelled with the vehicle's ``roll_rad`` and ``pitch_rad``
        (body FRD in NED, rad) at its capture time."""
        grey = frame.image if frame.image.ndim == 2 else cv2.cvtColor(frame.image, cv2.COLOR_BGR2GRAY)
        corners, found, _ = self.detector.detectMarkers(grey)
        detected = [] if found is None else [int(i) for i in found.ravel()]
        low, high = self.params.id_range
        inside = [k for k, i in enumerate(detected) if low <= i <= high]
        unique = [k for k in inside if detected.count(detected[k]) == 1]
        level = rotation_from_euler(roll_rad, pitch_rad, 0.0)  # body FRD -> level heading frame
        ids, observations, sigmas = [], [], []
        for k in unique:
            pixels = corners[k].reshape(4, 2).astype(float)
            centre = self._centre_optical(pixels)
            if centre is None:
                continue
            z = observe(np.zeros(3), 0.0, level @ (self.optical_to_body @ centre + self.camera_origin_body))
            ids.append(detected[k])
            observations.append(z)
            sigmas.append(self._sigma(z, pixels))
        z_all = np.array(observations, dtype=float).reshape(-1, 3)
        sigma_all = np.array(sigmas, dtype=float).reshape(-1, 3)
        largest = sigma_all.max(axis=0) if len(sigma_all) else np.zeros(3)
        stated = (float(largest[0]), float(largest[1]), float(largest[2]))
        sightings = LandmarkSightings(self.sensor_id, frame.t_capture, np.array(ids, dtype=int), z_all[:, 0],
                                      z_all[:, 1], z_all[:, 2], stated, frame.sequence, sigma_all)
        return MarkerFrame(sightings, len(detected) - len(inside), len(inside) - len(unique), len(unique) - len(ids))

    def _centre_optical(self, pixels: np.ndarray) -> np.ndarray | None:
        """The centre (3,) m in the optical frame of the marker with the (4, 2) corner ``pixels``
        (ArUco order), or None if the PnP fails or puts it behind the camera."""
        normalised = self.calibration.undistort_points(pixels).reshape(4, 1, 2)
        ok, _, tvec = cv2.solvePnP(self._object, normalised, np.eye(3), None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        centre = np.asarray(tvec, dtype=float).ravel() if ok else None
        return centre if centre is not None and np.all(np.isfinite(centre)) and centre[2] > 0.0 else None

    def _sigma(self, z: np.ndarray, pixels: np.ndarray) -> tuple[float, float, float]:
        """(range m, azimuth rad, elevation rad) 1-sigma of the observation ``z`` of the marker with
        the (4, 2) corner ``pixels`` (the first-order model of the module docstring)."""
        sigma_px = self.params.pixel_sigma_px
        side_px = float(np.mean(np.linalg.norm(pixels - np.roll(pixels, -1, axis=0), axis=1)))
        bearing = sigma_px / self._focal_px
        return (float(z[0]) * math.sqrt(2.0) * sigma_px / side_px, bearing / max(math.cos(float(z[2])), bearing),
                bearing)
