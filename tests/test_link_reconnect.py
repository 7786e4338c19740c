"""An autopilot that goes away (TCP peer closed, like an unplugged telemetry bridge) is
reconnected with backoff, without restarting the daemon."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

from tests.conftest import REPO, free_port  # noqa: E402


def companion_heartbeat_seen(autopilot: mavutil.mavfile, seconds: float) -> bool:
    """Send autopilot heartbeats and report whether the companion's (compid 197) heartbeat arrives."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        autopilot.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_QUADROTOR, mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                     0, 0, mavutil.mavlink.MAV_STATE_STANDBY)
        msg = autopilot.recv_match(type="HEARTBEAT", blocking=True, timeout=0.2)
        if msg is not None and msg.get_srcComponent() == 197:
            return True
    return False


def test_daemon_reconnects_when_the_tcp_autopilot_comes_back(tmp_path: Path) -> None:
    port = free_port(socket.SOCK_STREAM)
    cfg = tmp_path / "c.yaml"
    cfg.write_text("origin: {lat: 1.0, lon: 2.0, alt: 3.0}\ntelemetry: {enabled: false}\n"
                   "mavlink: {link_timeout_s: 0.5}\n")
    autopilot = mavutil.mavlink_connection(f"tcpin:127.0.0.1:{port}", source_system=1, source_component=1)
    daemon = subprocess.Popen([sys.executable, "-m", "companion.cli", "run", "-c", str(cfg),
                               "--mavlink", f"tcp:127.0.0.1:{port}"], cwd=REPO,
                              stderr=subprocess.PIPE, text=True)
    try:
        assert companion_heartbeat_seen(autopilot, 10.0)
        autopilot.close()  # the autopilot disappears
        time.sleep(1.0)
        autopilot = mavutil.mavlink_connection(f"tcpin:127.0.0.1:{port}", source_system=1, source_component=1)
        assert companion_heartbeat_seen(autopilot, 15.0), "the daemon did not reconnect"
        assert daemon.poll() is None
    finally:
        autopilot.close()
        daemon.send_signal(signal.SIGTERM)
        rc = daemon.wait(timeout=5)
        stderr = daemon.stderr.read()
    assert rc == 0
    assert "reopening the port" in stderr or "cannot open" in stderr
