"""The flight recorder (companion/recording/): exact encodings with schemas, the writer's bounds
(parts, size cap, full queue), files cut by a crash, and record-then-replay of a lockstep SITL
patrol end to end (`companion sitl --record`, `companion replay FILE.mcap --report`)."""

from __future__ import annotations

import json
import math
import shutil
import socket
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from mcap.reader import make_reader

from companion import messages as m
from companion.config import RecordConfig
from companion.recording import codec
from companion.recording.reader import Recording
from companion.recording.mcap_files import FILE_GLOB, McapFiles
from companion.recording.recorder import Recorder
from tests.conftest import REPO, free_port
from tests.sitl_helpers import write_sitl_config

RNG = np.random.default_rng(16)


def sample_messages() -> list[object]:
    """One of every typed message, with the awkward values a real one has (NaN, inf, None, grey and colour images)."""
    ranges = RNG.uniform(0.1, 30.0, 1081)
    ranges[[3, 9]] = [np.inf, np.nan]
    valid = np.ones(1081, bool)
    valid[[3, 9, 20]] = False
    angles = np.linspace(-2.356, 2.356, 1081)
    flows = RNG.normal(size=(6, 2))
    flows[2] = np.nan
    return [
        m.Scan("lidar_h", 12.025, angles, ranges, valid, sweep_s=0.025, sequence=481),
        m.Frame("down", 3.5, RNG.integers(0, 255, (48, 64), dtype=np.uint8), sequence=2, exposure_s=0.004),
        m.Frame("front", 3.6, RNG.integers(0, 255, (48, 64, 3), dtype=np.uint8)),
        m.ImuSample(1.0 / 3.0, RNG.normal(size=3), RNG.normal(size=3), (0.1, -0.2, 3.0), RNG.normal(size=3), 12.5),
        m.ImuSample(2.0, RNG.normal(size=3), RNG.normal(size=3)),
        m.GnssFix("gps", 7.1, 3, 1.2966, 103.7764, 10.0, np.array([1.0, 2.0, np.nan]), 0.8, 1.5, 0.1, 12),
        m.GnssFix("gps", 7.2, 1, math.nan, math.nan, math.nan),
        m.LandmarkSightings("markers", 4.0, np.array([3, 7]), RNG.uniform(1, 5, 2), RNG.normal(size=2), RNG.normal(size=2),
                            (0.05, 0.01, 0.01), 5, RNG.uniform(0, 1, (2, 3))),
        m.FlowField("front", 0.9, 1.0, RNG.normal(size=(6, 2)), flows, np.array([1, 1, 0, 1, 1, 1], bool), 4),
        m.PoseEstimate(5.0, RNG.normal(size=3), (0.01, -0.02, 2.5), np.diag(RNG.uniform(0, 1, 6)), RNG.normal(size=3),
                       np.eye(3) * 0.01, reset=True, source="lidar", degraded=True),
        m.AttitudeEstimate(6.0, (0.1, 0.05, math.nan), np.diag([1e-4, 1e-4, math.inf]), source="gnss_flow.images"),
        m.RangeEstimate(6.5, 12.25, 0.04, source="gnss_flow"),
    ]


def same(a: object, b: object) -> bool:
    """Bit-for-bit equality of two messages (arrays by bytes, NaN equal to NaN)."""
    if type(a) is not type(b):
        return False
    for name in a.__dataclass_fields__:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            if not (isinstance(y, np.ndarray) and x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()):
                return False
        elif isinstance(x, tuple) and isinstance(y, tuple):
            if np.asarray(x, float).tobytes() != np.asarray(y, float).tobytes():
                return False
        elif isinstance(x, float) and isinstance(y, float):
            if np.float64(x).tobytes() != np.float64(y).tobytes():
                return False
        elif x != y:
            return False
    return True


@pytest.mark.parametrize("msg", sample_messages(), ids=lambda msg: type(msg).__name__)
def test_every_message_comes_back_bit_for_bit_and_its_document_validates_against_its_schema(msg: object) -> None:
    doc = json.loads(codec.dumps(codec.encode_message(msg)))
    schema = json.loads(codec.message_schema(type(msg)).data)
    jsonschema.Draft202012Validator.check_schema(schema)
    jsonschema.validate(doc, schema)
    assert same(codec.decode_message(type(msg), doc), msg)


MM = np.round(np.random.default_rng(3).uniform(0.02, 30.0, 1081) * 1000.0) / 1000.0  # a Hokuyo scan's ranges


