"""`--format ros`: ROS 1 and ROS 2 bags of LaserScan messages with a pose topic, written here with
rosbags' writers from scans of the simulated arena rendered in ROS frames (REP-103: x forward,
y left, angles counter-clockwise: ours mirrored), read by drivers.lidar_replay.read_ros_bag,
replayed by `companion replay` and mapped by `companion map build`."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from companion.cli import main
from companion.nav.bench_stages import DEFAULT_WORLD
from companion.world import load_world
from drivers.lidar_replay import read_ros_bag
from drivers.mount import beam_directions
from sitl.raycast import WorldGeometry, cast
from companion.nav.bench_robustness import arena_path

SCAN, ODOMETRY, POSE = "sensor_msgs/msg/LaserScan", "nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped"
BEAMS = 271  # a UTM-30LX as its ROS driver publishes it: 1 deg steps over 270 deg, from the right
ANGLE_MIN, ANGLE_INCREMENT = math.radians(-135.0), math.radians(1.0)  # ROS: counter-clockwise
RANGE_MIN_M, RANGE_MAX_M = 0.1, 30.0
SCAN_HEIGHT_M = 1.0
T0_NS = 1_700_000_000 * 10**9  # the bag clock's start
POSE_STEP_NS = 80_000_000  # one pose message per 8 cm step of the arena path (1 m/s)
LAYOUTS = ("ros1", "ros2", "db3", "mcap")  # a .bag; a ROS 2 directory (sqlite3); its .db3 file; an .mcap file

Message = tuple[str, str, int, Any]  # topic, type, stamp ns, payload: ranges (LaserScan) or an NED pose (x, y, yaw)


def _ros_message(store: Any, ros1: bool, kind: str, stamp_ns: int, payload: Any) -> Any:
    """A ``kind`` message of ``store``; a pose payload (x, y, yaw NED) goes into the ROS map frame as
    (x, -y, -yaw)."""
    t = store.types
    header = t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9),
        frame_id="laser" if kind == SCAN else "map", **({"seq": 0} if ros1 else {}))
    if kind == SCAN:
        ranges = np.asarray(payload, dtype=np.float32)
        return t[SCAN](header=header, angle_min=ANGLE_MIN, angle_max=ANGLE_MIN + (len(ranges) - 1) * ANGLE_INCREMENT,
                       angle_increment=ANGLE_INCREMENT, time_increment=0.0, scan_time=0.025, range_min=RANGE_MIN_M,
                       range_max=RANGE_MAX_M, ranges=ranges, intensities=np.zeros(0, np.float32))
    x, y, yaw = payload
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=float(x), y=-float(y), z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(-yaw / 2), w=math.cos(-yaw / 2)))
    if kind == POSE:
        return t[POSE](header=header, pose=pose)
    zero = t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    return t[ODOMETRY](
        header=header, child_frame_id="base_link",
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=t["geometry_msgs/msg/Twist"](linear=zero, angular=zero),
                                                         covariance=np.zeros(36)))


def write_bag(folder: Path, layout: str, messages: Sequence[Message]) -> Path:
    """``messages`` (in time order) as a bag in ``folder`` with rosbags' writers; the path to
    replay: the .bag file, the ROS 2 directory, or the .db3 / .mcap file in it (``LAYOUTS``)."""
    ros1 = layout == "ros1"
    if ros1:
        store = get_typestore(Stores.ROS1_NOETIC)
        writer: Any = Writer1(folder / "walk.bag")
        serialize = store.serialize_ros1
    else:
        store = get_typestore(Stores.LATEST)
        plugin = StoragePlugin.MCAP if layout == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(folder / "walk", version=9, storage_plugin=plugin)
        serialize = store.serialize_cdr
    with writer:
        connections: dict[str, Any] = {}
        for topic, kind, stamp_ns, payload in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, kind, typestore=store)
            message = _ros_message(store, ros1, kind, stamp_ns, payload)
            writer.write(connections[topic], stamp_ns, serialize(message, kind))
    if layout in ("db3", "mcap"):
        return next((folder / "walk").glob(f"*.{layout}"))
    return folder / ("walk.bag" if ros1 else "walk")


def _ros_ranges(geometry: WorldGeometry, pose: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The LaserScan ranges of a scan at ``pose`` (x, y, yaw NED): the ROS beam angles are
    counter-clockwise, so in our frame they are their negatives; 1 cm noise, inf = no return."""
    ros_angles = ANGLE_MIN + ANGLE_INCREMENT * np.arange(BEAMS)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    ranges = cast(geometry, np.array([pose[0], pose[1], -SCAN_HEIGHT_M]), beam_directions(-ros_angles) @ rot.T)
    return np.where(ranges < RANGE_MAX_M, ranges + rng.normal(0.0, 0.01, BEAMS), np.inf)


