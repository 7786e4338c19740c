"""Where a sensor sits on the vehicle: the sensor frame placed in the body frame.

Frames (companion/frames.py): body FRD; world LOCAL_NED; the lidar sensor frame of
:mod:`companion.messages` (x front, y right, z down through the base when upright). The mount
config gives the sensor origin in body FRD (``position_m``, metres) and the sensor frame's
orientation relative to body FRD as ZYX roll, pitch, yaw (``rpy_deg``, degrees), the same
convention as the vehicle attitude, so ``v_body = R_mount @ v_sensor + position``.

Examples: ``rpy_deg [0, 0, 90]`` turns the scanner's front to the body's right;
``rpy_deg [90, 0, 0]`` (roll 90 deg) stands the scan plane up so that it holds the body x
and z axes: the sensor's right (+90 deg beam) points down along body z, its left up.

A camera's sensor frame is FRD like a scanner's: x along the optical axis, y to the image's
right, z to the image's bottom, so a camera with ``rpy_deg [0, 0, 0]`` looks forward with the
image upright, and ``rpy_deg [0, -90, 0]`` looks down with the image's top towards the front.
OpenCV's optical frame (x right, y down, z along the axis: companion/calibration.py) is
``v_sensor = OPTICAL_TO_SENSOR @ v_optical``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.config import MountConfig
from companion.frames import rotation_from_euler, rotation_from_quat


OPTICAL_TO_SENSOR = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
"""Rotation from OpenCV's optical frame to a camera's sensor frame (see the module docstring)."""


def beam_directions(angles_rad: np.ndarray) -> np.ndarray:
    """(N, 3) unit beam directions in the sensor frame for beam angles (N,) in radians."""
    return np.column_stack((np.cos(angles_rad), np.sin(angles_rad), np.zeros_like(angles_rad)))


def _as_points3(points: np.ndarray) -> np.ndarray:
    """(N, 3) from (N, 2) planar sensor points (z = 0) or (N, 3) points."""
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] not in (2, 3):
        raise ValueError(f"points must be (N, 2) or (N, 3), got shape {points.shape}")
    if points.shape[1] == 2:
        return np.column_stack((points, np.zeros(len(points))))
    return points


@dataclass(frozen=True)
class Mount:
    """A rigid sensor mount: ``rotation`` (3x3, sensor -> body FRD) and ``offset_m`` (3,),
    the sensor origin in body FRD, metres."""

    rotation: np.ndarray
    offset_m: np.ndarray

    @classmethod
    def from_config(cls, cfg: MountConfig) -> Mount:
        """The mount of a sensor's ``mount:`` config section."""
        roll, pitch, yaw = (math.radians(v) for v in cfg.rpy_deg)
        return cls(rotation_from_euler(roll, pitch, yaw), np.array(cfg.position_m, dtype=float))

    def to_body(self, points_sensor: np.ndarray) -> np.ndarray:
        """(N, 3) body FRD points (m) of sensor-frame points (N, 2) or (N, 3), metres."""
        return _as_points3(points_sensor) @ self.rotation.T + self.offset_m

    def sensor_to_world(self, position_ned: np.ndarray, quat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rotation sensor -> NED (3x3), sensor origin in NED (3,) m) for a vehicle at
        ``position_ned`` (m) with attitude ``quat`` ([w, x, y, z], body FRD -> NED)."""
        body_to_ned = rotation_from_quat(quat)
        return body_to_ned @ self.rotation, np.asarray(position_ned, dtype=float) + body_to_ned @ self.offset_m

    def to_world(self, points_sensor: np.ndarray, position_ned: np.ndarray, quat: np.ndarray) -> np.ndarray:
        """(N, 3) NED points (m) of sensor-frame points (N, 2) or (N, 3) for a vehicle at
        ``position_ned`` (m) with attitude ``quat`` ([w, x, y, z], body FRD -> NED)."""
        rotation, origin = self.sensor_to_world(position_ned, quat)
        return _as_points3(points_sensor) @ rotation.T + origin
