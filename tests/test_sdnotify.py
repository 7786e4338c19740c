"""sd_notify over real AF_UNIX datagram sockets, and the watchdog gate and pinger."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
import tempfile
import uuid
from collections.abc import Callable, Iterator

import pytest

from companion.sdnotify import Notifier, WatchdogGate, run_watchdog


@contextlib.contextmanager
def _bound_receiver(address: str) -> Iterator[socket.socket]:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        sock.bind(address)
        sock.settimeout(5.0)
        yield sock
    finally:
        sock.close()


@pytest.fixture
def path_receiver() -> Iterator[tuple[str, socket.socket]]:
    """A datagram socket on a file path (short: AF_UNIX paths are limited to 107 bytes)."""
    with tempfile.TemporaryDirectory(prefix="sdn") as tmp:
        path = os.path.join(tmp, "notify")
        with _bound_receiver(path) as sock:
            yield path, sock


@pytest.fixture
def abstract_receiver() -> Iterator[tuple[str, socket.socket]]:
    """A datagram socket in the abstract namespace, named the way systemd passes it."""
    name = f"companion-test-{uuid.uuid4().hex}"
    with _bound_receiver("\0" + name) as sock:
        yield "@" + name, sock


@pytest.mark.parametrize("receiver", ["path_receiver", "abstract_receiver"])
def test_messages_arrive(receiver: str, request: pytest.FixtureRequest) -> None:
    address, sock = request.getfixturevalue(receiver)
    notifier = Notifier({"NOTIFY_SOCKET": address})
    assert notifier.enabled
    try:
        assert notifier.ready()
        assert sock.recv(4096) == b"READY=1"
        assert notifier.status("tracking 40 Hz")
        assert sock.recv(4096) == b"STATUS=tracking 40 Hz"
        assert notifier.watchdog()
        assert sock.recv(4096) == b"WATCHDOG=1"
        assert notifier.stopping()
        assert sock.recv(4096) == b"STOPPING=1"
    finally:
        notifier.close()


def test_status_cannot_inject_assignments(path_receiver: tuple[str, socket.socket]) -> None:
    address, sock = path_receiver
    notifier = Notifier({"NOTIFY_SOCKET": address})
    notifier.status("lidar lost\nREADY=1")
    notifier.close()
    assert sock.recv(4096) == b"STATUS=lidar lost READY=1"


def test_reads_os_environ_by_default(
    path_receiver: tuple[str, socket.socket], monkeypatch: pytest.MonkeyPatch
) -> None:
    address, sock = path_receiver
    monkeypatch.setenv("NOTIFY_SOCKET", address)
    notifier = Notifier()
    notifier.ready()
    notifier.close()
    assert sock.recv(4096) == b"READY=1"


def test_unset_socket_is_a_no_op(monkeypatch: pytest.MonkeyPatch) -> None:
    def no_socket(*args: object) -> socket.socket:
        raise AssertionError("a disabled notifier must not create a socket")

    monkeypatch.setattr(socket, "socket", no_socket)
    for environ in ({}, {"NOTIFY_SOCKET": ""}, {"NOTIFY_SOCKET": "vsock:2:1234"}):
        notifier = Notifier(environ)
        assert not notifier.enabled
        assert not notifier.ready()
        assert not notifier.status("x")
        assert not notifier.watchdog()
        assert not notifier.stopping()
        assert notifier.watchdog_interval() is None
        notifier.close()


def test_send_errors_are_logged_once_and_never_raise(caplog: pytest.LogCaptureFixture) -> None:
    with tempfile.TemporaryDirectory(prefix="sdn") as tmp:
        notifier = Notifier({"NOTIFY_SOCKET": os.path.join(tmp, "nobody-listens")})
        with caplog.at_level(logging.DEBUG, logger="companion.sdnotify"):
            assert not notifier.ready()
            assert not notifier.watchdog()
            assert not notifier.watchdog()
        notifier.close()
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1
    assert "sd_notify" in warnings[0].getMessage()


@pytest.mark.parametrize(
    ("extra", "expected"),
    [
        ({"WATCHDOG_USEC": "5000000"}, 5.0),
        ({"WATCHDOG_USEC": "20000"}, 0.02),
        ({"WATCHDOG_USEC": "5000000", "WATCHDOG_PID": str(os.getpid())}, 5.0),
        ({"WATCHDOG_USEC": "5000000", "WATCHDOG_PID": str(os.getpid() + 1)}, None),
        ({"WATCHDOG_USEC": "5000000", "WATCHDOG_PID": "self"}, None),
        ({"WATCHDOG_USEC": "0"}, None),
        ({"WATCHDOG_USEC": "-1"}, None),
        ({"WATCHDOG_USEC": "5s"}, None),
        ({}, None),
    ],
)
def test_watchdog_interval(extra: dict[str, str], expected: float | None) -> None:
    notifier = Notifier({"NOTIFY_SOCKET": "/run/systemd/notify", **extra})
    assert notifier.watchdog_interval() == expected


def test_watchdog_interval_needs_a_socket() -> None:
    assert Notifier({"WATCHDOG_USEC": "5000000"}).watchdog_interval() is None


class FakeClock:
    """A clock the test sets by hand; counts how often it is read."""

    def __init__(self) -> None:
        self.now = 0.0
        self.reads = 0

    def __call__(self) -> float:
        self.reads += 1
        return self.now


def test_gate_health() -> None:
    clock = FakeClock()
    gate = WatchdogGate(max_age=1.0, clock=clock)
    assert not gate.healthy(0.0)  # never beat
    assert gate.age(0.0) is None
    clock.now = 10.0
    gate.beat()
    assert gate.healthy(10.0)
    assert gate.healthy(10.99)
    assert gate.age(10.5) == pytest.approx(0.5)
    assert not gate.healthy(11.0)
    clock.now = 11.5
    gate.beat()
    assert gate.healthy(12.0)


@pytest.mark.parametrize("max_age", [0.0, -1.0, float("nan")])
def test_gate_rejects_bad_max_age(max_age: float) -> None:
    with pytest.raises(ValueError, match="max_age"):
        WatchdogGate(max_age)


def test_run_watchdog_returns_without_watchdog(path_receiver: tuple[str, socket.socket]) -> None:
    address, _ = path_receiver
    gate = WatchdogGate(1.0)
    for environ in ({}, {"NOTIFY_SOCKET": address}, {"WATCHDOG_USEC": "20000"}):
        asyncio.run(asyncio.wait_for(run_watchdog(Notifier(environ), gate), timeout=5.0))


async def _wait_until(condition: Callable[[], bool], what: str) -> None:
    """Yield to the pinger until ``condition`` holds (generous limit: a slow CI is fine)."""
    for _ in range(5000):
        if condition():
            return
        await asyncio.sleep(0.001)
    raise AssertionError(f"timed out waiting for {what}")


def test_run_watchdog_pings_only_while_the_loop_beats(
    path_receiver: tuple[str, socket.socket], caplog: pytest.LogCaptureFixture
) -> None:
    """Time is the fake clock; the pinger's real sleeps (10 ms) only pace the iterations.

    Each pinger iteration reads ``pinger_clock`` once, so counting reads tells the test how
    many decisions the pinger made since a change, without relying on wall-clock timing.
    """
    address, sock = path_receiver
    sock.setblocking(False)
    received: list[bytes] = []

    def pump() -> list[bytes]:
        with contextlib.suppress(BlockingIOError):
            while True:
                received.append(sock.recv(4096))
        return received

    beat_clock = FakeClock()
    gate = WatchdogGate(max_age=1.0, clock=beat_clock)
    pinger_clock = FakeClock()

    def set_time(t: float) -> None:
        beat_clock.now = pinger_clock.now = t

    notifier = Notifier({"NOTIFY_SOCKET": address, "WATCHDOG_USEC": "20000"})

    async def scenario() -> None:
        task = asyncio.create_task(run_watchdog(notifier, gate, clock=pinger_clock))
        try:
            # Before the first beat: the pinger runs but sends nothing.
            await _wait_until(lambda: pinger_clock.reads >= 3, "three pinger iterations")
            assert pump() == []

            # The loop beats: pings flow.
            gate.beat()
            await _wait_until(lambda: len(pump()) >= 3, "three pings")
            assert set(received) == {b"WATCHDOG=1"}

            # The loop stalls (time moves past max_age without a beat): pings stop. Pings
            # sent before the change are already queued, so drain them first.
            set_time(5.0)
            pump()
            received.clear()
            reads = pinger_clock.reads
            await _wait_until(lambda: pinger_clock.reads >= reads + 5, "five more iterations")
            assert pump() == []

            # The loop recovers: pings resume.
            gate.beat()
            await _wait_until(lambda: len(pump()) >= 1, "a ping after recovery")
            assert set(received) == {b"WATCHDOG=1"}
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    with caplog.at_level(logging.INFO, logger="companion.sdnotify"):
        asyncio.run(scenario())
    notifier.close()
    messages = [r.getMessage() for r in caplog.records]
    assert sum("stalled" in m for m in messages) == 1
    assert sum("resumed" in m for m in messages) == 1