@pytest.fixture(scope="module")
def arena() -> dict[str, np.ndarray]:
    """The arena path as pose messages (every 8 cm) and scans halfway in time between every third
    pair of them, rendered at the true pose there (position and yaw linear between the two)."""
    geometry = WorldGeometry.from_world(load_world(DEFAULT_WORLD))
    poses = arena_path()
    first = np.arange(0, len(poses) - 1, 3)
    truth = (poses[first] + poses[first + 1]) / 2  # arena_path's yaw is unwrapped: its mean is the halfway yaw
    rng = np.random.default_rng(41)
    return {"pose_ns": T0_NS + POSE_STEP_NS * np.arange(len(poses)), "poses": poses,
            "scan_ns": T0_NS + POSE_STEP_NS * first + POSE_STEP_NS // 2, "truth": truth,
            "ranges": np.array([_ros_ranges(geometry, p, rng) for p in truth])}


def _arena_messages(arena: dict[str, np.ndarray],
                    pose_topics: Sequence[tuple[str, str, float]] = (("/odom", ODOMETRY, 0.0),)) -> list[Message]:
    """The arena's scans on /scan and its poses on each of ``pose_topics`` (topic, type, north
    offset m), in time order."""
    messages = [("/scan", SCAN, int(t), r) for t, r in zip(arena["scan_ns"], arena["ranges"])]
    for topic, kind, offset in pose_topics:
        messages += [(topic, kind, int(t), p + (offset, 0.0, 0.0)) for t, p in zip(arena["pose_ns"], arena["poses"])]
    return sorted(messages, key=lambda m: m[2])


def _distance_to_walls(points: np.ndarray, walls: np.ndarray) -> np.ndarray:
    """(N,) distance (m) of each point (N, 2) to the nearest of the segments (K, 4) [x0, y0, x1, y1]."""
    a, d = walls[:, 0:2], walls[:, 2:4] - walls[:, 0:2]
    rel = points[:, None, :] - a[None]
    u = np.clip(np.sum(rel * d, axis=2) / np.sum(d * d, axis=1), 0.0, 1.0)
    return np.min(np.hypot(*(rel - u[..., None] * d).transpose(2, 0, 1)), axis=1)


@pytest.mark.parametrize("layout", ["ros1", "ros2", "mcap"])  # mcap: a ROS 2 bag, not a flight recording
def test_a_bag_of_the_arena_is_replayed_and_scored_against_its_pose_topic(
        layout: str, arena: dict[str, np.ndarray], tmp_path: Path) -> None:
    """The arena flown as a bag with its true poses on an Odometry topic: the replay starts at the
    first scan's pose, adds simulated wheel-odometry errors to the pose topic (it is the
    reference) and tracks the whole path."""
    bag = write_bag(tmp_path, layout, _arena_messages(arena))
    report_path = tmp_path / "r.json"
    assert main(["replay", str(bag), "--format", "ros", "--map", str(DEFAULT_WORLD), "--report", str(report_path)]) == 0
    report = json.loads(report_path.read_text())
    assert report["scans"] == len(arena["truth"]) and report["reference"] == "the log's own poses"
    assert report["odometry"]["mode"] == "noisy"
    assert report["lost_fraction"] < 0.05 and report["wrong_resets"] == 0
    assert report["position_median_m"] < 0.03 and report["heading_rms_deg"] < 1.0