@pytest.mark.parametrize("array, form", [
    (MM, "mm_dtype"), (-MM[:100], "mm_dtype"), (MM.reshape(23, 47).T, "mm_dtype"),  # whole mm, any sign, any layout
    (MM + 1e-4, "base64"), (np.r_[MM[:99], -0.0], "base64"),  # not whole mm; -0.0 would come back +0.0
    (np.r_[MM[:50], np.nan, MM[:50]], "base64"), (np.r_[MM[:50], 3e7, MM[:50]], "base64"),  # NaN; past int32
    (MM[:10], "base64"),  # small arrays (covariances) are not tried
    (np.arange(1200) % 3 == 0, "bits"), (np.zeros((0,), bool), "bits"), (np.ones((3, 5), bool), "bits"),
])
def test_arrays_take_a_compact_form_only_where_it_decodes_to_the_same_bits(array: np.ndarray, form: str) -> None:
    doc = json.loads(codec.dumps({"a": codec.exact(array)}))["a"]
    back = codec.unexact(doc)
    assert form in doc
    assert back.dtype == array.dtype and back.shape == array.shape
    assert back.tobytes() == np.ascontiguousarray(array).tobytes()
    jsonschema.validate(doc, codec.ARRAY)


def test_the_foxglove_messages_carry_the_fields_foxglove_draws_from() -> None:
    scan, frame, _, _, _, fix, _, _, _, pose, _, _ = sample_messages()
    view = codec.laser_scan_view(scan, "lidar_h")
    assert codec.LASER_SCAN_SCHEMA.name == "foxglove.LaserScan" and codec.LASER_SCAN_SCHEMA.encoding == "protobuf"
    shown = np.where(scan.valid, scan.ranges_m, np.nan)
    assert shown.tobytes() in view  # packed doubles: every range exact, NaN where the beam is invalid
    assert b"lidar_h" in view
    f = codec.encode_message(frame)
    assert codec.message_schema(m.Frame).name == "foxglove.CompressedImage" and f["format"] == "png"
    g = codec.encode_message(fix)
    assert codec.message_schema(m.GnssFix).name == "foxglove.LocationFix"
    assert (g["latitude"], g["position_covariance"][0], g["position_covariance_type"]) == (1.2966, 0.8 ** 2, 2)
    p = codec.encode_message(pose)
    q = p["pose"]["orientation"]
    assert codec.message_schema(m.PoseEstimate).name == "foxglove.PoseInFrame"
    assert p["frame_id"] == "local_ned" and math.isclose(math.hypot(q["x"], q["y"], q["z"], q["w"]), 1.0)
    assert math.isclose(2 * math.atan2(q["z"], q["w"]), 2.5, abs_tol=0.05)  # yaw, nearly level


def test_an_estimate_in_a_nav_cycle_comes_back_bit_for_bit() -> None:
    for e in sample_messages()[-3:]:
        assert same(codec.decode_estimate(json.loads(codec.dumps(codec.encode_estimate(e)))), e)


def test_a_text_field_that_reads_like_a_non_finite_number_stays_text() -> None:
    scan = replace(sample_messages()[0], sensor_id="inf")
    assert codec.decode_message(m.Scan, json.loads(codec.dumps(codec.encode_message(scan)))).sensor_id == "inf"


# -- the writer ------------------------------------------------------------------------------------

def recorder(directory: Path, **settings: object) -> Recorder:
    config = directory / "companion.yaml"
    config.write_text("# the config\n")
    world = directory / "world.yaml"
    world.write_text("walls: []\n")
    clock = iter(np.arange(0.0, 1e6, 0.01))
    record = replace(RecordConfig(enabled=True), **settings)
    files = McapFiles(record, directory / "rec", "0123456789abcdef", config.read_text(), str(config),
                      {"pipelines.lidar.map": world})
    return Recorder(record, [files], lambda: float(next(clock)), files.id)


def feed_scans(rec: Recorder, count: int) -> list[m.Scan]:
    scan = sample_messages()[0]
    handler = rec.sensor("lidar_h")
    scans = [replace(scan, t_capture=0.025 * i, sequence=i, ranges_m=RNG.uniform(0.1, 30, 1081)) for i in range(count)]
    for s in scans:
        handler(s)
    return scans


def test_a_recording_keeps_every_message_in_order_with_its_config_and_files(tmp_path: Path) -> None:
    rec = recorder(tmp_path)
    rec.start()
    scans = feed_scans(rec, 50)
    rec.close(timeout_s=10)
    recording = Recording.open(next((tmp_path / "rec").glob(FILE_GLOB)))
    read = [codec.decode_message(m.Scan, msg.doc) for msg in recording.messages()]
    assert len(read) == 50 and all(same(a, b) for a, b in zip(read, scans))
    assert recording.config_yaml == "# the config\n"
    assert recording.attachments == {"pipelines.lidar.map": b"walls: []\n"}
    assert recording.truncated == [] and recording.stats["written"] == 50


