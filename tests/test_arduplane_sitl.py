"""The GNSS + optic-flow attitude on the real ArduPlane 4.0.7 SITL (../shared/ardupilot; skipped without it).

`companion sitl -c config/sitl-arduplane.yaml --ardupilot .../arduplane` as a user runs it, with a
shorter flight: armed, ArduPlane's TAKEOFF mode to 100 m, two guided waypoints; the harness sets
AHRS_TRIM_Y mid-flight (the autopilot's pitch 15 deg off the truth, which it flies on). The report's
attitude block is scored against SITL's own SIMSTATE truth.
"""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.ardupilot_helpers import ARDUPILOT_DIR
from tests.conftest import REPO, free_port

ARDUPLANE = ARDUPILOT_DIR / "arduplane"
pytestmark = pytest.mark.skipif(not os.access(ARDUPLANE, os.X_OK), reason=f"no ArduPlane SITL binary at {ARDUPLANE}")
TAKEOFF_M = 100.0
FAULT_S = (78.0, 90.0)  # AHRS_TRIM_Y 0.26 rad (15 deg) between these flight seconds: on the straight north leg
ALARM_HOLD_S = 2.0  # pipelines.attitude_alarm_s: an alarm starts this long after the fault at the earliest
MISSION = {"name": "arduplane-short", "steps": [
    {"arm": {"timeout_s": 60}},
    {"mode": "TAKEOFF"},
    {"takeoff": {"altitude_m": TAKEOFF_M, "timeout_s": 120}},
    {"mode": "GUIDED"},
    {"goto": {"position": [850.0, 0.0, -TAKEOFF_M], "seconds": 40}},
    {"goto": {"position": [850.0, 600.0, -TAKEOFF_M], "seconds": 40}},
    {"goto": {"position": [250.0, 600.0, -TAKEOFF_M], "seconds": 30}},
]}  # armed at about 37 s (ArduPlane's pre-arm checks), at 100 m (GUIDED) at 60 s, straight north 75-97 s


def write_config(directory: Path) -> Path:
    """config/sitl-arduplane.yaml with free ports, the short mission and the fault at FAULT_S."""
    raw = yaml.safe_load((REPO / "config" / "sitl-arduplane.yaml").read_text())
    raw["telemetry"]["listen"] = [f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"]
    raw["sitl"]["gcs_urls"] = [f"udpout:127.0.0.1:{free_port()}"]
    raw["sitl"]["ardupilot"]["binary"] = str(ARDUPLANE)
    raw["sitl"]["ardupilot"]["parameter_events"] = [
        {"at_s": FAULT_S[0], "name": "AHRS_TRIM_Y", "value": 0.26}, {"at_s": FAULT_S[1], "name": "AHRS_TRIM_Y", "value": 0.0}]
    (directory / "mission.yaml").write_text(yaml.safe_dump(MISSION, sort_keys=False))
    raw["mission"]["file"] = str(directory / "mission.yaml")
    for name in ("cameras", "worlds"):
        (directory / name).symlink_to(REPO / "config" / name)
    path = directory / "companion.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def test_arduplane_takes_off_flies_guided_waypoints_and_the_cross_check_alarms_on_the_attitude_fault_only(
        tmp_path: Path) -> None:
    report_path = tmp_path / "r.json"
    proc = subprocess.run([sys.executable, "-m", "companion.cli", "sitl", "-c", str(write_config(tmp_path)),
                           "--ardupilot", str(ARDUPLANE), "--seed", "1", "--report", str(report_path)],
                          cwd=REPO, capture_output=True, text=True, timeout=420)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]
    report = json.loads(report_path.read_text())
    found = re.search(r"flight log \(truth, everything the autopilot received\) in (\S+)", proc.stdout)
    assert found is not None, proc.stdout[-2000:]
    log = json.loads(Path(found.group(1)).read_text())

    assert report["autopilot"]["firmware"] == "ArduPilot plane 4.0.7"
    # ArduPlane 4.0.7 SITL sometimes panics writing to SERIAL0 just after the daemon hung up at the end
    # of the run ("Short write on UART"; seen in 1 of 3 runs): after the flight, so it is tolerated (the
    # harness reports it but does not count that exit as the vehicle dying: `companion sitl` exits 0)
    assert set(report["autopilot"]["internal_errors"]) <= {"Short write on UART: 0 < 10"}
    assert report["control"]["mission_completed"]
    modes = [mode for _, mode, _ in log["modes"]]
    assert modes.index("TAKEOFF") < modes.index("GUIDED")  # (then RTL: the daemon stopping leaves a plane in RTL)
    truth = np.asarray(log["truth"]["pos_ned"], dtype=float)
    assert (-truth[:, 2]).max() == pytest.approx(TAKEOFF_M, abs=10.0)  # took off to 100 m (truth)
    assert truth[:, 0].max() > 450.0 and truth[:, 1].max() > 450.0  # flew to both waypoints (80 m loiter radius)
    assert len(log["setpoints"]["t_rx"]) <= 10  # guided waypoints sent on change, not streamed

    source = report["attitude"]["sources"]["gnss_flow"]
    assert source["count"] > 100
    roll_std, pitch_std, _ = source["euler_std_deg"]
    assert roll_std < 2.0 and pitch_std < 3.5  # (four runs: roll 0.9-1.4, pitch 2.1-2.8 deg)
    alarms = source["alarm_intervals_s"]
    assert alarms, "no cross-check alarm while the autopilot's pitch was 15 deg off"
    assert all(FAULT_S[0] + ALARM_HOLD_S - 1.0 <= start and end <= FAULT_S[1] + 5.0 for start, end in alarms), alarms