def test_scans_placed_at_their_reference_pose_land_on_the_arena_walls(arena: dict[str, np.ndarray],
                                                                      tmp_path: Path) -> None:
    """The reader's frames: each scan's returns, placed with the pose interpolated from the pose
    topic, lie on the arena's walls; not with the ROS angles taken as ours (not mirrored)."""
    scans = read_ros_bag(write_bag(tmp_path, "ros1", _arena_messages(arena)))
    walls = load_world(DEFAULT_WORLD).segments_at(SCAN_HEIGHT_M)
    assert len(scans) == len(arena["truth"])
    np.testing.assert_allclose([s.t_s for s in scans], arena["scan_ns"] * 1e-9, atol=1e-6, rtol=0)
    misses = {}
    for mirrored in (True, False):
        distances = []
        for scan in scans:
            assert scan.pose_ned is not None
            x, y, yaw = scan.pose_ned
            angles = yaw + (scan.angles_rad if mirrored else -scan.angles_rad)
            r = scan.ranges_m[scan.valid]
            distances.append(_distance_to_walls(np.column_stack((x + r * np.cos(angles[scan.valid]),
                                                                 y + r * np.sin(angles[scan.valid]))), walls))
        misses[mirrored] = float(np.median(np.concatenate(distances)))
    assert misses[True] < 0.03 and misses[False] > 0.3, misses