def test_a_long_recording_is_split_into_parts_and_the_oldest_removed_under_the_cap(tmp_path: Path) -> None:
    rec = recorder(tmp_path, max_file_mb=1.0, max_total_mb=3.0, chunk_kb=64)
    rec.start()
    feed_scans(rec, 1200)  # about 12 MB of scans before compression
    rec.close(timeout_s=30)
    on_disk = sorted((tmp_path / "rec").glob(FILE_GLOB))
    files = rec.sinks[0]
    assert len(files.parts) >= 4 and files.removed
    assert [p.name for p in on_disk] == files.parts[len(files.removed):]
    assert sum(p.stat().st_size for p in on_disk) <= 3.0e6 + 1.2e6  # the cap, plus the part being written when checked
    recording = Recording.open(on_disk[-1])
    assert recording.first_part == len(files.removed) + 1
    sequences = [msg.doc["sequence"] for msg in recording.messages()]
    assert sequences == list(range(sequences[0], 1200))  # the kept parts, whole and in order


def test_a_full_queue_drops_and_counts_instead_of_blocking(tmp_path: Path) -> None:
    rec = recorder(tmp_path, queue_size=64)
    feed_scans(rec, 100)  # the writer thread is not started: nothing drains the queue
    assert rec.snapshot()["dropped"] == {"/sensors/lidar_h": 36}
    rec.start()
    rec.close(timeout_s=10)
    assert Recording.open(next((tmp_path / "rec").glob(FILE_GLOB))).stats["dropped"] == {"/sensors/lidar_h": 36}


def test_a_file_cut_anywhere_is_read_up_to_its_last_whole_chunk(tmp_path: Path) -> None:
    rec = recorder(tmp_path, chunk_kb=64)
    rec.start()
    feed_scans(rec, 200)
    rec.close(timeout_s=10)
    path = next((tmp_path / "rec").glob(FILE_GLOB))
    data = path.read_bytes()
    whole = len(list(Recording.open(path).messages()))
    counts = []
    for fraction in (0.3, 0.55, 0.8, 0.97):
        cut = tmp_path / "cut" / path.name
        cut.parent.mkdir(exist_ok=True)
        cut.write_bytes(data[: int(len(data) * fraction)])
        recording = Recording.open(cut)
        read = [msg.doc["sequence"] for msg in recording.messages()]
        assert recording.truncated == [cut]
        assert read == list(range(len(read)))  # a prefix, nothing garbled
        counts.append(len(read))
    assert counts == sorted(counts) and 0 < counts[0] and counts[-1] < whole
    assert counts[-1] >= whole * 0.97 - 40  # one 64 kB chunk holds about 7 of these scans; a few chunks at most


# -- record a lockstep SITL patrol, replay it ------------------------------------------------------

