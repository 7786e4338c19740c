"""The lidar pipeline's telemetry streams: the binary scan encoding, lines, corners and the map.

The scan is a real 1081-beam UTM-30LX scan of the default arena, ray cast and processed by the
planar localizer as the lidar pipeline does it; zenoh is a pair of real peers on loopback.
"""

from __future__ import annotations

import dataclasses
import math
import queue
import socket

import numpy as np
import pytest
import zenoh

from companion.dashboard.bench import arena_scan
from companion.config import MountConfig
from companion.health import Health
from companion.nav.lidar_pipeline import LidarPipeline, LidarPipelineConfig
from companion.nav.lidar_streams import ProcessedScan, map_payload, scan_payloads
from companion.telemetry.publisher import TelemetryPublisher
from companion.telemetry.scan_codec import SCAN_ENCODING, decode_scan, encode_scan
from companion.telemetry.session import open_session
from companion.world import load_world
from tests.conftest import REPO, free_port

POSE = (2.0, 2.0, math.radians(30.0))  # where arena_scan() scans from
ARENA = load_world(REPO / "config" / "worlds" / "arena.yaml")


def _scan_payload(**changes: object) -> dict:
    payload = {"sensor": "lidar_h", "t_capture": 12.25, "sequence": 7, "sweep_s": 0.025,
               "angles_rad": np.linspace(-math.pi / 2, math.pi / 2, 5), "ranges_m": np.array([0.5, 70.0, 1.2344, np.nan, 3.0]),
               "valid": np.array([True, True, True, True, False]), "mount": (0.1, -0.05, 0.5), "pose": (1.5, 2.5, -0.25)}
    return {**payload, **changes}


def _world_point(pose: tuple[float, float, float], q: np.ndarray) -> np.ndarray:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.array([pose[0] + c * q[0] - s * q[1], pose[1] + s * q[0] + c * q[1]])


def _distance_to_walls(p: np.ndarray) -> float:
    return min(wall.locate((float(p[0]), float(p[1])))[0] for wall in ARENA.walls)


def test_scan_encoding_round_trip() -> None:
    data = encode_scan(100.5, _scan_payload())
    assert len(data) == 60 + len("lidar_h") + 2 * 5  # header, name, one u16 per beam
    scan = decode_scan(data)
    assert scan["ranges_mm"].tolist() == [500, 65535, 1234, 0, 0]  # capped; NaN and invalid are 0
    assert (scan["t"], scan["t_capture"], scan["sequence"], scan["sensor"]) == (100.5, 12.25, 7, "lidar_h")
    assert scan["angle_min_rad"] == pytest.approx(-math.pi / 2)
    assert scan["angle_increment_rad"] == pytest.approx(math.pi / 4)
    assert scan["sweep_s"] == pytest.approx(0.025)
    assert scan["mount"] == pytest.approx([0.1, -0.05, 0.5])
    assert scan["pose"] == pytest.approx([1.5, 2.5, -0.25])
    assert decode_scan(encode_scan(1.0, _scan_payload(pose=None)))["pose"] is None


def test_scan_encoding_refuses_what_it_cannot_represent() -> None:
    with pytest.raises(ValueError, match="uniformly"):
        encode_scan(1.0, _scan_payload(angles_rad=np.array([0.0, 0.1, 0.3, 0.4, 0.5])))
    data = encode_scan(1.0, _scan_payload())
    for broken in (data[:40], data[:-1], bytes([2]) + data[1:]):
        with pytest.raises(ValueError):
            decode_scan(broken)


