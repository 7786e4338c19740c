"""Replay of recorded scans as a lidar backend, and the readers and writer of the recordings.

Formats:

- ``breezyslam``: the text logs of the BreezySLAM / CoreSLAM project (a Hokuyo URG-04LX with
  wheel odometry, e.g. ../shared/data/real/urg04lx-corridor-exp2.dat). One scan per line,
  whitespace separated: token 0 timestamp (microseconds), tokens 2 and 3 left and right wheel
  odometry (ticks), tokens 24 .. 705 the 682 ranges (millimetres, 0 = no return), one trailing
  token that BreezySLAM's own loader ignores too. The timestamp is taken as the capture time
  of the scan's first beam. The ticks become the scanner's odometry poses with BreezySLAM's
  model of the rover that recorded these logs (:data:`MINES_ROVER`, :func:`wheel_odometry`).

  Sweep direction, checked on the corridor recording: the beams run in Hokuyo step order,
  from the scanner's right to its left (counter-clockwise seen from above), beam i being step
  44 + i of the URG-04LX. Projecting scans 3 and 10 apart into the plane with the wheel odometry
  (heading change proportional to right minus left ticks, BreezySLAM's rover) makes the walls of
  the two scans coincide (median point-to-point distance 0.13 m over 20 windows turning by more
  than 10 degrees) with this order, and not with the reverse (0.39 m; this order wins 19 of 20
  and 48 of 55 windows). The data cannot rule out a mirror of both the beam order and the
  wheel assignment; the README's left/right wheel tokens settle it. Beam 340 (step 384, AFRT)
  is the front: the data's README says 341; the 0.35 degree difference is below what the
  recording can resolve.
  Ranges: readings below the model's DMIN (0 and the URG error codes 1..19 mm) are invalid;
  readings up to DMAX = 5.6 m are kept (the device is rated to 4 m; the file holds up to 5.58 m).

- ``carmen``: CARMEN logger logs (the Radish repository's FLASER / RLASER / ROBOTLASER1 /
  ROBOTLASER2 lines, plain or gzip; :func:`read_carmen`). Every laser message carries the
  robot's pose, which the "corrected" logs hold as the reference (kept by :func:`read_carmen`
  for scoring, never given to the pipelines). CARMEN frames are x forward / y left with angles
  counter-clockwise; ours are mirrored (FRD: y right, angles clockwise), so a beam at CARMEN
  angle ``a`` is at ``-a`` here and a CARMEN pose (x, y, theta) is NED (x, -y, -theta) in a
  map frame whose north is the log's x axis. FLASER / RLASER: ``n`` beams over 180 degrees,
  from the robot's right (CARMEN -90 deg) in steps of 180 / n degrees (the rear laser's turned
  by 180 deg); readings at the log's largest value (the scanner's maximum: 81.9, 50 or 32.7 m)
  or 0 are no return. ROBOTLASER lines give start angle, resolution and maximum range.

- ``ros``: ROS 1 bags (a ``.bag`` file) and ROS 2 bags (a directory with ``metadata.yaml``, or
  one of its ``.db3`` / ``.mcap`` files), read with the ``rosbags`` library (pure Python, no ROS
  install; :func:`read_ros_bag`). The scans are a ``sensor_msgs/msg/LaserScan`` topic: the header
  stamp is the capture time of the first beam, beam i at ``angle_min + i * angle_increment``,
  a reading valid when finite and within ``[range_min, range_max]``. The reference pose is a
  ``nav_msgs/msg/Odometry`` or ``geometry_msgs/msg/PoseStamped`` topic, interpolated to each
  scan's stamp. ROS frames (REP-103: x forward, y left, angles counter-clockwise) are mirrored
  like CARMEN's, with the same conversion (:func:`mirrored_angles`, :func:`mirrored_pose`).

- ``npz``: our own recordings (:func:`record_npz`): arrays ``t_capture`` (S,) s,
  ``angles_rad`` (N,), ``ranges_m`` (S, N), ``valid`` (S, N), ``sweep_s`` (S,), ``sequence`` (S,)
  and the scalar ``sensor_id``.

Timing: scan i is stamped ``t_open + (t_i - t_first) / rate_scale`` on the daemon clock and
delivered when its sweep is over, ``sweep_s / rate_scale`` later (``asyncio.sleep`` on the daemon
clock, so lockstep works); sweep times shrink with ``rate_scale`` too. With ``loop`` the
recording starts over, one median scan period after its last scan, with sequence numbers
going on. ``Scan.sequence`` is the record's index in the recording (plus its length per pass
before), so a corrupt record leaves a gap. A malformed line raises
:class:`~drivers.base.CorruptFrame` (the frontend counts and skips it); the end raises
:class:`~drivers.base.EndOfData`.
"""

