"""Whatever the autopilot's end of the link does, the daemon keeps running and stops on SIGTERM
within 2 s with exit 0: a TCP peer that accepts and then neither reads nor speaks (a hung
autopilot), one that sends garbage, and one that never accepts at all (its connect hangs)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

from tests.conftest import REPO  # noqa: E402

RUN_S = 3.0  # the daemon runs against the peer this long (3 x link_timeout_s) before SIGTERM


def start_daemon(tmp_path: Path, port: int) -> subprocess.Popen:
    cfg = tmp_path / "c.yaml"
    cfg.write_text("origin: {lat: 1.0, lon: 2.0, alt: 3.0}\ntelemetry: {enabled: false}\n"
                   f"mavlink: {{url: 'tcp:127.0.0.1:{port}', link_timeout_s: 1.0}}\n")
    return subprocess.Popen([sys.executable, "-m", "companion.cli", "run", "-c", str(cfg)], cwd=REPO,
                            stderr=subprocess.PIPE, text=True)


def runs_then_stops(proc: subprocess.Popen) -> tuple[int, float]:
    """Let the daemon run RUN_S against the peer (it must still be running), then SIGTERM it:
    (exit status, seconds from SIGTERM to exit); kills the process if it hangs."""
    time.sleep(RUN_S)
    assert proc.poll() is None, proc.stderr.read()
    started = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    try:
        return proc.wait(timeout=10), time.monotonic() - started
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        return -9, time.monotonic() - started


@pytest.fixture
def listener() -> Iterator[socket.socket]:
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(10.0)  # a daemon that never dials fails the test instead of hanging it
    try:
        yield sock
    finally:
        sock.close()


def test_an_autopilot_that_accepts_and_then_hangs(tmp_path: Path, listener: socket.socket) -> None:
    listener.listen(1)
    daemon = start_daemon(tmp_path, listener.getsockname()[1])
    peer, _ = listener.accept()  # never read from, never written to
    try:
        rc, took = runs_then_stops(daemon)
        listener.setblocking(False)
        with pytest.raises(BlockingIOError):  # silence is no reason to hang up and dial again
            listener.accept()[0].close()
    finally:
        peer.close()
    assert rc == 0 and took <= 2.0, (rc, took)


def test_an_autopilot_that_talks_garbage(tmp_path: Path, listener: socket.socket) -> None:
    listener.listen(1)
    daemon = start_daemon(tmp_path, listener.getsockname()[1])
    peer, _ = listener.accept()
    codec = mavlink.MAVLink(None, 1, 1)
    heartbeat = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                  0, 0, mavlink.MAV_STATE_STANDBY, 3).pack(codec)
    stop = threading.Event()

    def babble() -> None:  # random bytes, MAVLink-looking frames with bad checksums, now and then a real heartbeat
        while not stop.is_set():
            try:
                peer.sendall(os.urandom(512) + b"\xfd\x09\x00\x00\x01\x01\x01" + os.urandom(20) + heartbeat)
            except OSError:
                return
            time.sleep(0.002)

    talker = threading.Thread(target=babble, daemon=True)
    talker.start()
    try:
        rc, took = runs_then_stops(daemon)
    finally:
        stop.set()
        talker.join(2)
        peer.close()
    assert rc == 0 and took <= 2.0, (rc, took)
    assert "Traceback" not in daemon.stderr.read()


def test_an_endpoint_that_never_accepts(tmp_path: Path, listener: socket.socket) -> None:
    listener.listen(0)
    fillers = []
    for _ in range(3):  # fill the accept queue: further SYNs are dropped, a connect() just waits
        filler = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        filler.setblocking(False)
        filler.connect_ex(listener.getsockname())
        fillers.append(filler)
    daemon = start_daemon(tmp_path, listener.getsockname()[1])
    try:
        rc, took = runs_then_stops(daemon)
    finally:
        for filler in fillers:
            filler.close()
    assert rc == 0 and took <= 2.0, (rc, took)
