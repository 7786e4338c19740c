"""The GNSS + optic-flow attitude on the SITL fixed wing in lockstep (config/sitl-fixedwing.yaml, a
one-minute leg instead of Table 1's 300 s): both flow paths (the seed's synthetic flow and the
forward camera's rendered images) scored against the simulator's truth, a held rudder flagged as
uncoordinated flight, and an attitude fault of the autopilot raising the cross-check alarm, with
no alarm outside it. The full Table 1 flight is the README's figure."""

from __future__ import annotations

import json
import math
import socket
import subprocess
import sys
from pathlib import Path

import yaml

from tests.conftest import REPO, free_port

CONFIG = REPO / "config" / "sitl-fixedwing.yaml"
TARGET = (900.0, 900.0, -100.0)  # straight north-east from the start (the faults on the way), then circle
SIDESLIP_S = (20.0, 28.0)
TILT_FAULT_S = (40.0, 52.0)


def fly_leg(tmp_path: Path) -> tuple[dict, dict]:
    """(report, flight log) of the fixed wing flying one leg with the two scripted events."""
    raw = yaml.safe_load(CONFIG.read_text())
    raw["mavlink"]["url"] = f"udpout:127.0.0.1:{(port := free_port())}"
    raw["sitl"]["vehicle_url"] = f"udpin:127.0.0.1:{port}"
    raw["sitl"]["gcs_urls"] = [f"udpout:127.0.0.1:{free_port()}"]
    raw["telemetry"]["listen"] = [f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"]
    raw["sitl"]["events"] = [{"start_s": SIDESLIP_S[0], "end_s": SIDESLIP_S[1], "sideslip_deg_s": 5.0},
                             {"start_s": TILT_FAULT_S[0], "end_s": TILT_FAULT_S[1], "tilt_fault_deg": [0.0, 15.0]}]
    mission = {"name": "leg", "steps": [{"wait_ready": {"timeout_s": 30}}, {"mode": "GUIDED"},
                                        {"goto": {"position": list(TARGET), "seconds": 85}}]}
    (tmp_path / "missions").mkdir()
    (tmp_path / "missions" / "leg.yaml").write_text(yaml.safe_dump(mission, sort_keys=False))
    for folder in ("worlds", "cameras"):
        (tmp_path / folder).symlink_to(REPO / "config" / folder)
    cfg, report = tmp_path / "fixedwing.yaml", tmp_path / "report.json"
    raw["mission"]["file"] = "missions/leg.yaml"
    cfg.write_text(yaml.safe_dump(raw, sort_keys=False))
    proc = subprocess.run([sys.executable, "-m", "companion.cli", "sitl", "-c", str(cfg), "--mission", "leg",
                           "--lockstep", "--seed", "1", "--report", str(report)],
                          cwd=REPO, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    log_path = next(line.split(" in ")[-1].strip() for line in proc.stdout.splitlines() if "flight log" in line)
    return json.loads(report.read_text()), json.loads(Path(log_path).read_text())


def overlaps(intervals: list[list[float]], window: tuple[float, float]) -> bool:
    return any(a <= window[1] and b >= window[0] for a, b in intervals)


def test_the_fixed_wing_s_attitude_from_gnss_and_flow_holds_flags_a_slip_and_alarms_on_a_fault(tmp_path: Path) -> None:
    report, log = fly_leg(tmp_path)
    assert report["control"]["mission_completed"], report["control"]
    assert report["autopilot"]["firmware"].startswith("ArduPilot plane")
    sources = report["attitude"]["sources"]
    assert set(sources) == {"gnss_flow", "gnss_flow.images"}
    for name, scored in sources.items():
        assert scored["count"] > 100, (name, scored)
        assert all(abs(m) < 1.5 for m in scored["euler_mean_deg"]), (name, scored)
        assert all(s < 2.0 for s in scored["euler_std_deg"]), (name, scored)
        # the held rudder is flagged; the autopilot's tilt fault raises the alarm, and nothing else does
        assert overlaps(scored["uncoordinated_intervals_s"], SIDESLIP_S), (name, scored)
        alarms = scored["alarm_intervals_s"]
        assert alarms and all(TILT_FAULT_S[0] <= a and b <= TILT_FAULT_S[1] + 3.0 for a, b in alarms), (name, alarms)
    truth = log["truth"]
    last = [p for t, p in zip(truth["t"], truth["pos_ned"]) if t > truth["t"][-1] - 5.0]
    assert all(20.0 < math.hypot(p[0] - TARGET[0], p[1] - TARGET[1]) < 70.0 for p in last)  # circling the target
