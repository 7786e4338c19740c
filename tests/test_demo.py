"""`make demo`: `companion sitl` with config/sitl.yaml, in real time, until Ctrl-C.

The same command path (``python -m companion.cli sitl -c CONFIG``, no --seconds) runs from a copy
of config/sitl.yaml that differs only in free loopback ports and absolute paths (the real ports
may be taken). The daemon flies the config's hover mission (~20 s); once its zenoh telemetry
reports the mission "completed", the test does what Ctrl-C does in a terminal: SIGINT to the
whole foreground process group (harness, vehicle and daemon alike). ``companion sitl`` must then
exit 0 within 10 s and say it stopped.
"""

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
import yaml

from sitl.harness import TelemetryListener
from tests.conftest import REPO, free_port
from tests.sitl_helpers import write_sitl_config
from tests.test_mavsdk_interop import SitlRun, children_of, cmdline_of, note_children, stop_sitl

MISSION_TIMEOUT_S = 60.0
EXIT_TIMEOUT_S = 10.0


def demo_config(path: Path) -> tuple[Path, int]:
    """config/sitl.yaml with free ports and absolute paths, its mission kept; (path, zenoh port)."""
    mission = yaml.safe_load((REPO / "config" / "sitl.yaml").read_text())["mission"]["file"]
    zenoh_port = free_port(socket.SOCK_STREAM)
    write_sitl_config(path, vehicle_port=free_port(), gcs_port=free_port(), zenoh_port=zenoh_port,
                      mission=str(REPO / "config" / mission))
    return path, zenoh_port


def start_in_own_group(args: list[str], output: Path) -> subprocess.Popen:
    """Start ``args`` as the leader of a new session (a terminal's foreground group, for the signals).

    SIGINT must reach the harness as Python's KeyboardInterrupt, as in a terminal: a child inherits an
    ignored SIGINT (e.g. when the test runner itself was started in the background), but a handled
    one is reset to the default at exec, so the handler is set around the start.
    """
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGINT, signal.default_int_handler) if in_main_thread else None
    try:
        with open(output, "w") as out:
            return subprocess.Popen(args, cwd=REPO, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    finally:
        if in_main_thread:
            signal.signal(signal.SIGINT, signal.SIG_DFL if previous is None else previous)


@pytest.fixture
def demo(tmp_path: Path) -> Iterator[tuple[SitlRun, int]]:
    """`companion sitl -c <copy of config/sitl.yaml>` (no --seconds) and its zenoh port; always stopped after."""
    cfg, zenoh_port = demo_config(tmp_path / "sitl.yaml")
    output = tmp_path / "demo.out"
    run = SitlRun(start_in_own_group([sys.executable, "-m", "companion.cli", "sitl", "-c", str(cfg)], output),
                  gcs_port=0, output=output)  # the GCS link is not used here
    try:
        note_children(run)
        yield run, zenoh_port
    finally:
        stop_sitl(run)


def test_demo_flies_the_hover_mission_and_ctrl_c_stops_it_cleanly(demo) -> None:
    run, zenoh_port = demo
    proc = run.proc
    listener = TelemetryListener([f"tcp/127.0.0.1:{zenoh_port}"], sysid=1)
    try:
        deadline = time.monotonic() + MISSION_TIMEOUT_S
        mission: dict = {}
        while time.monotonic() < deadline and proc.poll() is None:
            mission = listener.snapshot().get("mission", {})
            if mission.get("state") in ("completed", "failed", "aborted"):
                break
            time.sleep(0.2)
    finally:
        listener.close()
    assert proc.poll() is None, f"companion sitl exited early:\n{run.text()}"
    assert mission.get("name") == "hover"
    assert mission.get("state") == "completed", f"mission telemetry: {mission}\n{run.text()}"

    children = children_of(proc.pid)
    assert len(children) == 2  # the vehicle and the daemon
    sent = time.monotonic()
    os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C: the whole foreground process group
    try:
        rc = proc.wait(EXIT_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        pytest.fail(f"companion sitl still running {EXIT_TIMEOUT_S:g} s after SIGINT:\n{run.text()}")
    took = time.monotonic() - sent
    text = run.text()
    assert rc == 0, text
    assert "companion sitl: stopped" in text
    assert "Traceback" not in text
    assert all(cmdline_of(pid) != cmdline for pid, cmdline in children.items()), "a child outlived the harness"
    print(f"companion sitl exited {took:.2f} s after SIGINT")