@pytest.mark.parametrize("layout", LAYOUTS)
def test_the_pose_topic_is_interpolated_in_time_on_the_circle_and_none_outside_it(layout: str, tmp_path: Path) -> None:
    """PoseStamped poses at 1 s and 2 s whose yaw crosses +-180 deg: a scan at 1.25 s gets the pose
    a quarter of the way (yaw along the shorter arc), scans before and after get none. Beams:
    ROS angles negated; valid = finite and within [range_min, range_max]."""
    second = 10**9
    ranges = np.array([1.0, np.nan, np.inf, 0.05, 31.0, RANGE_MAX_M, RANGE_MIN_M])
    messages: list[Message] = [
        ("/scan", SCAN, T0_NS + second // 2, ranges),
        ("/pose", POSE, T0_NS + second, (1.0, 2.0, math.radians(170.0))),
        ("/scan", SCAN, T0_NS + second + second // 4, ranges),
        ("/pose", POSE, T0_NS + 2 * second, (3.0, -2.0, math.radians(-170.0))),
        ("/scan", SCAN, T0_NS + 2 * second, ranges),
        ("/scan", SCAN, T0_NS + 3 * second, ranges)]
    scans = read_ros_bag(write_bag(tmp_path, layout, messages))
    assert [s.pose_ned is None for s in scans] == [True, False, False, True]
    x, y, yaw = scans[1].pose_ned  # type: ignore[misc]
    assert (x, y) == pytest.approx((1.5, 1.0)) and math.degrees(yaw) == pytest.approx(175.0)
    assert scans[2].pose_ned == pytest.approx((3.0, -2.0, math.radians(-170.0)))
    assert scans[1].t_s == pytest.approx(T0_NS * 1e-9 + 1.25, abs=1e-6)
    np.testing.assert_allclose(scans[0].angles_rad, -(ANGLE_MIN + ANGLE_INCREMENT * np.arange(len(ranges))), atol=1e-6)
    assert scans[0].valid.tolist() == [True, False, False, False, False, True, True]


def test_a_map_is_built_from_the_bag_pose_topic_it_is_told(arena: dict[str, np.ndarray], tmp_path: Path,
                                                           capsys: pytest.CaptureFixture) -> None:
    """Two pose topics (the truth on Odometry, one 1 m off on PoseStamped): none is taken unless
    named (the scans are then placed by scan matching, and the output says so); with
    ``--pose-topic`` the map loads and its walls are the arena's."""
    bag = write_bag(tmp_path, "ros2", _arena_messages(arena, (("/odom", ODOMETRY, 0.0), ("/slam", POSE, 1.0))))
    out = tmp_path / "m.yaml"
    assert main(["map", "build", str(bag), "--format", "ros", "--out", str(out), "--wall-angle", "45"]) == 0
    assert "scans placed by scan matching" in capsys.readouterr().out
    assert main(["map", "build", str(bag), "--format", "ros", "--out", str(out), "--wall-angle", "45",
                 "--pose-topic", "/odom"]) == 0
    assert "scans placed by the log's own poses" in capsys.readouterr().out
    built = load_world(out)
    ends = np.vstack([[w.start, w.end] for w in built.walls])
    assert len(built.walls) >= 10 and built.wall_offset_deg == pytest.approx(0.0, abs=0.1)
    assert np.max(_distance_to_walls(ends, load_world(DEFAULT_WORLD).segments_at(SCAN_HEIGHT_M))) < 0.05


def test_a_bag_with_two_scan_topics_is_refused_naming_both(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    ranges = np.full(BEAMS, 2.0)
    messages: list[Message] = [("/front/scan", SCAN, T0_NS, ranges), ("/rear/scan", SCAN, T0_NS, ranges),
                               ("/odom", ODOMETRY, T0_NS, (0.0, 0.0, 0.0)), ("/rear/scan", SCAN, T0_NS, ranges)]
    bag = write_bag(tmp_path, "ros1", messages)
    assert main(["replay", str(bag), "--format", "ros", "--map", str(DEFAULT_WORLD)]) == 2
    err = capsys.readouterr().err
    assert "/front/scan" in err and "/rear/scan" in err and "--scan-topic" in err
    report_path = tmp_path / "r.json"
    assert main(["replay", str(bag), "--format", "ros", "--map", str(DEFAULT_WORLD), "--scan-topic", "/rear/scan",
                 "--report", str(report_path)]) == 0
    assert json.loads(report_path.read_text())["scans"] == 2


def test_a_bag_without_a_pose_topic_replays_unscored_and_is_mapped_by_scan_matching(
        arena: dict[str, np.ndarray], tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    bag = write_bag(tmp_path, "ros2", _arena_messages(arena, ())[:20])
    report_path = tmp_path / "r.json"
    assert main(["replay", str(bag), "--format", "ros", "--map", str(DEFAULT_WORLD), "--start", "relocalize",
                 "--report", str(report_path)]) == 0
    report = json.loads(report_path.read_text())
    assert report["scans"] == 20 and report["reference"] is None and report["odometry"]["mode"] == "none"
    assert report["position_median_m"] is None and report["heading_rms_deg"] is None and report["wrong_resets"] is None
    out = tmp_path / "m.yaml"
    assert main(["map", "build", str(bag), "--format", "ros", "--out", str(out), "--wall-angle", "45"]) == 0
    assert "scans placed by scan matching" in capsys.readouterr().out and load_world(out).walls


@pytest.mark.parametrize("content", [b"", b"#ROSBAG V2.0\n" + bytes(range(256)) * 4])
def test_a_damaged_bag_is_refused_naming_the_file(content: bytes, tmp_path: Path) -> None:
    bag = tmp_path / "walk.bag"
    bag.write_bytes(content)
    with pytest.raises(ValueError, match="walk.bag"):
        read_ros_bag(bag)
    with pytest.raises(OSError, match="missing.bag"):
        read_ros_bag(tmp_path / "missing.bag")
