"""The one frame convention used everywhere in this project.

World frame: MAVLink LOCAL_NED at the autopilot's EKF origin (x north, y east, z down, metres).
Body frame: FRD (x forward, y right, z down).
Attitude: unit quaternion ``q = [w, x, y, z]`` (MAVLink order) rotating body vectors into NED,
``v_ned = R(q) @ v_body``; Euler angles are aerospace ZYX (yaw about z, then pitch, then roll),
radians, yaw measured from north towards east.

Geodetic conversion uses a local tangent plane at the origin (flat earth); over an indoor
arena or a few kilometres the error is far below a millimetre per metre.
"""

from __future__ import annotations

import math

import numpy as np

EARTH_RADIUS_M = 6_378_137.0  # WGS-84 equatorial radius
GRAVITY_MPS2 = 9.80665


def quat_from_euler(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Quaternion [w, x, y, z] (body FRD -> NED) from ZYX Euler angles in radians."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return np.array(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]
    )


def euler_from_quat(q: np.ndarray) -> tuple[float, float, float]:
    """ZYX Euler angles (roll, pitch, yaw) in radians from a quaternion [w, x, y, z]."""
    w, x, y, z = (float(v) for v in q)
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def rotation_from_quat(q: np.ndarray) -> np.ndarray:
    """3x3 rotation matrix R (body FRD -> NED) of a quaternion [w, x, y, z]."""
    w, x, y, z = (float(v) for v in q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotation_from_euler(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """3x3 rotation matrix (body FRD -> NED) from ZYX Euler angles in radians."""
    return rotation_from_quat(quat_from_euler(roll, pitch, yaw))


def euler_from_rotation(rotation: np.ndarray) -> tuple[float, float, float]:
    """ZYX Euler angles (roll, pitch, yaw) in radians of a rotation matrix body FRD -> NED: the
    inverse of :func:`rotation_from_euler` (pitch within [-pi/2, pi/2])."""
    r = np.asarray(rotation, dtype=float)
    roll = math.atan2(r[2, 1], r[2, 2])
    pitch = math.asin(max(-1.0, min(1.0, -r[2, 0])))
    yaw = math.atan2(r[1, 0], r[0, 0])
    return roll, pitch, yaw


def euler_yaw_rate(gyro_body: np.ndarray, roll: float, pitch: float) -> float:
    """ZYX Euler yaw rate (rad/s) of body FRD rates ``gyro_body`` (p, q, r rad/s) at ``roll``,
    ``pitch`` (rad): ``(q sin roll + r cos roll) / cos pitch``, the cosine kept above 1e-3."""
    q, r = float(gyro_body[1]), float(gyro_body[2])
    return (q * math.sin(roll) + r * math.cos(roll)) / max(math.cos(pitch), 1e-3)


def wrap_pi(angle: float) -> float:
    """Angle wrapped to [-pi, pi)."""
    return (angle + math.pi) % (2 * math.pi) - math.pi


def planar_rotation(yaw: float) -> np.ndarray:
    """2-D rotation (2, 2) from a levelled body frame (x forward, y right) at ``yaw`` (rad, from
    north towards east) to the world's (north, east)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s], [s, c]])


def planar_increment(a: tuple[float, float, float], b: tuple[float, float, float]) -> tuple[float, float, float]:
    """The motion from planar pose ``a`` to ``b`` (x north, y east m, yaw rad) in ``a``'s body
    frame: (forward m, right m, turn rad)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return c * dx + s * dy, -s * dx + c * dy, wrap_pi(b[2] - a[2])


def planar_moved(pose: tuple[float, float, float], forward: float, right: float,
                 turn: float = 0.0) -> tuple[float, float, float]:
    """Planar ``pose`` (x north, y east m, yaw rad) moved by ``forward``, ``right`` (m, its body
    frame) and turned by ``turn`` (rad): the inverse of :func:`planar_increment`."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return pose[0] + c * forward - s * right, pose[1] + s * forward + c * right, wrap_pi(pose[2] + turn)


def ned_from_geodetic(
    lat_deg: float, lon_deg: float, alt_m: float, origin: tuple[float, float, float]
) -> np.ndarray:
    """NED position (m) of a WGS-84 point relative to ``origin`` = (lat deg, lon deg, alt m AMSL)."""
    lat0, lon0, alt0 = origin
    north = math.radians(lat_deg - lat0) * EARTH_RADIUS_M
    east = math.radians(lon_deg - lon0) * EARTH_RADIUS_M * math.cos(math.radians(lat0))
    return np.array([north, east, alt0 - alt_m])


def geodetic_from_ned(
    ned: np.ndarray, origin: tuple[float, float, float]
) -> tuple[float, float, float]:
    """(lat deg, lon deg, alt m AMSL) of an NED position (m) relative to ``origin``."""
    lat0, lon0, alt0 = origin
    lat = lat0 + math.degrees(float(ned[0]) / EARTH_RADIUS_M)
    lon = lon0 + math.degrees(float(ned[1]) / (EARTH_RADIUS_M * math.cos(math.radians(lat0))))
    return lat, lon, alt0 - float(ned[2])
