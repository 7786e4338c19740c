"""`companion replay`: a recorded 2-D scanner log through the lidar pipeline's localizer, scored
against the log's own poses.

The log is read by the replay backend's readers (drivers/lidar_replay.py; a recording of this
daemon, ``--format companion``, by companion/recording/reader.py); every scan goes, in
log order, through the same :class:`~companion.nav.planar.PlanarLocalizer` the ``lidar``
pipeline builds (companion/nav/lidar_pipeline.py: its default thresholds, the map's survey error),
the scanner taken as the body (the log's poses are the scanner's). Nothing of the reference
reaches the localizer except, by default, the first pose as the start (what
``pipelines.lidar.initial_pose`` is on a vehicle; ``--start relocalize`` starts with none;
``--start map`` at the map's ``start``, which ``companion map build`` sets to the first scan's
pose: replaying the walk a map was built from, without poses of its own, starts where it began).

Motion between scans (``--odometry``), standing in for the fused IMU of a vehicle:

- ``log``: the increments of the log's own odometry poses (a BreezySLAM log's: its wheel ticks
  through BreezySLAM's model of its rover, drivers/lidar_replay.py ``wheel_odometry``);
- ``noisy``: the same with wheel-odometry errors drawn (``--seed``): each step's length and turn
  off by :data:`WHEEL_ERROR_FRACTION` (1-sigma) and the heading by
  :data:`WHEEL_ERROR_DEG_PER_M` per metre driven;
- ``none``: no motion: each scan is predicted at the pose held;
- ``auto`` (default): ``log`` when the log's odometry is its own (raw) odometry, ``noisy``
  when it equals the reference (the Radish "corrected" logs: the SLAM pose written into both
  fields, so the raw increments would hand the localizer the answer; a ROS bag's pose topic,
  both its reference and its odometry), ``none`` without odometry.

Scores (the report, :func:`score`), over the scans with a reference pose; a field is null when
the log has none:

- ``heading_rms_deg``, ``position_median_m``, ``position_p95_m``: of the measured fixes
  (corners or walls); the position error counts both directions, also the one a corridor's
  walls leave unmeasured;
- ``nees_mean``: 2-D position NEES of the measured fixes with their covariance (2 is consistent),
  and ``nees_band``, its 95 % band for the independent samples the fixes are worth;
  ``heading_nees_mean`` and ``heading_nees_band``: the same of their heading (1 is consistent),
  counting the reference's own heading error if given (``--reference-heading-sd-deg``);
- ``lost_fraction``: scans without a measured fix;
- ``relocalizations``, ``wrong_resets``: relocalization jumps, and those landing more than
  :data:`~companion.scoring.WRONG_RESET_M` from the reference;
- ``ms_per_scan_p50``: the localizer's wall time per scan on this machine.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np

from companion.frames import planar_increment, planar_moved, wrap_pi
from companion.nav.lidar_pipeline import LidarPipelineConfig, planar_localizer, planar_params
from companion.nav.planar import Mount2D, PlanarFix, PlanarParams
from companion.scoring import WRONG_RESET_M, heading_nees, mean_or_none, nees, nees_band
from companion.world import World

Pose = tuple[float, float, float]  # x north, y east (m), yaw (rad) in the log's map frame as NED
Odometry = Literal["auto", "log", "noisy", "none"]
FORMATS = ("carmen", "ros", "breezyslam", "npz", "companion")
WHEEL_ERROR_FRACTION = 0.05  # simulated wheel odometry: 1-sigma error, fraction of each step's length and turn
WHEEL_ERROR_DEG_PER_M = 1.0  # ... and 1-sigma heading error per metre driven, deg
SAME_POSE_M = 1e-6  # odometry this close to the reference everywhere is the reference


@dataclass(frozen=True)
class LogScan:
    """One scan of a log: beams in the scanner frame (angles rad, positive to the right; ranges
    m; valid = a return), the log's reference pose and odometry pose when it has them."""

    t_s: float
    angles_rad: np.ndarray
    ranges_m: np.ndarray
    valid: np.ndarray
    reference: Pose | None
    odometry: Pose | None

    def points(self) -> np.ndarray:
        """(N, 2) returns in the scanner frame (x forward, y right, m)."""
        return np.column_stack((self.ranges_m * np.cos(self.angles_rad), self.ranges_m * np.sin(self.angles_rad)))


