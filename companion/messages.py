"""The typed messages between drivers, pipelines and the edges (like PX4's ``msg/``).

Drivers produce sensor messages (:class:`Scan`, :class:`Frame`, :class:`ImuSample`,
:class:`GnssFix`, :class:`LandmarkSightings`, :class:`FlowField`); pipelines consume them and
produce estimates (:class:`PoseEstimate`, :class:`AttitudeEstimate`, :class:`RangeEstimate`); the
estimate-source selection and the
MAVLink and telemetry edges consume those. This module imports numpy only: pipelines import it
and nothing from ``companion.mavlink``, ``companion.telemetry`` or ``sitl``.

Frames (one convention everywhere, README "Frames and units"):

- world: MAVLink LOCAL_NED at the autopilot's EKF origin (north, east, down; metres);
- body: FRD (forward, right, down) at the vehicle's reference point;
- a sensor frame is placed in the body frame by its configured mount (``sensors.<name>.mount``).

Times: every ``t_capture`` is the daemon's monotonic clock (``companion.clock.now``), seconds,
at the instant the data was captured (not when it arrived).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np


# -- sensor messages ------------------------------------------------------------------------

@dataclass(frozen=True)
class Scan:
    """One sweep of a 2-D scanner.

    Sensor frame (FRD like the body): x along the scanner's front (Hokuyo step AFRT), y to its
    right, z down through its base when it stands upright. A beam at angle ``a`` points along
    ``(cos a, sin a, 0)``, so positive angles turn from the front towards the right (clockwise
    seen from above).
    """

    sensor_id: str
    t_capture: float  # daemon clock, s: time of the first beam
    angles_rad: np.ndarray  # (N,) beam angles in the sensor frame
    ranges_m: np.ndarray  # (N,) float64 metres; meaningless where not valid
    valid: np.ndarray  # (N,) bool: a real return within [min, max] range
    sweep_s: float = 0.0  # time from the first to the last beam, s (per-beam time = linear)
    sequence: int = 0  # increases by one per scan from this sensor (gaps = lost scans)

    def __post_init__(self) -> None:
        n = self.angles_rad.shape
        if self.ranges_m.shape != n or self.valid.shape != n or len(n) != 1:
            raise ValueError("angles_rad, ranges_m and valid must be 1-D arrays of one length")

    @property
    def valid_count(self) -> int:
        return int(np.count_nonzero(self.valid))

    def points(self) -> np.ndarray:
        """(M, 2) x, y of the valid returns in the sensor frame, metres, in beam order."""
        r = self.ranges_m[self.valid]
        a = self.angles_rad[self.valid]
        return np.column_stack((r * np.cos(a), r * np.sin(a)))


@dataclass(frozen=True)
class Frame:
    """One camera image.

    Pixels (u, v) = (column, row) with integer values at pixel centres, as OpenCV's functions
    take them; OpenCV's optical frame is x right, y down, z along the axis. The mount
    (``sensors.<name>.mount``) places the camera's FRD sensor frame (x along the axis, y to the
    image's right, z to its bottom) in the body frame: drivers/mount.py, ``OPTICAL_TO_SENSOR``.
    """

    camera_id: str
    t_capture: float  # daemon clock, s: mid-exposure when the backend knows it
    image: np.ndarray  # (H, W) uint8 grey or (H, W, 3) uint8 BGR, as OpenCV delivers
    sequence: int = 0  # increases by one per frame from this camera (gaps = lost frames)
    exposure_s: float | None = None  # exposure time, s, if the backend knows it

    def __post_init__(self) -> None:
        if self.image.ndim not in (2, 3) or (self.image.ndim == 3 and self.image.shape[2] != 3):
            raise ValueError(f"image must be (H, W) or (H, W, 3), got shape {self.image.shape}")


@dataclass(frozen=True)
class ImuSample:
    """One IMU reading in body FRD: specific force (m/s^2; about (0, 0, -9.81) at rest, level)
    and angular rate (rad/s), at ``t`` (daemon clock, s: the sample time mapped onto it).

    ``euler_rad`` is the autopilot's own attitude estimate (roll, pitch, yaw of body FRD in
    NED, rad) newest at this sample, and ``velocity_ned`` its own velocity estimate (NED m/s,
    LOCAL_POSITION_NED, at most a second old), when the IMU comes from the autopilot; None otherwise.
    ``pressure_alt_m``: the barometric altitude sent with the sample (HIGHRES_IMU ``pressure_alt``,
    m, up; the autopilot's datum: only its changes mean something), None if not sent.
    """

    t: float
    accel_body: np.ndarray  # (3,) m/s^2, body FRD
    gyro_body: np.ndarray  # (3,) rad/s, body FRD
    euler_rad: tuple[float, float, float] | None = None
    velocity_ned: np.ndarray | None = None  # (3,) m/s
    pressure_alt_m: float | None = None  # m, up


GNSS_NO_FIX, GNSS_2D, GNSS_3D, GNSS_DGPS, GNSS_RTK_FLOAT, GNSS_RTK_FIXED = 1, 2, 3, 4, 5, 6  # MAVLink GPS_FIX_TYPE


@dataclass(frozen=True)
class GnssFix:
    """One GNSS solution (WGS-84).

    ``fix_type`` uses MAVLink's GPS_FIX_TYPE numbers (0 no GPS, 1 no fix, 2 2-D, 3 3-D, 4 DGPS,
    5 RTK float, 6 RTK fixed). Accuracies are 1-sigma; None when the receiver does not say.
    """

    receiver_id: str
    t_capture: float  # daemon clock, s: the solution's epoch (receiver latency removed when known)
    fix_type: int
    lat_deg: float
    lon_deg: float
    alt_m: float  # above mean sea level, m
    velocity_ned_mps: np.ndarray | None = None  # (3,) Doppler velocity north, east, down, m/s; down NaN if not measured
    h_acc_m: float | None = None  # horizontal position accuracy, m
    v_acc_m: float | None = None  # vertical position accuracy, m
    speed_acc_mps: float | None = None  # velocity accuracy, m/s
    satellites: int | None = None
    jamming: bool = False  # the receiver (or the simulation) reports interference

    @property
    def has_position(self) -> bool:
        return self.fix_type >= GNSS_2D


@dataclass(frozen=True)
class LandmarkSightings:
    """The point landmarks one sensor frame saw (a vision sensor, a marker detector): a range and
    two bearings to each, with known identities (the landmark ids).

    Level heading frame at the sensor: ``azimuth_rad`` from the vehicle's heading (the body's
    forward axis projected on the horizontal) towards its right, i.e. ``atan2(d_east, d_north) -
    yaw``, wrapped to +-pi; ``elevation_rad`` from the horizontal, positive *up*
    (``atan2(-d_down, horizontal distance)``: a landmark on the ground below the vehicle has a
    negative elevation); ``range_m`` the straight-line distance. The d's are landmark minus
    sensor in NED, metres. ``sigma`` is the sensor's stated 1-sigma noise (range m, azimuth
    rad, elevation rad) for every landmark of the frame (the largest, when they differ);
    ``sigmas``, if given, each landmark's own (a marker's range noise grows with its distance, its
    azimuth's near the nadir).
    """

    sensor_id: str
    t_capture: float  # daemon clock, s: when the frame was captured
    ids: np.ndarray  # (N,) int landmark ids
    range_m: np.ndarray  # (N,) m
    azimuth_rad: np.ndarray  # (N,) rad, clockwise from the heading seen from above
    elevation_rad: np.ndarray  # (N,) rad, above the horizontal (negative below)
    sigma: tuple[float, float, float]  # 1-sigma range m, azimuth rad, elevation rad
    sequence: int = 0  # increases by one per frame of this sensor
    sigmas: np.ndarray | None = None  # (N, 3) each landmark's 1-sigma (as sigma), rows in the order of ids

    def __post_init__(self) -> None:
        n = np.shape(self.ids)
        if len(n) != 1 or any(np.shape(a) != n for a in (self.range_m, self.azimuth_rad, self.elevation_rad)):
            raise ValueError("ids, range_m, azimuth_rad and elevation_rad must be 1-D arrays of one length")
        if self.sigmas is not None and np.shape(self.sigmas) != (n[0], 3):
            raise ValueError("sigmas must be an (N, 3) array, one row per id")

    def sigma_of(self) -> dict[int, tuple[float, float, float]] | tuple[float, float, float]:
        """Each id's 1-sigma if the frame states them per landmark, else the frame's one."""
        if self.sigmas is None:
            return self.sigma
        return {int(i): (float(r[0]), float(r[1]), float(r[2])) for i, r in zip(self.ids, self.sigmas)}


@dataclass(frozen=True)
class FlowField:
    """The image motion one flow sensor measured between two instants (an optic-flow map, as the
    GNSS + optic-flow seed's vision model gives one): no image, no calibration needed.

    Normalised image coordinates of the camera's optical frame (OpenCV's: x right, y down, z along
    the axis; a ray (x, y, 1), so x = X / Z, y = Y / Z). The mount (``sensors.<name>.mount``) places
    the camera's FRD sensor frame in the body frame exactly as a camera's (:class:`Frame`,
    drivers/mount.py ``OPTICAL_TO_SENSOR``). ``points_n`` are where the grid points lie in the
    earlier view, ``flows_n`` where they moved to in the later view minus that: a point seen at
    ``p`` at ``t_earlier`` is seen at ``p + flow`` at ``t_capture``. Invalid points (not tracked,
    or nothing there to track: sky) carry no meaning in ``flows_n`` (NaN allowed there).
    """

    sensor_id: str
    t_earlier: float  # daemon clock, s: capture of the earlier view
    t_capture: float  # daemon clock, s: capture of the later view (the message's stamp)
    points_n: np.ndarray  # (N, 2) grid points (x, y) in the earlier view, normalised image coordinates
    flows_n: np.ndarray  # (N, 2) their displacement to the later view, normalised image coordinates
    valid: np.ndarray  # (N,) bool: the flow of this point was measured
    sequence: int = 0  # increases by one per field from this sensor (gaps = lost fields)

    def __post_init__(self) -> None:
        n = np.shape(self.valid)
        if len(n) != 1 or np.shape(self.points_n) != (n[0], 2) or np.shape(self.flows_n) != (n[0], 2):
            raise ValueError("points_n and flows_n must be (N, 2) and valid (N,)")


# -- estimates --------------------------------------------------------------------------------

@dataclass(frozen=True)
class PoseEstimate:
    """One navigation estimate in the project frame (LOCAL_NED at the EKF origin, body FRD)."""

    t_capture: float  # daemon monotonic clock, seconds: when the sensor data was captured
    position_ned: np.ndarray  # (3,) metres
    euler_rad: tuple[float, float, float]  # roll, pitch, yaw of body FRD in NED, radians
    pose_covariance: np.ndarray  # (6, 6) over x, y, z (m^2) and roll, pitch, yaw (rad^2)
    velocity_ned: np.ndarray | None = None  # (3,) m/s
    velocity_covariance: np.ndarray | None = None  # (3, 3) (m/s)^2
    reset: bool = False  # True when the estimate jumped (e.g. relocalization)
    source: str = ""  # the pipeline that made it
    degraded: bool = False  # the pipeline's health is degraded (e.g. coasting on the IMU without fixes)

    def __post_init__(self) -> None:
        if np.shape(self.position_ned) != (3,) or np.shape(self.pose_covariance) != (6, 6):
            raise ValueError("position_ned must be (3,) and pose_covariance (6, 6)")
        if (self.velocity_ned is None) != (self.velocity_covariance is None):
            raise ValueError("velocity_ned and velocity_covariance go together")
        if self.velocity_ned is not None and (np.shape(self.velocity_ned) != (3,)
                                              or np.shape(self.velocity_covariance) != (3, 3)):
            raise ValueError("velocity_ned must be (3,) and velocity_covariance (3, 3)")

    def is_finite(self) -> bool:
        """True if every number the autopilot would receive is finite.

        Tested on their sum: a NaN or an infinity makes it non-finite, and values an autopilot can
        take (MAVLink floats, below 3.4e38) cannot add up to an overflow."""
        total = (float(np.sum(self.position_ned)) + float(np.sum(self.pose_covariance))
                 + sum(self.euler_rad) + self.t_capture)
        if self.velocity_ned is not None:
            total += float(np.sum(self.velocity_ned)) + float(np.sum(self.velocity_covariance))
        return bool(np.isfinite(total))


@dataclass(frozen=True)
class AttitudeEstimate:
    """An attitude-only estimate (roll, pitch, yaw of body FRD in NED, rad) with its 3x3
    covariance (rad^2). A cross-check of the autopilot's attitude: never sent as a pose. An angle
    the source cannot observe is NaN (e.g. yaw from the tilt of the floor), its variance inf."""

    t_capture: float
    euler_rad: tuple[float, float, float]
    covariance: np.ndarray  # (3, 3) rad^2
    source: str = ""


@dataclass(frozen=True)
class RangeEstimate:
    """A distance along one body direction, e.g. the height above the ground (``orientation``
    "down"), sent to the autopilot as DISTANCE_SENSOR."""

    t_capture: float
    distance_m: float
    variance_m2: float
    min_m: float = 0.1  # the valid span the autopilot is told, m
    max_m: float = 40.0
    orientation: Literal["down", "forward", "up"] = "down"
    source: str = ""


Estimate = PoseEstimate | AttitudeEstimate | RangeEstimate


# -- guidance ---------------------------------------------------------------------------------

@dataclass(frozen=True)
class Guidance:
    """Where a pipeline that flies the vehicle itself (the EKF-SLAM return to base) wants it now.

    ``kind``: ``fly`` (track ``position_ned`` with ``velocity_ned`` as feed-forward), ``hold``
    (stay at ``position_ned``; e.g. nothing in view and the search given up) or ``land`` (land
    where it is). ``position_ned`` is in the frame of the estimates the same pipeline sends (LOCAL_NED
    at the EKF origin, m), ``velocity_ned`` m/s, ``yaw_rad`` the heading to fly (rad from north,
    None: keep it). ``trigger`` says why the pipeline took over (``gnss_lost``, ``commanded``);
    ``reason`` what it is doing (for telemetry and logs)."""

    t: float  # daemon clock, s
    kind: Literal["fly", "hold", "land"]
    position_ned: np.ndarray  # (3,) m
    velocity_ned: np.ndarray  # (3,) m/s
    yaw_rad: float | None
    trigger: str
    reason: str

    def is_finite(self) -> bool:
        """True if every number a setpoint would carry is finite."""
        yaw = [] if self.yaw_rad is None else [self.yaw_rad]
        return bool(np.all(np.isfinite(self.position_ned)) and np.all(np.isfinite(self.velocity_ned))
                    and np.all(np.isfinite(yaw)))

