"""The EKF-SLAM return to base flown by the SITL vehicle in lockstep (config/sitl-outdoor.yaml, a
shortened flight out): GNSS jammed at the far end, the mission's takeover to ``return_to_base``,
the way home on the SLAM scored against the simulator's truth, and the autopilot keeping a
position all the way. The full 500 m scenario is the README's figure."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import yaml

from sitl.report import capture_times
from tests.conftest import REPO, free_port

CONFIG = REPO / "config" / "sitl-outdoor.yaml"
OUT_NE = (250.0, 250.0)  # 146 m from the base along the diagonal
JAM_AT_S = 190.0  # since the receiver opened: after the arrival there


def fly_short_return(tmp_path: Path) -> tuple[dict, dict]:
    """(report, flight log) of the outdoor scenario flown out to OUT_NE only."""
    raw = yaml.safe_load(CONFIG.read_text())
    raw["mavlink"]["url"] = f"udpout:127.0.0.1:{(port := free_port())}"
    raw["sitl"]["vehicle_url"] = f"udpin:127.0.0.1:{port}"
    raw["sitl"]["gcs_urls"] = [f"udpout:127.0.0.1:{free_port()}"]
    raw["telemetry"]["listen"] = [f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"]
    raw["sensors"]["gnss"]["settings"]["denied"] = [[JAM_AT_S, 100000]]
    mission = yaml.safe_load((REPO / "config" / "missions" / "gnss-loss-return.yaml").read_text())
    fly = next(step["fly"] for step in mission["steps"] if "fly" in step)
    fly["waypoints"] = [{"position": [*OUT_NE, -100.0]}]
    (tmp_path / "missions").mkdir()
    (tmp_path / "missions" / "short-return.yaml").write_text(yaml.safe_dump(mission, sort_keys=False))
    (tmp_path / "worlds").symlink_to(REPO / "config" / "worlds")
    cfg, report = tmp_path / "outdoor.yaml", tmp_path / "report.json"
    raw["mission"]["file"] = "missions/short-return.yaml"
    cfg.write_text(yaml.safe_dump(raw, sort_keys=False))
    proc = subprocess.run([sys.executable, "-m", "companion.cli", "sitl", "-c", str(cfg), "--mission", "short-return",
                           "--lockstep", "--seed", "1", "--report", str(report)],
                          cwd=REPO, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    log_path = next(line.split(" in ")[-1].strip() for line in proc.stdout.splitlines() if "flight log" in line)
    return json.loads(report.read_text()), json.loads(Path(log_path).read_text())


def test_gnss_jammed_out_there_the_vehicle_flies_home_on_the_ekf_slam_and_the_autopilot_keeps_its_position(
        tmp_path: Path) -> None:
    report, log = fly_short_return(tmp_path)
    assert report["control"]["mission_completed"], report["control"]
    assert report["control"]["failsafes_triggered"] == ["guidance"]  # the takeover on GNSS loss
    assert report["recovery"]["autopilot_position_lost_s"] == 0.0
    assert report["estimate"]["lost_seconds"] == 0.0 and report["autopilot"]["nonfinite_dropped"] == 0
    # At the return altitude, from the jam until over the base: the SLAM pose against the truth at
    # each estimate's capture time.
    t = np.asarray(log["truth"]["t"])
    truth = np.asarray(log["truth"]["pos_ned"])
    vp = log["vision_position"]
    captured = capture_times(log, np.asarray(vp["usec"], dtype=float))
    sent = np.asarray(vp["pos_ned"])
    aloft = (captured > JAM_AT_S) & (sent[:, 2] < -95.0)
    true_at = np.column_stack([np.interp(captured[aloft], t, truth[:, k]) for k in range(2)])
    errors = np.hypot(*(sent[aloft, :2] - true_at).T)
    assert len(errors) > 1000 and np.percentile(errors, 90) < 4.0 and errors.max() < 10.0, np.percentile(errors, [50, 90, 100])
    over_base = np.hypot(sent[aloft, 0] - 353.5, sent[aloft, 1] - 353.5) < 2.0
    assert over_base.any() and errors[over_base].max() < 3.0  # it came home, and knew where it was