from __future__ import annotations

import asyncio
import gzip
import io
import math
import stat
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, TypeVar

import numpy as np

from companion.frames import euler_from_quat, wrap_pi
from companion.plugins import register_backend
from companion.schema import meta, read_regular_file
from drivers.base import Backend, CorruptFrame, EndOfData
from drivers.lidar_models import URG_04LX
from companion.messages import Scan

BREEZYSLAM_BEAMS = 682
_BREEZYSLAM_FIRST_RANGE = 24
_BREEZYSLAM_TOKENS = (_BREEZYSLAM_FIRST_RANGE + BREEZYSLAM_BEAMS, _BREEZYSLAM_FIRST_RANGE + BREEZYSLAM_BEAMS + 1)
RECORDING_MAX_BYTES = 256 << 20  # hours of scans (the BreezySLAM corridor log is 1.4 MB)


def read_recording(path: str | Path) -> bytes:
    """The bytes of the recording file at ``path``; OSError if it is not a regular file of at most
    :data:`RECORDING_MAX_BYTES` (a FIFO or /dev/zero is refused, never read)."""
    return read_regular_file(path, RECORDING_MAX_BYTES)


def _text_lines(path: str | Path) -> Iterator[tuple[int, str]]:
    """(1-based number, line) of a text recording; bytes that are not ASCII read as U+FFFD."""
    return enumerate(io.TextIOWrapper(io.BytesIO(read_recording(path)), encoding="ascii", errors="replace"), start=1)


def breezyslam_angles() -> np.ndarray:
    """(682,) sensor-frame angles (radians, positive to the right) of a BreezySLAM line's beams."""
    return URG_04LX.angles_rad()


def parse_breezyslam_line(line: str) -> tuple[float, np.ndarray, np.ndarray]:
    """(timestamp s, ranges m (682,) with 0 = no return, odometry ticks (2,) left, right) of one
    line; ValueError if it is malformed."""
    tokens = line.split()
    if len(tokens) not in _BREEZYSLAM_TOKENS:
        raise ValueError(f"{len(tokens)} tokens, expected {' or '.join(map(str, _BREEZYSLAM_TOKENS))}")
    ranges_mm = np.array(tokens[_BREEZYSLAM_FIRST_RANGE:_BREEZYSLAM_FIRST_RANGE + BREEZYSLAM_BEAMS], dtype=np.int64)
    if (ranges_mm < 0).any():
        raise ValueError("negative range")
    return int(tokens[0]) * 1e-6, ranges_mm * 1e-3, np.array([int(tokens[2]), int(tokens[3])], dtype=np.int64)


