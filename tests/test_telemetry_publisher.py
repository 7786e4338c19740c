"""Telemetry publisher: real zenoh peers on 127.0.0.1 (scouting off) and gated fakes."""

from __future__ import annotations

import json
import logging
import math
import queue
import socket
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
import zenoh

from companion.telemetry.keys import SCHEMA_VERSION, STREAMS, key
from companion.telemetry.publisher import TelemetryPublisher, encode_json
from companion.telemetry.rate import RateWindow
from companion.telemetry.session import open_session, zenoh_config

pytestmark = pytest.mark.timeout(30)

OpenPeer = Callable[..., zenoh.Session]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_for(predicate: Callable[[], bool], timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail("condition not reached in time")
        time.sleep(0.005)


@pytest.fixture
def open_peer() -> Iterator[OpenPeer]:
    """Open zenoh peers on loopback with scouting off; all are closed at teardown."""
    sessions: list[zenoh.Session] = []

    def _open(listen: list[str] | None = None, connect: list[str] | None = None) -> zenoh.Session:
        session = open_session("peer", listen or [], connect or [], False, False)
        sessions.append(session)
        return session

    yield _open
    for session in reversed(sessions):
        session.close()


@pytest.fixture
def endpoint() -> str:
    return f"tcp/127.0.0.1:{_free_port()}"


def _subscribe(session: zenoh.Session, key_expr: str) -> queue.Queue[zenoh.Sample]:
    samples: queue.Queue[zenoh.Sample] = queue.Queue()
    session.declare_subscriber(key_expr, samples.put)
    return samples


def _publish_until_received(
    publisher: TelemetryPublisher,
    stream: str,
    make_payload: Callable[[int], dict[str, Any]],
    samples: queue.Queue[zenoh.Sample],
    timeout_s: float = 5.0,
) -> zenoh.Sample:
    """Publish numbered messages until the subscriber gets one (routes take a moment)."""
    deadline = time.monotonic() + timeout_s
    i = 0
    while time.monotonic() < deadline:
        publisher.publish(stream, make_payload(i))
        i += 1
        try:
            return samples.get(timeout=0.05)
        except queue.Empty:
            continue
    pytest.fail(f"no {stream} sample received in {timeout_s} s")


class _GatedSession:
    """Wraps a zenoh session; its publishers' put() waits for ``gate`` and may raise."""

    def __init__(self, inner: zenoh.Session, fail_keys: frozenset[str] = frozenset()) -> None:
        self.inner = inner
        self.fail_keys = fail_keys
        self.gate = threading.Event()
        self.gate.set()
        self.entered = threading.Event()
        self.declared: list[str] = []
        self.sent: list[tuple[str, dict[str, Any]]] = []
        self.undeclared = 0

    def declare_publisher(self, key_expr: str, **kwargs: Any) -> _GatedPublisher:
        self.declared.append(key_expr)
        return _GatedPublisher(self, key_expr, self.inner.declare_publisher(key_expr, **kwargs))


class _GatedPublisher:
    def __init__(self, owner: _GatedSession, key_expr: str, inner: zenoh.Publisher) -> None:
        self.owner = owner
        self.key_expr = key_expr
        self.inner = inner

    def put(self, data: bytes) -> None:
        self.owner.entered.set()
        self.owner.gate.wait()
        if self.key_expr in self.owner.fail_keys:
            raise RuntimeError("simulated zenoh failure")
        self.inner.put(data)
        self.owner.sent.append((self.key_expr, json.loads(data)))

    def undeclare(self) -> None:
        self.owner.undeclared += 1
        self.inner.undeclare()


class _ManualClock:
    def __init__(self, t: float = 0.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


# --- keys and session -----------------------------------------------------------------------


def test_key_space() -> None:
    assert key(1, "pose") == "uav/1/pose"
    assert key(255, "estimate_stats") == "uav/255/estimate_stats"
    assert SCHEMA_VERSION == 1
    assert {"trajectory", "scan", "lines", "corners", "map", "sources", "attitude_check"} <= set(STREAMS)
    assert len(STREAMS) == 18
    for bad_sysid in (0, 256, True, 1.0):
        with pytest.raises(ValueError):
            key(bad_sysid, "pose")  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        key(1, "pointcloud")


def test_a_pipeline_declares_its_own_streams_and_nothing_else_is_accepted() -> None:
    publisher = TelemetryPublisher(None, sysid=1)
    with pytest.raises(ValueError):
        publisher.publish("flow", {"u": 1})
    publisher.add_streams(("flow", "foe"))
    publisher.publish("flow", {"u": 1})
    assert publisher.stats()["flow"]["offered"] == 1
    with pytest.raises(ValueError):
        publisher.add_streams(("Bad Name",))


def test_zenoh_config_is_explicit(endpoint: str) -> None:
    config = zenoh_config("peer", [endpoint], ["tcp/127.0.0.1:1"], False, False)
    assert json.loads(config.get_json("mode")) == "peer"
    assert json.loads(config.get_json("listen/endpoints")) == [endpoint]
    assert json.loads(config.get_json("connect/endpoints")) == ["tcp/127.0.0.1:1"]
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False
    assert json.loads(config.get_json("scouting/gossip/enabled")) is False
    with pytest.raises(zenoh.ZError):
        zenoh_config("peer", ["not-an-endpoint"], [], False, False)


# --- delivery over real zenoh peers ---------------------------------------------------------


def test_pose_arrives_as_json_with_envelope(open_peer: OpenPeer, endpoint: str) -> None:
    publisher_session = open_peer(listen=[endpoint])
    samples = _subscribe(open_peer(connect=[endpoint]), "uav/7/**")
    telemetry = TelemetryPublisher(publisher_session, sysid=7)
    try:
        sample = _publish_until_received(
            telemetry,
            "pose",
            lambda i: {
                "position_ned_m": np.array([1.0, -2.5, np.nan]),
                "euler_rad": (np.float32(0.5), 0.0, math.inf),
                "covariance": {"position": np.float64(0.01), "yaw": -math.inf},
                "seq": np.int64(i),
                "valid": np.bool_(True),
                "source": "vio",
            },
            samples,
        )
    finally:
        telemetry.close()
    assert str(sample.key_expr) == "uav/7/pose"
    assert str(sample.encoding) == str(zenoh.Encoding.APPLICATION_JSON) == "application/json"
    doc = json.loads(sample.payload.to_bytes())
    assert doc["v"] == 1
    assert isinstance(doc["t"], float) and doc["t"] <= time.monotonic()
    assert doc["position_ned_m"] == [1.0, -2.5, None]
    assert doc["euler_rad"] == [0.5, 0.0, None]
    assert doc["covariance"] == {"position": 0.01, "yaw": None}
    assert isinstance(doc["seq"], int) and doc["valid"] is True and doc["source"] == "vio"
    stats = telemetry.stats()["pose"]
    assert stats["published"] >= 1 and stats["last_publish_t"] is not None


def test_subscriber_joins_late_and_rejoins(open_peer: OpenPeer, endpoint: str) -> None:
    telemetry = TelemetryPublisher(open_peer(listen=[endpoint]), sysid=3)
    try:
        for i in range(5):  # nobody listening yet: puts succeed and go nowhere
            telemetry.publish("health", {"overall": "ok", "n": i})
        _wait_for(lambda: telemetry.stats()["health"]["published"] == 5)

        first = open_peer(connect=[endpoint])
        doc = json.loads(
            _publish_until_received(
                telemetry, "health", lambda i: {"n": 100 + i}, _subscribe(first, "uav/3/health")
            ).payload.to_bytes()
        )
        assert doc["n"] >= 100
        first.close()  # the listener goes away; publishing carries on regardless
        for i in range(5):
            telemetry.publish("health", {"n": 500 + i})

        second = open_peer(connect=[endpoint])
        doc = json.loads(
            _publish_until_received(
                telemetry, "health", lambda i: {"n": 1000 + i}, _subscribe(second, "uav/3/*")
            ).payload.to_bytes()
        )
        assert doc["n"] >= 1000
        assert telemetry.stats()["health"]["errors"] == 0
    finally:
        telemetry.close()


# --- queueing, limits and failure handling --------------------------------------------------


def test_full_queue_drops_oldest_and_publish_never_blocks(open_peer: OpenPeer) -> None:
    session = _GatedSession(open_peer())
    session.gate.clear()
    telemetry = TelemetryPublisher(session, sysid=1, queue_size=256)  # type: ignore[arg-type]
    try:
        telemetry.publish("pose", {"i": -1})
        assert session.entered.wait(5.0)  # the worker is now held inside put()
        for i in range(10):
            telemetry.publish("alerts", {"i": i})
        for i in range(10_000):  # would hang (test timeout) if publish() waited for the worker
            telemetry.publish("pose", {"i": i})
        stats = telemetry.stats()
        assert stats["pose"]["offered"] == 10_001
        assert stats["pose"]["dropped"] == 10_000 - 256
        assert stats["alerts"]["dropped"] == 10  # the oldest go first, whatever their stream
        assert stats["pose"]["published"] == 0

        session.gate.set()
        _wait_for(lambda: telemetry.stats()["pose"]["published"] == 1 + 256)
        assert [doc["i"] for _, doc in session.sent] == [-1, *range(10_000 - 256, 10_000)]
        assert session.declared == ["uav/1/pose"]  # one publisher per key, reused
        assert telemetry.stats()["alerts"]["published"] == 0
    finally:
        telemetry.close()
    assert session.undeclared == 1


def test_rate_limit_counts_rate_limited_not_drops(open_peer: OpenPeer) -> None:
    session = _GatedSession(open_peer())
    clock = _ManualClock()
    telemetry = TelemetryPublisher(
        session, sysid=1, max_rate_hz={"pose": 4.0}, clock=clock  # type: ignore[arg-type]
    )
    try:
        for step in range(64):  # 1 s in steps of 1/64 s (exact in binary)
            clock.t = step / 64
            telemetry.publish("pose", {"step": step})
            telemetry.publish("velocity", {"step": step})
        _wait_for(lambda: telemetry.stats()["velocity"]["published"] == 64)
        _wait_for(lambda: telemetry.stats()["pose"]["published"] == 4)
        pose = telemetry.stats()["pose"]
        assert (pose["offered"], pose["rate_limited"], pose["dropped"]) == (64, 60, 0)
        assert [doc["step"] for k, doc in session.sent if k == "uav/1/pose"] == [0, 16, 32, 48]
        assert telemetry.stats()["velocity"]["rate_limited"] == 0
    finally:
        telemetry.close()
    for bad in ({"pointcloud": 1.0}, {"pose": 0.0}, {"pose": math.nan}):
        with pytest.raises(ValueError):
            TelemetryPublisher(None, sysid=1, max_rate_hz=bad)


def test_close_returns_promptly_with_a_stuck_put(
    open_peer: OpenPeer, caplog: pytest.LogCaptureFixture
) -> None:
    session = _GatedSession(open_peer())
    session.gate.clear()  # put() never returns until the end of the test
    telemetry = TelemetryPublisher(session, sysid=1)  # type: ignore[arg-type]
    telemetry.publish("system", {"uptime_s": 1.0})
    assert session.entered.wait(5.0)
    for i in range(20):
        telemetry.publish("system", {"uptime_s": float(i)})

    started = time.monotonic()
    with caplog.at_level(logging.WARNING, logger="companion.telemetry"):
        telemetry.close(timeout_s=0.3)
    assert time.monotonic() - started < 2.0
    assert any("abandoning" in r.getMessage() for r in caplog.records)
    telemetry.publish("system", {"uptime_s": 99.0})  # after close: only counted
    assert telemetry.stats()["system"]["offered"] == 22

    session.gate.set()  # zenoh recovers: the worker sends the one put, drops the rest, exits
    _wait_for(lambda: session.undeclared == 1)
    stats = telemetry.stats()["system"]
    assert (stats["published"], stats["dropped"], stats["errors"]) == (1, 20, 0)


def test_put_errors_are_counted_and_logged_once_per_minute(
    open_peer: OpenPeer, caplog: pytest.LogCaptureFixture
) -> None:
    session = _GatedSession(open_peer(), fail_keys=frozenset({"uav/1/link"}))
    clock = _ManualClock(100.0)
    telemetry = TelemetryPublisher(session, sysid=1, clock=clock)  # type: ignore[arg-type]
    try:
        with caplog.at_level(logging.WARNING, logger="companion.telemetry"):
            for _ in range(3):
                telemetry.publish("link", {"connected": True})
            _wait_for(lambda: telemetry.stats()["link"]["errors"] == 3)
            assert len(caplog.records) == 1
            clock.t = 130.0
            telemetry.publish("link", {"connected": True})
            _wait_for(lambda: telemetry.stats()["link"]["errors"] == 4)
            assert len(caplog.records) == 1
            clock.t = 160.0
            telemetry.publish("link", {"connected": True})
            telemetry.publish("alerts", {"severity": "info", "text": "still alive"})
            _wait_for(lambda: telemetry.stats()["alerts"]["published"] == 1)  # worker survived
        assert len(caplog.records) == 2
        assert all(r.name == "companion.telemetry" for r in caplog.records)
        assert telemetry.stats()["link"]["errors"] == 5
        assert telemetry.stats()["link"]["published"] == 0
    finally:
        telemetry.close()


def test_disabled_publisher_only_counts() -> None:
    telemetry = TelemetryPublisher(None, sysid=1)
    for i in range(1000):
        telemetry.publish("pose", {"i": i})
    stats = telemetry.stats()
    assert set(stats) == set(STREAMS)
    assert stats["pose"] == {
        "offered": 1000,
        "published": 0,
        "dropped": 0,
        "rate_limited": 0,
        "errors": 0,
        "last_publish_t": None,
        "age_s": None,
        "rate_hz": 0.0,
    }
    with pytest.raises(ValueError):
        telemetry.publish("pointcloud", {})
    with pytest.raises(ValueError):
        telemetry.publish("pose", {"t": 1.0})
    telemetry.close()
    telemetry.close()


def test_encode_json_converts_numpy_and_non_finite() -> None:
    doc = json.loads(
        encode_json(
            12.5,
            {"a": np.array([[1, 2], [3, 4]], dtype=np.int16), "b": [np.float32(np.nan)], 3: None},
        )
    )
    assert doc == {"v": 1, "t": 12.5, "a": [[1, 2], [3, 4]], "b": [None], "3": None}
    with pytest.raises(TypeError):
        encode_json(0.0, {"when": object()})


def test_rate_limit_keeps_the_configured_rate_of_a_faster_loop() -> None:
    clock = _ManualClock()
    telemetry = TelemetryPublisher(None, sysid=1, max_rate_hz={"pose": 20.0}, clock=clock)
    accepted: list[float] = []
    for tick in range(500):  # a 50 Hz nav loop for 10 s offers every cycle
        clock.t = tick / 50
        limited = telemetry.stats()["pose"]["rate_limited"]
        due = telemetry.due("pose")
        telemetry.publish("pose", {})
        if telemetry.stats()["pose"]["rate_limited"] == limited:
            accepted.append(clock.t)
        assert due == (accepted[-1:] == [clock.t])  # due() foretells publish() and counts nothing
    assert 199 <= len(accepted) <= 201  # 20 Hz, not every third tick (16.7 Hz)
    assert min(np.diff(accepted)) >= 0.025 - 1e-9  # never closer than half a period


def test_rates_report_message_rate_and_age(open_peer: OpenPeer) -> None:
    clock = _ManualClock(10.0)
    telemetry = TelemetryPublisher(open_peer(), sysid=1, clock=clock)
    try:
        for i in range(11):  # 10 Hz for 1 s
            clock.t = 10.0 + i / 10
            telemetry.publish("setpoint", {"i": i})
            _wait_for(lambda: telemetry.stats()["setpoint"]["published"] == i + 1)
        clock.t = 11.05
        assert telemetry.stats()["setpoint"]["rate_hz"] == pytest.approx(10.0)
        clock.t = 11.5  # silent for 5 of its intervals: stopped, the rate falls
        stats = telemetry.stats()["setpoint"]
        assert stats["rate_hz"] == pytest.approx(10 / 1.5)
        assert stats["age_s"] == pytest.approx(0.5)
        clock.t = 20.0  # silent for longer than the window
        assert telemetry.stats()["setpoint"]["rate_hz"] == 0.0
    finally:
        telemetry.close()


def test_a_stream_that_stops_reads_a_falling_rate_not_its_old_one() -> None:
    window = RateWindow(window_s=5.0)
    for i in range(50):  # 10 Hz for 5 s
        window.add(i * 0.1)
    assert window.rate_hz(4.95) == pytest.approx(10.0)
    assert window.rate_hz(7.0) < 6.0  # 2 s of silence: 28 intervals over 4.9 s
    assert window.rate_hz(9.0) < window.rate_hz(7.0)
    assert window.rate_hz(10.0) == 0.0  # all out of the window