@pytest.fixture(scope="module")
def patrol(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """`companion sitl --mission patrol --lockstep --report --record DIR` (config/sitl.yaml on free
    ports), then `companion replay` of its recording with --report."""
    directory = tmp_path_factory.mktemp("patrol-recording")
    (directory / "missions").symlink_to(REPO / "config" / "missions")
    cfg = write_sitl_config(directory / "sitl.yaml", vehicle_port=free_port(), gcs_port=free_port(),
                            zenoh_port=free_port(socket.SOCK_STREAM), mission=None, source="sitl.yaml")
    flight, replayed, record = directory / "flight.json", directory / "replay.json", directory / "rec"
    proc = subprocess.run(
        [sys.executable, "-m", "companion.cli", "sitl", "-c", str(cfg), "--mission", "patrol", "--lockstep",
         "--seed", "1", "--seconds", "150", "--report", str(flight), "--record", str(record)],
        cwd=REPO, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    part = sorted(record.glob(FILE_GLOB))[0]
    estimates = directory / "estimates.mcap"
    proc = subprocess.run([sys.executable, "-m", "companion.cli", "replay", str(part), "--report", str(replayed),
                           "--estimates", str(estimates)], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return {"flight": flight, "replay": replayed, "part": part, "record": record, "estimates": estimates}


def test_the_replayed_patrol_equals_the_recorded_one_bit_for_bit(patrol: dict[str, Path]) -> None:
    r = json.loads(patrol["replay"].read_text())["replay"]
    assert r["exact"] and r["mismatched_cycles"] == 0
    assert r["max_position_diff_m"] == 0.0 and r["max_yaw_diff_deg"] == 0.0
    assert r["cycles"] > 50 * 100 and r["messages"] > r["cycles"]  # 50 Hz cycles of a 2-minute flight, and the scans
    assert r["recorder_dropped"] == {} and r["truncated_parts"] == []


def test_the_replay_report_equals_the_flights_report(patrol: dict[str, Path]) -> None:
    flight = json.loads(patrol["flight"].read_text())
    replayed = json.loads(patrol["replay"].read_text())
    assert set(replayed) == set(flight) | {"replay"}
    replayed.pop("replay")
    assert replayed == flight
    assert flight["control"]["mission_completed"] and flight["estimate"]["position_rms_m"] is not None


def test_every_channel_opens_with_the_mcap_reader_and_validates_against_its_schema(patrol: dict[str, Path]) -> None:
    with open(patrol["part"], "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count > 0
        validators: dict[int, jsonschema.Validator] = {}
        seen: dict[str, int] = {}
        topics: dict[str, int] = {}
        for schema, channel, message in reader.iter_messages():
            topics[channel.topic] = topics.get(channel.topic, 0) + 1
            if schema.encoding == "protobuf":  # Foxglove's view of a scan: its ranges are there, raw
                assert schema.name == "foxglove.LaserScan" and channel.topic.endswith("/laser_scan")
                seen[schema.name] = seen.get(schema.name, 0) + 1
                continue
            if channel.id not in validators:
                body = json.loads(schema.data)
                jsonschema.Draft202012Validator.check_schema(body)
                assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
                validators[channel.id] = jsonschema.Draft202012Validator(body)
            validators[channel.id].validate(json.loads(message.data))
            seen[schema.name] = seen.get(schema.name, 0) + 1
    assert {"foxglove.LaserScan", "foxglove.PoseInFrame", "companion.Scan", "companion.ImuSample", "companion.NavCycle",
            "companion.MavlinkMessages", "companion.Telemetry", "companion.HealthChange"} <= set(seen)
    # the views at record.view_hz (10): every scan of the 10 Hz URG-04LX, one in four of the 40 Hz UTM-30LX
    assert topics["/sensors/lidar_v/laser_scan"] == topics["/sensors/lidar_v"]
    assert abs(topics["/sensors/lidar_h/laser_scan"] - topics["/sensors/lidar_h"] / 4) <= 2


def test_the_replayed_poses_are_written_next_to_the_recorded_ones_for_foxglove(patrol: dict[str, Path]) -> None:
    poses: dict[str, list[tuple[int, bytes]]] = {"/recorded/nav/pose": [], "/replayed/nav/pose": []}
    with open(patrol["estimates"], "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(topics=list(poses)):
            assert schema.name == "foxglove.PoseInFrame"
            poses[channel.topic].append((message.log_time, message.data))
    assert len(poses["/recorded/nav/pose"]) > 5000
    assert poses["/replayed/nav/pose"] == poses["/recorded/nav/pose"]


def test_replaying_only_named_pipelines_and_refusing_an_unknown_one(patrol: dict[str, Path]) -> None:
    proc = subprocess.run([sys.executable, "-m", "companion.cli", "replay", str(patrol["part"]), "--pipelines", "nope"],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "nope: not a pipeline of the recorded config (lidar)" in proc.stderr


# -- live to the Foxglove app -------------------------------------------------------------------------

def test_the_recorders_channels_are_served_live_to_a_foxglove_client_with_their_schemas() -> None:
    import asyncio
    import struct

    import websockets

    from companion.recording.foxglove_live import FoxgloveLive

    live = FoxgloveLive("127.0.0.1", 0)
    rec = Recorder(replace(RecordConfig(), foxglove_server=True), [live], lambda: 4.0)
    rec.start()
    pose = sample_messages()[-3]
    received: dict[str, dict] = {}

    async def client() -> None:
        async with websockets.connect(f"ws://127.0.0.1:{live.port}", subprotocols=["foxglove.sdk.v1"]) as ws:
            channels: dict[int, dict] = {}
            for i in range(100):
                rec.cycle(5.0 + 0.2 * i, [pose], pose)  # a pose view is due every 0.1 s (record.view_hz)
                try:
                    msg = await asyncio.wait_for(ws.recv(), 0.2)
                except asyncio.TimeoutError:
                    continue
                if isinstance(msg, str) and json.loads(msg)["op"] == "advertise":
                    for c in json.loads(msg)["channels"]:
                        channels[c["id"]] = c
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": c["id"], "channelId": c["id"]}]}))
                elif isinstance(msg, bytes) and msg[0] == 1:  # message data: opcode, subscription id, log time, payload
                    subscription, log_ns = struct.unpack_from("<IQ", msg, 1)
                    received[channels[subscription]["topic"]] = {"channel": channels[subscription], "log_ns": log_ns,
                                                                 "doc": json.loads(msg[13:])}
                if len(received) == 2:
                    return

    try:
        asyncio.run(asyncio.wait_for(client(), 30))
    finally:
        rec.close(timeout_s=5)
    pose_channel = received["/nav/pose"]["channel"]
    assert pose_channel["schemaName"] == "foxglove.PoseInFrame" and pose_channel["encoding"] == "json"
    assert pose_channel["schemaEncoding"] == "jsonschema"
    jsonschema.validate(received["/nav/pose"]["doc"], json.loads(pose_channel["schema"]))
    assert same(codec.decode_message(m.PoseEstimate, received["/nav/pose"]["doc"]), pose)
    cycle = received["/nav/cycle"]
    assert cycle["log_ns"] == round(cycle["doc"]["now"] * 1e9) and cycle["doc"]["selected"] == "lidar"


def test_replay_at_a_speed_waits_for_each_messages_recorded_time_scaled_by_the_speed() -> None:
    from companion.recording.replay import Pacer

    wall = [100.0]
    slept: list[float] = []

    def sleep(seconds: float) -> None:
        slept.append(seconds)
        wall[0] += seconds

    pacer = Pacer(4.0, clock=lambda: wall[0], sleep=sleep)
    pacer.wait_for(10.0)  # the first message sets the origin
    pacer.wait_for(12.0)  # 2 s recorded at 4x: 0.5 s of wall time
    wall[0] += 1.0  # the replay itself took 1 s: the next message is late already
    pacer.wait_for(14.0)
    pacer.wait_for(18.0)
    assert slept == [0.5, 0.5]  # 12: due at +0.5 s; 14: due at +1.0 s, at +1.5 s already (no sleep); 18: due at +2.0 s
    with pytest.raises(ValueError):
        Pacer(0.0)


def test_a_recording_without_its_scoring_file_gets_the_report_schema_with_the_truth_scored_fields_null(
        patrol: dict[str, Path], tmp_path: Path) -> None:
    alone = tmp_path / patrol["part"].name
    shutil.copy(patrol["part"], alone)  # as from a real vehicle: no truth beside it
    out = tmp_path / "r.json"
    proc = subprocess.run([sys.executable, "-m", "companion.cli", "replay", str(alone), "--pipelines", "lidar",
                           "--report", str(out)], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report, flight = json.loads(out.read_text()), json.loads(patrol["flight"].read_text())
    assert set(report) == set(flight) | {"replay"}
    assert all(set(report[k]) == set(flight[k]) for k in flight if isinstance(flight[k], dict))
    assert report["estimate"]["position_rms_m"] is None and report["control"]["tracking_rms_m"] is None
    assert report["control"]["law"] == "rpt" and report["mission"] == "patrol"
    assert report["autopilot"]["firmware"] == flight["autopilot"]["firmware"]  # from the recorded telemetry
    assert report["replay"]["exact"] and report["replay"]["pipelines"] == ["lidar"]


def test_camera_frames_are_recorded_at_most_at_the_frame_rate_cap_and_the_rest_counted(tmp_path: Path) -> None:
    rec = recorder(tmp_path, frame_rate_hz=10.0)
    handler = rec.sensor("down")
    frame = sample_messages()[1]
    for i in range(30):  # a 30 Hz camera for one second
        handler(replace(frame, t_capture=i / 30.0, sequence=i))
    rec.start()
    rec.close(timeout_s=10)
    read = [msg.doc["sequence"] for msg in Recording.open(next((tmp_path / "rec").glob(FILE_GLOB))).messages()]
    assert read == list(range(0, 30, 3)) and rec.stats.frames_skipped == 20


def test_a_renamed_part_still_opens_as_a_recording(tmp_path: Path) -> None:
    rec = recorder(tmp_path)
    rec.start()
    feed_scans(rec, 5)
    rec.close(timeout_s=10)
    renamed = tmp_path / "flight-to-look-at.mcap"
    next((tmp_path / "rec").glob(FILE_GLOB)).rename(renamed)
    recording = Recording.open(renamed)
    assert recording.parts == [renamed] and len(list(recording.messages())) == 5
