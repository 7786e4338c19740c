"""The built-in fixed wing from the runway, in lockstep: the mission's take-off in the autopilot's TAKEOFF
mode (as on ArduPlane: armed, switched to TAKEOFF, it climbs to its TKOFF_ALT by itself) and a GUIDED
target sent once as a guided waypoint (MISSION_ITEM_INT, current 2), not streamed."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import yaml

from tests.conftest import REPO, free_port

TKOFF_ALT_M = 30.0  # the built-in plane's TKOFF_ALT (sitl/plane_guidance.py PlaneLimits)
TARGET = (400.0, 0.0, -50.0)


def test_a_fixed_wing_takes_off_in_takeoff_mode_and_flies_a_guided_waypoint_sent_once(tmp_path: Path) -> None:
    raw = yaml.safe_load((REPO / "config" / "sitl-fixedwing.yaml").read_text())
    for key in ("start_in_flight", "events"):
        raw["sitl"].pop(key)
    raw["sensors"] = {"imu": raw["sensors"]["imu"]}  # no simulated sensors or pipeline: the flight only
    raw["pipelines"] = {}
    raw["mavlink"]["url"] = f"udpout:127.0.0.1:{(port := free_port())}"
    raw["sitl"]["vehicle_url"] = f"udpin:127.0.0.1:{port}"
    raw["sitl"]["gcs_urls"] = [f"udpout:127.0.0.1:{free_port()}"]
    raw["telemetry"]["listen"] = [f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"]
    mission = {"name": "runway", "steps": [
        {"wait_ready": {"timeout_s": 30}}, {"arm": {"timeout_s": 10}}, {"mode": "TAKEOFF"},
        {"takeoff": {"altitude_m": TKOFF_ALT_M, "timeout_s": 60}}, {"mode": "GUIDED"},
        {"goto": {"position": list(TARGET), "seconds": 30}}]}
    (tmp_path / "missions").mkdir()
    (tmp_path / "missions" / "runway.yaml").write_text(yaml.safe_dump(mission, sort_keys=False))
    (tmp_path / "worlds").symlink_to(REPO / "config" / "worlds")
    raw["mission"]["file"] = "missions/runway.yaml"
    cfg, report_path = tmp_path / "fixedwing.yaml", tmp_path / "report.json"
    cfg.write_text(yaml.safe_dump(raw, sort_keys=False))
    proc = subprocess.run([sys.executable, "-m", "companion.cli", "sitl", "-c", str(cfg), "--mission", "runway",
                           "--lockstep", "--seed", "1", "--report", str(report_path)],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    log_path = next(line.split(" in ")[-1].strip() for line in proc.stdout.splitlines() if "flight log" in line)
    report, log = json.loads(report_path.read_text()), json.loads(Path(log_path).read_text())

    assert report["control"]["mission_completed"], report["control"]
    modes = [mode for _, mode, _ in log["modes"]]
    assert modes.index("TAKEOFF") < modes.index("GUIDED")
    t = np.asarray(log["truth"]["t"])
    pos = np.asarray(log["truth"]["pos_ned"], dtype=float)
    guided_at = next(entry[0] for entry in log["modes"] if entry[1] == "GUIDED")
    assert abs(-np.interp(guided_at, t, pos[:, 2]) - TKOFF_ALT_M) < 5.0  # the take-off ended at TKOFF_ALT
    assert pos[-1, 0] > 250.0  # on its way to (or circling) the target
    sent = np.asarray(log["setpoints"]["pos"], dtype=float)
    assert 1 <= len(sent) <= 2  # one guided waypoint (a second only if the first went unanswered)
    np.testing.assert_allclose(sent[0], TARGET, atol=0.05)