@dataclass(frozen=True)
class ReplayStep:
    """What the localizer made of one scan, with the time it took (ms)."""

    scan: LogScan
    fix: PlanarFix | None
    ms: float


def read_log(path: str | Path, log_format: str, laser: str = "front", scan_topic: str | None = None,
             pose_topic: str | None = None) -> list[LogScan]:
    """The scans of ``path``; ValueError for a format not readable here or a malformed log,
    OSError when it cannot be read. ``laser``: carmen's; ``scan_topic``, ``pose_topic``: ros's
    (:func:`drivers.lidar_replay.read_ros_bag`, None: the bag's only one); ``scan_topic`` also
    companion's (:func:`recorded_scans`). A bag's pose topic is
    both its reference and its odometry, like the CARMEN "corrected" logs (so ``auto`` adds
    simulated wheel-odometry errors to it); a scan outside the pose topic's time span has neither."""
    from drivers.lidar_replay import (breezyslam_angles, breezyslam_valid, carmen_valid, read_breezyslam,
                                      read_carmen, read_npz, read_ros_bag, wheel_odometry)

    if log_format == "ros":
        return [LogScan(s.t_s, s.angles_rad, s.ranges_m, s.valid, s.pose_ned, s.pose_ned)
                for s in read_ros_bag(path, scan_topic, pose_topic)]
    if log_format == "carmen":
        scans = read_carmen(path, laser)
        log_max = max((float(s.ranges_m.max()) for s in scans), default=0.0)
        return [LogScan(s.t_s, s.angles_rad, s.ranges_m, carmen_valid(s, log_max), s.pose_ned, s.odometry_ned)
                for s in scans]
    if log_format == "breezyslam":
        stamps, ranges, ticks = read_breezyslam(path)
        angles = breezyslam_angles()
        return [LogScan(float(t), angles, r, breezyslam_valid(r), None, (float(x), float(y), float(yaw)))
                for t, r, (x, y, yaw) in zip(stamps, ranges, wheel_odometry(ticks))]
    if log_format == "npz":
        angles, stamps, ranges, valid, _ = read_npz(path)
        return [LogScan(float(t), angles, r, v, None, None) for t, r, v in zip(stamps, ranges, valid)]
    if log_format == "companion":
        return recorded_scans(path, scan_topic)
    raise ValueError(f"--format {log_format}: not a log format (those: {', '.join(FORMATS)})")


def recorded_scans(path: str | Path, scan_topic: str | None = None) -> list[LogScan]:
    """The scans of one scanner in a flight recording of this daemon (``record.enabled``; any
    part of it, companion/recording): the topic ``scan_topic`` (``/sensors/<name>``), by default
    the recording's only scanner. A recording holds no reference poses (a walk recorded to build
    a map has no map to localize in yet): ``map build`` places its scans by scan matching.
    ValueError (RecordingError) for a file that is no recording or a topic it does not hold."""
    from companion.messages import Scan
    from companion.recording.codec import decode_message, message_schema
    from companion.recording.reader import Recording

    schema = message_schema(Scan).name
    by_topic: dict[str, list[LogScan]] = {}
    # With the topic named, only its messages are decoded (a recording is mostly IMU, estimates, MAVLink).
    for msg in Recording.open(path).messages(None if scan_topic is None else {scan_topic}):
        if msg.schema == schema:
            scan = decode_message(Scan, msg.doc)
            by_topic.setdefault(msg.topic, []).append(
                LogScan(scan.t_capture, scan.angles_rad, scan.ranges_m, scan.valid, None, None))
    if scan_topic is None and len(by_topic) > 1:
        raise ValueError(f"{path}: scans of several scanners ({', '.join(sorted(by_topic))}): "
                         "choose one with --scan-topic")
    if scan_topic is not None and not by_topic:
        raise ValueError(f"{path}: no scan on {scan_topic}")
    return next(iter(by_topic.values()), [])


