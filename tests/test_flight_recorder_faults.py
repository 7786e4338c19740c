"""The flight recorder under the faults a real vehicle meets: the daemon killed mid-flight (power
loss, a crash) and a full disk. Real `companion sitl` runs (vehicle and daemon processes on
loopback); the disk is a real 2 MB tmpfs, mounted in a user and mount namespace of its own."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from companion.config import RecordConfig
from companion.recording.reader import Recording
from companion.recording.mcap_files import FILE_GLOB
from tests.conftest import REPO, free_port
from tests.sitl_helpers import wait_for, write_sitl_config


def sitl_config(directory: Path) -> Path:
    (directory / "missions").symlink_to(REPO / "config" / "missions")
    return write_sitl_config(directory / "sitl.yaml", vehicle_port=free_port(), gcs_port=free_port(),
                             zenoh_port=free_port(socket.SOCK_STREAM), mission=None, source="sitl.yaml")


def daemon_of(harness: subprocess.Popen) -> int:
    """The pid of the daemon process `companion sitl` started."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        parent = int(stat.rsplit(")", 1)[1].split()[1])
        if parent == harness.pid and b"run" in cmdline and b"companion.cli" in cmdline:
            return int(entry.name)
    raise AssertionError("no daemon process under the harness")


def test_a_daemon_killed_mid_flight_leaves_its_recording_readable_to_within_one_chunk_of_the_kill(tmp_path: Path) -> None:
    record = tmp_path / "rec"
    harness = subprocess.Popen(
        [sys.executable, "-m", "companion.cli", "sitl", "-c", str(sitl_config(tmp_path)), "--mission", "patrol",
         "--seconds", "60", "--record", str(record)], cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        part = wait_for(lambda: next(record.glob(FILE_GLOB), None), 30, "the recording's first part")
        wait_for(lambda: part.stat().st_size > 1_000_000, 60, "a megabyte recorded (the vehicle flying)")
        daemon = daemon_of(harness)
        killed_at = time.monotonic()  # the daemon's clock in real time (CLOCK_MONOTONIC, system-wide)
        os.kill(daemon, signal.SIGKILL)
        harness.communicate(timeout=60)
    finally:
        if harness.poll() is None:
            harness.kill()
    recording = Recording.open(part)
    messages = list(recording.messages())
    assert recording.truncated == [part] and recording.stats == {}  # cut: no summary, no footer
    last = max(msg.t for msg in messages)
    assert killed_at - last <= RecordConfig().flush_s + 0.5  # a chunk is written at least every flush_s
    assert any(msg.topic == "/sensors/lidar_h" for msg in messages) and any(msg.topic == "/nav/cycle" for msg in messages)


def _can_mount_tmpfs() -> bool:
    try:
        return subprocess.run(["unshare", "-rm", "sh", "-c", "mount -t tmpfs -o size=1m tmpfs /mnt"],
                              capture_output=True, timeout=10).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


@pytest.mark.skipif(not _can_mount_tmpfs(), reason="unprivileged user and mount namespaces are not allowed here")
def test_a_full_disk_stops_the_recording_with_a_clear_report_and_the_vehicle_flies_on(tmp_path: Path) -> None:
    record, report = tmp_path / "rec", tmp_path / "report.json"
    record.mkdir()
    proc = subprocess.run(
        ["unshare", "-rm", "sh", "-c", f'mount -t tmpfs -o size=2m tmpfs "{record}" && exec "$0" "$@"',
         sys.executable, "-m", "companion.cli", "sitl", "-c", str(sitl_config(tmp_path)), "--mission", "hover",
         "--lockstep", "--seed", "1", "--seconds", "30", "--report", str(report), "--record", str(record)],
        cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "recorder: disk full: No space left on device; recording stopped" in proc.stderr
    assert "recorder: degraded (recording stopped: disk full" in proc.stderr  # health, also sent as STATUSTEXT
    r = json.loads(report.read_text())
    assert r["control"]["mission_completed"] and r["control"]["failsafes_triggered"] == []
    assert r["estimate"]["lost_seconds"] == 0.0 and r["estimate"]["position_rms_m"] < 0.05
    assert r["autopilot"]["vision_position_estimate_hz"] >= 28.0