def read_breezyslam(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A whole BreezySLAM log: (timestamps s (S,), ranges m (S, 682) with 0 = no return,
    wheel odometry ticks (S, 2) as [left, right]); ValueError naming the first bad line."""
    stamps, ranges, odometry = [], [], []
    for number, line in _text_lines(path):
        try:
            stamp, r, odo = parse_breezyslam_line(line)
        except ValueError as exc:
            raise ValueError(f"{path}:{number}: {exc}") from None
        stamps.append(stamp)
        ranges.append(r)
        odometry.append(odo)
    return (np.array(stamps), np.array(ranges).reshape(-1, BREEZYSLAM_BEAMS),
            np.array(odometry, dtype=np.int64).reshape(-1, 2))


@dataclass(frozen=True)
class WheelRig:
    """A differential-drive robot's odometry geometry, as BreezySLAM's ``WheeledVehicle`` models it."""

    wheel_radius_m: float
    half_axle_m: float  # wheel to the axle's middle, m
    ticks_per_wheel_turn: float
    scanner_ahead_m: float  # the scanner's centre ahead of the axle's middle, m


# The rover of the BreezySLAM logs (BreezySLAM's examples/mines.py: wheels of 77 mm, half axle 165 mm,
# laser 145 mm ahead). Its ``ticks * 180 / 2000`` degrees per wheel, taken by BreezySLAM's
# computePoseChange with twice the textbook distance and turn, is 2000 ticks per wheel turn; the
# corridor log's walls line up with that (tests/test_real_corridor.py), not with half of it.
MINES_ROVER = WheelRig(wheel_radius_m=0.077, half_axle_m=0.165, ticks_per_wheel_turn=2000.0, scanner_ahead_m=0.145)


def wheel_odometry(ticks: np.ndarray, rig: WheelRig = MINES_ROVER, heading_scale: float = 1.0) -> np.ndarray:
    """(S, 3) scanner poses [x north m, y east m, yaw rad] (FRD: yaw grows clockwise seen from
    above) integrated from wheel ticks (S, 2) [left, right], in the frame of the first scan's axle
    (so the first pose is ``(scanner_ahead_m, 0, 0)``). Each step moves the axle's middle by the
    mean of the wheel arcs along the mean heading of the step and turns it by (left - right) /
    (2 half axle), times ``heading_scale`` (an effective-track calibration; 1: the rig's)."""
    metres_per_tick = 2.0 * math.pi / rig.ticks_per_wheel_turn * rig.wheel_radius_m
    arcs = np.diff(np.asarray(ticks, dtype=float), axis=0) * metres_per_tick  # (S-1, 2) [left, right]
    forward = arcs.mean(axis=1)
    turn = heading_scale * (arcs[:, 0] - arcs[:, 1]) / (2.0 * rig.half_axle_m)
    yaw = np.concatenate(([0.0], np.cumsum(turn)))
    heading = yaw[:-1] + 0.5 * turn
    x = np.concatenate(([0.0], np.cumsum(forward * np.cos(heading))))
    y = np.concatenate(([0.0], np.cumsum(forward * np.sin(heading))))
    return np.column_stack((x + rig.scanner_ahead_m * np.cos(yaw), y + rig.scanner_ahead_m * np.sin(yaw), yaw))


def breezyslam_valid(ranges_m: np.ndarray) -> np.ndarray:
    """The readings of a BreezySLAM log that are returns (within the URG-04LX's range)."""
    return (ranges_m >= URG_04LX.min_range_m) & (ranges_m <= URG_04LX.max_range_m)


def mirrored_angles(angles_rad: np.ndarray) -> np.ndarray:
    """Beam angles (rad) of a frame mirrored to ours (x forward, y left, counter-clockwise: CARMEN's,
    ROS REP-103's) in our scanner frame (positive to the right), wrapped to (-pi, pi]."""
    return np.angle(np.exp(-1j * np.asarray(angles_rad, dtype=float)))


def mirrored_pose(x: float, y: float, theta: float) -> tuple[float, float, float]:
    """A pose (x, y m, theta rad counter-clockwise) in a mirrored map frame (CARMEN's, ROS REP-103's)
    as NED (x north, y east m, yaw rad) in a map frame whose north is that frame's x axis."""
    return x, -y, -theta


CARMEN_LASERS = {"FLASER": "front", "RLASER": "rear", "ROBOTLASER1": "front", "ROBOTLASER2": "rear"}
_CARMEN_OLD_TAIL = 9  # x y theta odom_x odom_y odom_theta timestamp hostname logger_timestamp
_CARMEN_ROBOT_TAIL = 14  # laser pose (3), robot pose (3), tv rv, 3 distances, timestamp host logger_timestamp


@dataclass(frozen=True)
class CarmenScan:
    """One laser message of a CARMEN log, in our frames (module docstring)."""

    laser: str  # "front" or "rear"
    t_s: float  # the log's timestamp, s
    angles_rad: np.ndarray  # (n,) sensor frame, positive to the right
    ranges_m: np.ndarray  # (n,) metres as logged (no return: see ``max_range_m``)
    max_range_m: float | None  # the message's maximum range (ROBOTLASER), None for FLASER / RLASER
    pose_ned: tuple[float, float, float]  # the log's robot pose: x, y (m, NED map frame), yaw (rad)
    odometry_ned: tuple[float, float, float] | None = None  # FLASER / RLASER: the odometry pose, same frame


def parse_carmen_line(line: str) -> CarmenScan | None:
    """The laser message of one CARMEN log line; None for other messages (ODOM, PARAM, comments);
    ValueError if a laser line is malformed."""
    tokens = line.split()
    if not tokens or tokens[0] not in CARMEN_LASERS:
        return None
    laser = CARMEN_LASERS[tokens[0]]
    try:
        if tokens[0].startswith("ROBOTLASER"):
            start, _fov, step, max_range = (float(v) for v in tokens[2:6])
            n = int(tokens[8])
            ranges = np.array(tokens[9:9 + n], dtype=float)
            remissions = int(tokens[9 + n])
            tail = tokens[10 + n + remissions:]
            if len(tail) != _CARMEN_ROBOT_TAIL:
                raise ValueError(f"{len(tail)} values after the readings, expected {_CARMEN_ROBOT_TAIL}")
            x, y, theta = (float(v) for v in tail[3:6])
            stamp, carmen_angles = float(tail[11]), start + step * np.arange(n)
            maximum: float | None = max_range
            odometry = None
        else:
            n = int(tokens[1])
            ranges = np.array(tokens[2:2 + n], dtype=float)
            tail = tokens[2 + n:]
            if len(tail) != _CARMEN_OLD_TAIL:
                raise ValueError(f"{len(tail)} values after the readings, expected {_CARMEN_OLD_TAIL}")
            x, y, theta = (float(v) for v in tail[0:3])
            ox, oy, otheta = (float(v) for v in tail[3:6])
            stamp, maximum, odometry = float(tail[6]), None, mirrored_pose(ox, oy, otheta)
            carmen_angles = -math.pi / 2 + math.pi / n * np.arange(n) + (math.pi if laser == "rear" else 0.0)
    except (IndexError, ValueError) as exc:
        raise ValueError(f"malformed {tokens[0]} line: {exc}") from None
    if ranges.size != n or n == 0:
        raise ValueError(f"malformed {tokens[0]} line: {ranges.size} of {n} readings")
    if not np.isfinite(ranges).all() or not all(map(math.isfinite, (x, y, theta, stamp, *(odometry or ())))):
        raise ValueError(f"malformed {tokens[0]} line: a reading, a pose or the time is not a finite number")
    return CarmenScan(laser, stamp, mirrored_angles(carmen_angles), ranges, maximum, mirrored_pose(x, y, theta),
                      odometry)


def carmen_valid(scan: CarmenScan, log_max_m: float) -> np.ndarray:
    """(n,) bool: the readings that are returns: above 0 and below the message's maximum range, or
    (FLASER / RLASER, which do not carry it) below ``log_max_m``, the largest reading of the log."""
    limit = scan.max_range_m if scan.max_range_m is not None else log_max_m
    return (scan.ranges_m > 0.0) & (scan.ranges_m < limit - 1e-6)


def read_carmen(path: str | Path, laser: str = "front") -> list[CarmenScan]:
    """The ``laser`` ("front" or "rear") messages of a CARMEN log (plain or gzip), in file order;
    ValueError naming the first malformed line."""
    data = read_recording(path)
    if data[:2] == b"\x1f\x8b":
        data = gzip.decompress(data)
    scans = []
    for number, line in enumerate(io.TextIOWrapper(io.BytesIO(data), encoding="ascii", errors="replace"), start=1):
        try:
            scan = parse_carmen_line(line)
        except ValueError as exc:
            raise ValueError(f"{path}:{number}: {exc}") from None
        if scan is not None and scan.laser == laser:
            scans.append(scan)
    return scans


ROS_SCAN_TYPE = "sensor_msgs/msg/LaserScan"
ROS_ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
ROS_POSE_TYPES = (ROS_ODOMETRY_TYPE, "geometry_msgs/msg/PoseStamped")
_T = TypeVar("_T")


@dataclass(frozen=True)
class BagScan:
    """One ``sensor_msgs/msg/LaserScan`` message of a ROS bag, in our frames (module docstring)."""

    t_s: float  # header stamp: the capture time of the first beam, s (the bag's clock)
    angles_rad: np.ndarray  # (n,) scanner frame, positive to the right (the ROS angles negated)
    ranges_m: np.ndarray  # (n,) metres as recorded
    valid: np.ndarray  # (n,) bool: finite and within [range_min, range_max]
    pose_ned: tuple[float, float, float] | None  # the pose topic's at t_s: x, y (m, NED map frame), yaw (rad)


def read_ros_bag(path: str | Path, scan_topic: str | None = None, pose_topic: str | None = None) -> list[BagScan]:
    """The LaserScan messages of ``scan_topic`` in a ROS 1 bag (``.bag`` file) or a ROS 2 bag (its
    directory, ``.db3`` or ``.mcap`` file), in bag order, each with the pose of ``pose_topic`` (an
    Odometry or PoseStamped topic) at its stamp: positions linear in time between the two nearest
    pose messages, yaw along the shorter arc, None outside the pose messages' time span.

    Default topics: the bag's only LaserScan topic (ValueError naming the candidates when it has
    several or none) and its only Odometry / PoseStamped topic (no pose when it has several or
    none). The pose is taken as the scanner's: a mounting offset in /tf is not applied. ValueError
    for a bag that cannot be decoded, OSError when it cannot be read; both name ``path``."""
    path = Path(path)
    topics = _with_bag(path, lambda reader: {name: info.msgtype for name, info in reader.topics.items()})
    scan_topics = sorted(name for name, kind in topics.items() if kind == ROS_SCAN_TYPE)
    chosen = _chosen_topic(path, scan_topics, scan_topic, "--scan-topic")
    if chosen is None:
        listing = ", ".join(f"{name} ({kind})" for name, kind in sorted(topics.items())) or "none"
        raise ValueError(f"{path}: several LaserScan topics ({', '.join(scan_topics)}): choose one with --scan-topic"
                         if scan_topics else f"{path}: no LaserScan topic; the bag's topics: {listing}")
    pose_chosen = _chosen_topic(path, sorted(name for name, kind in topics.items() if kind in ROS_POSE_TYPES),
                                pose_topic, "--pose-topic")
    messages = _with_bag(path, lambda reader: _decoded(reader, {chosen, pose_chosen}))
    times, poses = _pose_track(path, [message for topic, message in messages if topic == pose_chosen])
    scans = [message for topic, message in messages if topic == chosen]
    return [_bag_scan(path, k, message, times, poses) for k, message in enumerate(scans)]


def _with_bag(path: Path, use: Callable[[Any], _T]) -> _T:
    """``use`` applied to the bag at ``path`` opened with rosbags' ``AnyReader``; what goes wrong
    inside rosbags as OSError (cannot be read) or ValueError (cannot be decoded), naming ``path``."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    mode = path.stat().st_mode
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):  # a FIFO would block the reader
        raise OSError(f"{path}: not a bag file or directory")
    try:  # ROS 2 bags before Iron hold no message definitions: the standard ones (these types never changed)
        with AnyReader([path], default_typestore=get_typestore(Stores.LATEST)) as reader:
            return use(reader)
    except OSError as exc:
        raise OSError(f"{path}: cannot read the bag: {exc}") from exc
    except Exception as exc:  # a damaged bag raises many kinds in rosbags (its own, sqlite's, KeyError, ...)
        raise ValueError(f"{path}: not a readable ROS 1 or ROS 2 bag (rosbags: {exc})") from exc


def _decoded(reader: Any, topics: set[str | None]) -> list[tuple[str, Any]]:
    """(topic, deserialized message) of the messages of ``topics`` in an open ``AnyReader``, in bag order."""
    connections = [c for c in reader.connections if c.topic in topics]
    return [(c.topic, reader.deserialize(raw, c.msgtype)) for c, _, raw in reader.messages(connections)]


def _chosen_topic(path: Path, candidates: list[str], asked: str | None, option: str) -> str | None:
    """``asked`` when it is one of ``candidates`` (ValueError if not), else the only candidate, else None."""
    if asked is None:
        return candidates[0] if len(candidates) == 1 else None
    if asked not in candidates:
        raise ValueError(f"{path}: {option} {asked}: not a topic of that type in the bag "
                         f"(those: {', '.join(candidates) or 'none'})")
    return asked


def _stamp_s(message: Any) -> float:
    """The header stamp of a ROS message, s."""
    return message.header.stamp.sec + message.header.stamp.nanosec * 1e-9


def _pose_track(path: Path, messages: list[Any]) -> tuple[np.ndarray, np.ndarray]:
    """(times s (P,), poses (P, 3): x, y m, yaw rad, NED) of Odometry / PoseStamped messages, by time."""
    rows = []
    for m in messages:
        pose = m.pose.pose if m.__msgtype__ == ROS_ODOMETRY_TYPE else m.pose
        q = pose.orientation
        yaw = euler_from_quat(np.array([q.w, q.x, q.y, q.z]))[2]  # about z up: counter-clockwise
        rows.append((_stamp_s(m), *mirrored_pose(pose.position.x, pose.position.y, yaw)))
    track = np.array(rows, dtype=float).reshape(-1, 4)
    if not np.isfinite(track).all():
        raise ValueError(f"{path}: a pose message whose position or orientation is not a finite number")
    track = track[np.argsort(track[:, 0], kind="stable")]
    return track[:, 0], track[:, 1:]


def _pose_at(times: np.ndarray, poses: np.ndarray, t: float) -> tuple[float, float, float] | None:
    """The pose (x, y m, yaw rad) at ``t`` s between the two nearest of ``poses`` at sorted ``times``:
    position linear in time, yaw along the shorter arc; None outside [times[0], times[-1]]."""
    if not len(times) or not times[0] <= t <= times[-1]:
        return None
    i = int(np.searchsorted(times, t, side="right")) - 1  # times[i] <= t < times[i + 1]
    j = min(i + 1, len(times) - 1)
    a, b = poses[i], poses[j]
    f = (t - times[i]) / (times[j] - times[i]) if times[j] > times[i] else 0.0
    return (float(a[0] + f * (b[0] - a[0])), float(a[1] + f * (b[1] - a[1])),
            wrap_pi(float(a[2] + f * wrap_pi(float(b[2] - a[2])))))


def _bag_scan(path: Path, k: int, message: Any, times: np.ndarray, poses: np.ndarray) -> BagScan:
    """LaserScan message ``k`` (0-based) in our frames, with its pose; ValueError for non-finite angles."""
    if not (math.isfinite(message.angle_min) and math.isfinite(message.angle_increment)):
        raise ValueError(f"{path}: LaserScan message {k + 1}: angle_min or angle_increment is not a finite number")
    ranges = np.asarray(message.ranges, dtype=float)
    valid = np.isfinite(ranges) & (ranges >= message.range_min) & (ranges <= message.range_max)
    t = _stamp_s(message)
    angles = mirrored_angles(message.angle_min + message.angle_increment * np.arange(ranges.size))
    return BagScan(t, angles, ranges, valid, _pose_at(times, poses, t))


def read_npz(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """An npz recording (:func:`record_npz`): beam angles (N,) rad, capture times (S,) s, ranges
    (S, N) m, valid (S, N), sweep times (S,) s; OSError if it is not one."""
    try:
        with np.load(io.BytesIO(read_recording(path))) as data:
            angles = np.asarray(data["angles_rad"], dtype=float)
            t, ranges, valid = data["t_capture"], data["ranges_m"], data["valid"]
            sweep = data["sweep_s"] if "sweep_s" in data else np.zeros(len(t))
    except (KeyError, ValueError) as exc:
        raise OSError(f"{path}: not a scan recording: {exc}") from exc
    shape = (len(t), len(angles))
    if t.ndim != 1 or angles.ndim != 1 or ranges.shape != shape or valid.shape != shape or sweep.shape != t.shape:
        raise OSError(f"{path}: inconsistent arrays: t_capture {t.shape}, angles_rad "
                      f"{angles.shape}, ranges_m {ranges.shape}, valid {valid.shape}, sweep_s {sweep.shape}")
    return angles, np.asarray(t, dtype=float), np.asarray(ranges, dtype=float), np.asarray(valid, dtype=bool), sweep


def record_npz(path: str | Path, scans: Sequence[Scan]) -> None:
    """Write ``scans`` (one sensor, same beam angles, at least one) as an npz recording."""
    if not scans:
        raise ValueError("no scans to record")
    angles = scans[0].angles_rad
    if any(s.angles_rad.shape != angles.shape or not np.array_equal(s.angles_rad, angles) for s in scans):
        raise ValueError("all scans of a recording must have the same beam angles")
    np.savez_compressed(
        path, sensor_id=np.array(scans[0].sensor_id), angles_rad=angles,
        t_capture=np.array([s.t_capture for s in scans]), ranges_m=np.stack([s.ranges_m for s in scans]),
        valid=np.stack([s.valid for s in scans]), sweep_s=np.array([s.sweep_s for s in scans]),
        sequence=np.array([s.sequence for s in scans], dtype=np.int64),
    )


@dataclass(frozen=True)
class ReplayLidarSettings:
    """``settings:`` of a lidar with ``backend: replay`` (a companion.schema dataclass)."""

    file: str = field(metadata=meta("The recording; a relative path is relative to the config file's directory."))
    format: Literal["breezyslam", "carmen", "npz"] = field(default="npz", metadata=meta(
        "breezyslam: a BreezySLAM/CoreSLAM URG-04LX text log; carmen: a CARMEN logger log (FLASER, RLASER, "
        "ROBOTLASER1/2 lines; plain or gzip); npz: written by drivers.lidar_replay.record_npz."))
    laser: Literal["front", "rear"] = field(default="front", metadata=meta(
        "carmen: which laser's messages (FLASER / ROBOTLASER1: front, RLASER / ROBOTLASER2: rear)."))
    rate_scale: float = field(default=1.0, metadata=meta(
        "Replay speed: 1 = the recorded timing, 2 = twice as fast.", (0.01, 1000)))
    loop: bool = field(default=False, metadata=meta("Start over at the end instead of ending."))


@dataclass(frozen=True)
class _Record:
    """One recorded scan before stamping; ``error`` set when it could not be decoded."""

    t_s: float  # recording time, s (nan when unknown)
    ranges_m: np.ndarray
    valid: np.ndarray
    sweep_s: float
    error: str | None = None


class ReplayLidar(Backend[Scan]):
    """Plays a recording back as scans on the daemon clock (see the module docstring);
    ``settings.file`` is resolved against ``base_dir`` (the config file's directory)."""

    def __init__(self, sensor_id: str, settings: ReplayLidarSettings, base_dir: Path = Path(".")) -> None:
        self.sensor_id = sensor_id
        self.settings = settings
        self.path = base_dir / settings.file
        self.description = f"replay of {self.path.name}"
        self._angles = np.empty(0)
        self._records: list[_Record] = []
        self._index = 0  # next record
        self._pass_base = 0  # sequence number of the first record on the current pass
        self._offset = 0.0  # daemon time of recording time 0 on the current pass, s
        self._last_t = math.nan  # recording time of the last good record on this pass, s

    async def open(self) -> None:
        """Load the recording (OSError if it cannot be read) and start at its first scan now."""
        if self.settings.format == "breezyslam":
            self._load_breezyslam()
        elif self.settings.format == "carmen":
            self._load_carmen()
        else:
            self._load_npz()
        for record in self._records:  # scans share these arrays, on every pass
            record.ranges_m.flags.writeable = False
            record.valid.flags.writeable = False
        self._angles.flags.writeable = False
        self._index = 0
        self._pass_base = 0
        self._last_t = math.nan
        first = next((r.t_s for r in self._records if r.error is None), 0.0)
        self._offset = asyncio.get_running_loop().time() - first / self.settings.rate_scale

    def _load_breezyslam(self) -> None:
        self._angles = breezyslam_angles()
        records = []
        sweep = URG_04LX.sweep_s
        for number, line in _text_lines(self.path):
            try:
                stamp, ranges, _ = parse_breezyslam_line(line)
            except ValueError as exc:
                records.append(_Record(math.nan, np.empty(0), np.empty(0, bool), 0.0, f"line {number}: {exc}"))
                continue
            valid = breezyslam_valid(ranges)
            records.append(_Record(stamp, np.where(valid, ranges, 0.0), valid, sweep))
        self._records = records

    def _load_carmen(self) -> None:
        try:
            scans = read_carmen(self.path, self.settings.laser)
        except ValueError as exc:
            raise OSError(str(exc)) from exc
        if not scans:
            raise OSError(f"{self.path}: no {self.settings.laser} laser message")
        self._angles = scans[0].angles_rad
        log_max = max(float(scan.ranges_m.max()) for scan in scans)
        self._records = [
            _Record(scan.t_s, scan.ranges_m, carmen_valid(scan, log_max), 0.0) if np.array_equal(scan.angles_rad, self._angles)
            else _Record(math.nan, np.empty(0), np.empty(0, bool), 0.0, f"message {k + 1}: other beam angles than the first")
            for k, scan in enumerate(scans)]

    def _load_npz(self) -> None:
        self._angles, t, ranges, valid, sweep = read_npz(self.path)
        self._records = [_Record(float(t[i]), ranges[i], valid[i], float(sweep[i])) for i in range(len(t))]

    async def read(self) -> Scan:
        """The next recorded scan, at its replay time; CorruptFrame for a bad record, EndOfData
        at the end (unless looping)."""
        if self._index >= len(self._records):
            if not self.settings.loop or not any(r.error is None for r in self._records):
                raise EndOfData(f"{self.description}: all {len(self._records)} scans replayed")
            self._start_next_pass()
        record = self._records[self._index]
        self._index += 1
        if record.error is not None:
            raise CorruptFrame(record.error)
        if not math.isnan(self._last_t) and record.t_s < self._last_t:
            raise CorruptFrame(f"record {self._index}: time goes back from {self._last_t:.6f} s to {record.t_s:.6f} s")
        self._last_t = record.t_s
        scale = self.settings.rate_scale
        t_capture = self._offset + record.t_s / scale
        sweep = record.sweep_s / scale
        loop = asyncio.get_running_loop()
        await asyncio.sleep(max(0.0, t_capture + sweep - loop.time()))
        return Scan(self.sensor_id, t_capture, self._angles, record.ranges_m, record.valid,
                    sweep_s=sweep, sequence=self._pass_base + self._index - 1)

    def _start_next_pass(self) -> None:
        """Begin the recording again, one median scan period after the last scan played."""
        times = np.array([r.t_s for r in self._records if r.error is None])
        period = float(np.median(np.diff(times))) if len(times) > 1 else 0.1
        self._offset += (self._last_t + period - times[0]) / self.settings.rate_scale
        self._pass_base += len(self._records)
        self._index = 0
        self._last_t = math.nan

    async def close(self) -> None:
        """Forget the loaded recording."""
        self._records = []


def _check_recording(cfg: Any, name: str) -> None:
    """check-config: the recording named by ``sensors.<name>.settings.file`` can be read."""
    cfg.load_referenced(f"sensors.{name}.settings.file", cfg.sensors[name].settings["file"], read_recording)


@register_backend("lidar", "replay", ReplayLidarSettings, check_files=_check_recording)
def _replay(name: str, settings: ReplayLidarSettings, ctx: Any) -> ReplayLidar:
    """A recording played back on the daemon clock."""
    return ReplayLidar(name, settings, base_dir=ctx.base_dir)