def resolve_odometry(scans: list[LogScan], odometry: Odometry) -> tuple[Odometry, str]:
    """The motion source ``auto`` stands for in this log (module docstring), and why."""
    has = all(s.odometry is not None for s in scans) and bool(scans)
    if odometry != "auto":
        if odometry != "none" and not has:
            raise ValueError(f"--odometry {odometry}: the log has no odometry poses")
        return odometry, "as asked"
    if not has:
        return "none", "the log has no odometry"
    same = all(s.reference is not None and math.dist(s.odometry[:2], s.reference[:2]) < SAME_POSE_M  # type: ignore[index]
               for s in scans)
    if same:
        return "noisy", "the log's odometry equals its reference: simulated wheel-odometry errors added"
    return "log", "the log's own odometry"


def with_wheel_error(step: Pose, rng: np.random.Generator) -> Pose:
    """``step`` (forward, right m; turn rad) with simulated wheel-odometry errors."""
    forward, right, turn = step
    length = math.hypot(forward, right)
    return (forward + rng.normal(0.0, WHEEL_ERROR_FRACTION * length),
            right + rng.normal(0.0, WHEEL_ERROR_FRACTION * length),
            turn + rng.normal(0.0, WHEEL_ERROR_FRACTION * abs(turn) + math.radians(WHEEL_ERROR_DEG_PER_M) * length))


def replay_params(odometry: Odometry, world_map: World) -> PlanarParams:
    """The ``lidar`` pipeline's localizer thresholds (its defaults, the map's survey error and wall
    direction error); without motion between scans the heading has no prediction to weigh wall
    families by."""
    params = planar_params(LidarPipelineConfig(horizontal_sensor="horizontal", vertical_sensor="vertical"),
                           world_map.survey_error_m, world_map.wall_direction_error_deg)
    if odometry == "none":
        params = replace(params, heading=replace(params.heading, prediction_sigma_deg=math.inf))
    return params


def replay(scans: list[LogScan], world_map: World, odometry: Odometry, start: Pose | None,
           seed: int = 0) -> list[ReplayStep]:
    """Every scan through the localizer, in order (``odometry``: already resolved, not ``auto``)."""
    localizer = planar_localizer(replay_params(odometry, world_map), world_map, Mount2D(), start)
    rng = np.random.default_rng(seed)
    steps = []
    previous: LogScan | None = None
    for scan in scans:
        prior, turn, moved = None, 0.0, (0.0, 0.0)
        if odometry != "none" and previous is not None:
            assert scan.odometry is not None and previous.odometry is not None
            step = planar_increment(previous.odometry, scan.odometry)
            forward, right, turn = with_wheel_error(step, rng) if odometry == "noisy" else step
            moved = (forward, right)
            held = localizer.pose
            if held is not None:  # dead reckoning from the pose held; the turn goes in as yaw_delta
                prior = planar_moved(held, forward, right)
        started = time.perf_counter()
        fix = localizer.update(scan.points(), prior, yaw_delta=turn, moved_m=moved, valid=scan.valid)
        steps.append(ReplayStep(scan, fix, (time.perf_counter() - started) * 1e3))
        previous = scan
    return steps