def test_lidar_streams_of_a_real_scan_agree_with_the_map() -> None:
    record, localizer = arena_scan(POSE)
    assert record.fix is not None and record.fix.state == "tracking"
    streams = scan_payloads(record, localizer)
    scan, lines, corners, world_map = streams["scan"], streams["lines"], streams["corners"], map_payload(localizer)
    pose = lines["pose"]
    assert pose == pytest.approx(POSE, abs=0.02)  # the localizer's fix for this scan
    assert scan["sequence"] == lines["sequence"] == corners["sequence"] == record.scan.sequence
    segments = np.asarray(lines["segments_m"])
    assert segments.shape[0] >= 6
    for x0, y0, x1, y1 in segments:  # every extracted line lies on a wall of the arena
        for end in ((x0, y0), (x1, y1)):
            assert _distance_to_walls(_world_point(pose, np.array(end))) < 0.05
    assert corners["state"] == "tracking" and len(corners["matched"]) == corners["fix_matched"] >= 3
    for match in corners["matched"]:
        observed = _world_point(pose, np.asarray(corners["observed_m"])[match["observed"]])
        assert tuple(match["map_ned_m"]) in {tuple(c) for c in ARENA.corners}
        assert np.linalg.norm(observed - match["map_ned_m"]) < 0.05
    assert {tuple(c) for c in np.asarray(world_map["corners_ned_m"]).tolist()} == set(ARENA.corners)
    assert world_map["wall_angle_deg"] == 45.0


def test_pipeline_streams_each_scan_once_and_the_map_only_when_due() -> None:
    record, _ = arena_scan(POSE)
    cfg = LidarPipelineConfig(horizontal_sensor="h", vertical_sensor="v")
    pipeline = LidarPipeline(cfg, ARENA, MountConfig(), MountConfig(rpy_deg=(90.0, 0.0, 0.0)), Health(lambda: 0.0))
    assert pipeline.telemetry(static_due=False) == {}  # nothing processed yet
    offered: dict[str, int] = {}
    for step in range(100):  # a new scan every other call; the static streams every tenth
        if step % 2 == 0:
            pipeline.last_horizontal = ProcessedScan(record.scan, 0.0, 0.0, record.fix, record.lines, record.corners)
        for stream in pipeline.telemetry(static_due=step % 10 == 0):
            offered[stream] = offered.get(stream, 0) + 1
    assert offered == {"scan": 50, "lines": 50, "corners": 50, "map": 10}
    assert set(offered) == set(pipeline.telemetry_streams)


def test_the_corners_stream_lists_the_pairs_the_fix_used_without_associating_again() -> None:
    record, localizer = arena_scan(POSE)
    assert record.fix is not None and len(record.fix.corner_pairs) >= 3
    one_pair = dataclasses.replace(record, fix=dataclasses.replace(record.fix, corner_pairs=((1, 4),), matched=1))
    assert scan_payloads(one_pair, localizer)["corners"]["matched"] == [
        {"observed": 1, "map_ned_m": localizer.map[4].tolist()}]
    walls_only = dataclasses.replace(record, fix=dataclasses.replace(record.fix, corner_pairs=(), matched=0))
    assert scan_payloads(walls_only, localizer)["corners"]["matched"] == []
    assert scan_payloads(dataclasses.replace(record, fix=None), localizer)["corners"]["matched"] == []


def test_scan_travels_binary_with_its_zenoh_encoding() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    sender = open_session("peer", [endpoint], [], False, False)
    receiver = open_session("peer", [], [endpoint], False, False)
    samples: queue.Queue[zenoh.Sample] = queue.Queue()
    receiver.declare_subscriber("uav/4/scan", samples.put)
    telemetry = TelemetryPublisher(sender, sysid=4)
    record, localizer = arena_scan(POSE)
    try:
        for _ in range(100):  # until the route is up
            telemetry.publish("scan", _scan_payload(angles_rad=record.scan.angles_rad, ranges_m=record.scan.ranges_m,
                                                    valid=record.scan.valid))
            try:
                sample = samples.get(timeout=0.05)
                break
            except queue.Empty:
                continue
        else:
            pytest.fail("no scan sample arrived")
    finally:
        telemetry.close()
        receiver.close()
        sender.close()
    assert str(sample.encoding) == SCAN_ENCODING == "application/octet-stream;uav.scan.v1"
    scan = decode_scan(sample.payload.to_bytes())
    expected = np.where(record.scan.valid, np.rint(record.scan.ranges_m * 1e3), 0)
    assert np.array_equal(scan["ranges_mm"], expected)
    assert len(sample.payload.to_bytes()) < 2 * 1081 + 100
