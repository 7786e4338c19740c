"""What each sensor kind's frontend refuses before a pipeline sees it, and its capture stamp.

One row per kind in :data:`KINDS`: the message type, the check ``(message, previous capture
time) -> problem or None``, and the capture time (daemon clock, s). Every check refuses a
non-finite capture time or one not after the previous message's, and the non-finite values
of its kind (a backend bug, a corrupt recording): a NaN never reaches a pipeline.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.health import Health
from companion.messages import FlowField, Frame, GnssFix, ImuSample, LandmarkSightings, Scan
from drivers.base import Backend, SensorDriver


def _time_problem(t: float, previous_t: float | None) -> str | None:
    if not math.isfinite(t):
        return "non-finite capture time"
    if previous_t is not None and t <= previous_t:
        return "capture time not after the previous one's"
    return None


def scan_problem(scan: Scan, previous_t: float | None) -> str | None:
    """A non-finite range (of a valid beam) or angle, or a bad capture time."""
    problem = _time_problem(scan.t_capture, previous_t)
    if problem is None and not (np.all(np.isfinite(scan.angles_rad)) and np.all(np.isfinite(scan.ranges_m[scan.valid]))):
        return "non-finite range or angle"
    return problem


def frame_problem(frame: Frame, previous_t: float | None) -> str | None:
    """An empty or non-8-bit image, or a bad capture time."""
    problem = _time_problem(frame.t_capture, previous_t)
    if problem is None and (frame.image.size == 0 or frame.image.dtype != np.uint8):
        return f"image empty or not 8-bit ({frame.image.dtype}, shape {frame.image.shape})"
    return problem


def imu_problem(sample: ImuSample, previous_t: float | None) -> str | None:
    """A non-finite specific force, rate, attached velocity or pressure altitude, or a bad sample time."""
    problem = _time_problem(sample.t, previous_t)
    if problem is None and not (np.all(np.isfinite(sample.accel_body)) and np.all(np.isfinite(sample.gyro_body))):
        return "non-finite acceleration or rate"
    if problem is None and sample.velocity_ned is not None and not np.all(np.isfinite(sample.velocity_ned)):
        return "non-finite velocity"
    if problem is None and sample.pressure_alt_m is not None and not math.isfinite(sample.pressure_alt_m):
        return "non-finite pressure altitude"
    return problem


def gnss_problem(fix: GnssFix, previous_t: float | None) -> str | None:
    """A position fix with a non-finite or out-of-range latitude, longitude or altitude, a non-finite
    north or east velocity (down may be NaN: not measured), or a bad capture time. A no-fix report passes (it says the receiver has no fix)."""
    problem = _time_problem(fix.t_capture, previous_t)
    if problem is not None or not fix.has_position:
        return problem
    if not (math.isfinite(fix.alt_m) and abs(fix.lat_deg) <= 90.0 and abs(fix.lon_deg) <= 180.0):
        return "latitude, longitude or altitude non-finite or out of range"
    if fix.velocity_ned_mps is not None and not np.all(np.isfinite(fix.velocity_ned_mps[:2])):
        return "non-finite horizontal velocity"
    return None


def landmarks_problem(sightings: LandmarkSightings, previous_t: float | None) -> str | None:
    """A non-finite or non-positive range, a non-finite bearing or noise, or a bad capture time."""
    problem = _time_problem(sightings.t_capture, previous_t)
    if problem is not None:
        return problem
    values = (sightings.azimuth_rad, sightings.elevation_rad, np.asarray(sightings.sigma, dtype=float))
    if not (all(np.all(np.isfinite(v)) for v in values) and np.all(sightings.range_m > 0.0)):
        return "non-finite bearing or noise, or a range not above 0"
    if len(np.unique(sightings.ids)) != len(sightings.ids):
        return "a landmark id twice in one frame"
    return None


def flow_problem(flow: FlowField, previous_t: float | None) -> str | None:
    """A non-finite point or valid flow, an earlier instant not before the later one, or a bad
    capture time (the later instant's)."""
    problem = _time_problem(flow.t_capture, previous_t)
    if problem is not None:
        return problem
    if not (math.isfinite(flow.t_earlier) and flow.t_earlier < flow.t_capture):
        return "earlier instant non-finite or not before the capture time"
    if not (np.all(np.isfinite(flow.points_n)) and np.all(np.isfinite(flow.flows_n[flow.valid]))):
        return "non-finite point or flow"
    return None


@dataclass(frozen=True)
class Kind:
    """A sensor kind: what its backends deliver and how the frontend checks and stamps it."""

    message: type
    check: Callable[[Any, float | None], str | None]
    stamp: Callable[[Any], float]


KINDS: dict[str, Kind] = {
    "lidar": Kind(Scan, scan_problem, lambda m: m.t_capture),
    "camera": Kind(Frame, frame_problem, lambda m: m.t_capture),
    "imu": Kind(ImuSample, imu_problem, lambda m: m.t),
    "gnss": Kind(GnssFix, gnss_problem, lambda m: m.t_capture),
    "landmarks": Kind(LandmarkSightings, landmarks_problem, lambda m: m.t_capture),
    "flow": Kind(FlowField, flow_problem, lambda m: m.t_capture),
}


def sensor_driver(kind: str, name: str, backend: Backend, health: Health) -> SensorDriver:
    """The frontend around ``backend`` with the check and stamp of ``kind``."""
    k = KINDS[kind]
    return SensorDriver(name, backend, health, k.check, k.stamp)