def score(steps: list[ReplayStep], reference_heading_sd_deg: float = 0.0) -> dict[str, float | int | None]:
    """The contract's fields (module docstring) of a replay; ``reference_heading_sd_deg``: the
    reference's own 1-sigma heading error (deg), added to each fix's heading variance for the
    heading NEES."""
    measured = [s for s in steps if s.fix is not None and s.fix.measured]
    scored = [s for s in measured if s.scan.reference is not None]
    referenced = any(s.scan.reference is not None for s in steps)
    resets = [s for s in steps if s.fix is not None and s.fix.relocalized]
    out: dict[str, float | int | None] = {
        "scans": len(steps),
        "heading_rms_deg": None, "position_median_m": None, "position_p95_m": None, "nees_mean": None, "nees_band": None,
        "heading_nees_mean": None, "heading_nees_band": None,
        "lost_fraction": 1.0 - len(measured) / len(steps) if steps else None,
        "relocalizations": len(resets),
        "wrong_resets": sum(math.dist((s.fix.x, s.fix.y), s.scan.reference[:2]) > WRONG_RESET_M  # type: ignore[union-attr]
                            for s in resets if s.scan.reference is not None) if referenced else None,
        "ms_per_scan_p50": float(np.median([s.ms for s in steps])) if steps else None,
    }
    if scored:
        fixes = [s.fix for s in scored]
        reference = np.array([s.scan.reference for s in scored])
        error = np.array([[f.x, f.y] for f in fixes]) - reference[:, :2]  # type: ignore[union-attr]
        heading = np.array([wrap_pi(f.yaw - r) for f, r in zip(fixes, reference[:, 2])])  # type: ignore[union-attr]
        distance = np.hypot(error[:, 0], error[:, 1])
        values = nees(error, np.array([f.covariance[:2, :2] for f in fixes]))  # type: ignore[union-attr]
        band = nees_band(values, 2)
        reference_var = math.radians(reference_heading_sd_deg) ** 2
        variances = [f.covariance[2, 2] + reference_var for f in fixes]  # type: ignore[union-attr]
        heading_values = heading_nees(heading, variances)
        heading_band = nees_band(heading_values, 1)
        out.update({
            "heading_rms_deg": math.degrees(math.sqrt(float(np.mean(heading ** 2)))),
            "position_median_m": float(np.median(distance)),
            "position_p95_m": float(np.percentile(distance, 95)),
            "nees_mean": mean_or_none(values),
            "nees_band": None if band is None else list(band),
            "heading_nees_mean": mean_or_none(heading_values),
            "heading_nees_band": None if heading_band is None else list(heading_band),
        })
    return out


def replay_report(log: str | Path, log_format: str, world_map: World, map_path: str | Path, *,
                  laser: str = "front", scan_topic: str | None = None, pose_topic: str | None = None,
                  odometry: Odometry = "auto", start: Literal["reference", "relocalize", "map"] = "reference",
                  seed: int = 0, reference_heading_sd_deg: float = 0.0) -> dict:
    """The replay report of ``log`` on ``world_map``: the contract's fields and what the replay used.
    ``start``: the log's first reference pose, none (relocalize), or the map's ``start`` pose;
    ``reference_heading_sd_deg``: the reference's own heading error (:func:`score`)."""
    if not (reference_heading_sd_deg >= 0.0 and math.isfinite(reference_heading_sd_deg)):
        raise ValueError(f"--reference-heading-sd-deg must be a finite value >= 0, got {reference_heading_sd_deg}")
    scans = read_log(log, log_format, laser, scan_topic, pose_topic)
    if not scans:
        raise ValueError(f"{log}: no scan to replay")
    mode, why = resolve_odometry(scans, odometry)
    initial = scans[0].reference if start == "reference" else None
    if start == "reference" and initial is None:
        raise ValueError("--start reference: the log has no reference pose; use --start map (a map built from "
                         "this log starts where it began) or --start relocalize")
    if start == "map":
        x, y, yaw_deg = world_map.start
        initial = (x, y, math.radians(yaw_deg))
    report = score(replay(scans, world_map, mode, initial, seed), reference_heading_sd_deg)
    return {**report, "log": str(log), "format": log_format, "map": str(map_path),
            "odometry": {"mode": mode, "why": why, "seed": seed if mode == "noisy" else None},
            "start": start, "reference": "the log's own poses" if scans[0].reference is not None else None,
            "reference_heading_sd_deg": reference_heading_sd_deg}
