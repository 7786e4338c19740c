"""The seam, proven by a second pose pipeline defined only in the tests (tests/pose_plugin.py):
with the lidar and ``gnss_pose`` both configured (lidar first), unplugging the scanners in flight
switches the pose source to ``gnss_pose`` and ``reset_counter`` increments exactly once; when they
come back the lidar takes back over, ``reset_counter`` increments once more, and the SITL vehicle's
estimator jumps to it (the plugin's 0.4 m offset) at once instead of creeping.

Real time: the real Hokuyo driver behind the SCIP bridge (which unplugs the scanners), the built-in
vehicle with its simulated GPS receiver streaming GPS_RAW_INT, the daemon as a process.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import yaml

from companion.config import load_config
from sitl.rig import Rig, wait_until
from tests.sitl_helpers import real_driver_config

OFFSET_NORTH_M = 0.4  # within the localizer's corner gate (0.5 m): the lidar keeps tracking after the scanners return
UNPLUG_S = 6.0
HOVER_MISSION = {"name": "long hover", "steps": [
    {"wait_ready": {"timeout_s": 60}}, {"mode": "GUIDED"}, {"arm": {}},
    {"takeoff": {"altitude_m": 1.0, "timeout_s": 20}}, {"hold": {"seconds": 60}}, {"land": {"timeout_s": 40}}]}


def two_source_config(work: Path) -> Path:
    path, raw = real_driver_config(work, gps=True)
    raw["plugins"] = ["tests.pose_plugin"]
    raw["sensors"]["gnss"] = {"kind": "gnss", "backend": "autopilot"}
    # claimed as accurate as the lidar: the autopilot's EKF trusts it as much, so only a reset moves it by the offset
    raw["pipelines"]["gnss_pose"] = {"gnss_sensor": "gnss", "offset_ned_m": [OFFSET_NORTH_M, 0.0, 0.0],
                                     "position_sigma_m": 0.05}
    raw["pipelines"]["sources"] = ["lidar", "gnss_pose"]
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def test_killing_the_primary_switches_to_the_secondary_and_each_switch_is_one_jump(tmp_path: Path) -> None:
    mission = tmp_path / "long-hover.yaml"
    mission.write_text(yaml.safe_dump(HOVER_MISSION, sort_keys=False))
    rig = Rig(load_config(two_source_config(tmp_path)), mission, tmp_path / "run", seed=3)
    rig.start()
    try:
        def autopilot_position() -> np.ndarray | None:
            p = rig.telemetry("autopilot").get("local_position_ned_m")
            return None if p is None else np.asarray(p, dtype=float)

        def hovering() -> bool:
            p = autopilot_position()
            return (rig.telemetry("mission").get("step_kind") == "hold" and p is not None and p[2] < -0.8)

        assert wait_until(hovering, 60.0), rig.telemetry("mission")
        time.sleep(2.0)
        sources = rig.telemetry("sources")
        assert sources["active"] == "lidar" and sources["sources"]["gnss_pose"]["fresh"], sources
        resets_before = rig.telemetry("estimate_stats")["reset_counter"]
        gnss_minus_lidar = (np.asarray(sources["sources"]["gnss_pose"]["position_ned_m"])
                            - np.asarray(sources["sources"]["lidar"]["position_ned_m"]))
        assert abs(gnss_minus_lidar[0] - OFFSET_NORTH_M) < 0.6  # the simulated GPS's error is small

        for name in rig.cfg.sitl.scip_sensors:
            rig.bridge_command(f"unplug {name} {UNPLUG_S}")
        assert wait_until(lambda: rig.telemetry("sources").get("active") == "gnss_pose", 10.0), rig.telemetry("sources")
        assert wait_until(lambda: rig.telemetry("estimate_stats")["reset_counter"] == (resets_before + 1) % 256, 1.0)

        # The scanners come back: once the lidar has delivered for pipelines.source_return_s it takes back
        # over, with no gap in the estimates.
        assert wait_until(lambda: rig.telemetry("sources").get("active") == "lidar", UNPLUG_S + 15.0), (
            {k: (v["state"], v["reason"]) for k, v in rig.telemetry("health").get("components", {}).items()
             if k.startswith(("nav", "sensor"))})
        time.sleep(2.0)
        assert rig.telemetry("sources")["active"] == "lidar"
        assert rig.telemetry("estimate_stats")["reset_counter"] == (resets_before + 2) % 256
        assert rig.telemetry("mission").get("state") not in ("failed", "aborted"), rig.telemetry("mission")
    finally:
        rig.close()
    # The vehicle's own log: its estimate (50 Hz) moves by the offset in one step at the VPE that carries
    # the new reset_counter, not over the several updates a Kalman filter would take to absorb it.
    log = json.loads((tmp_path / "run" / "vehicle-0.json").read_text())
    vpe, own = log["vision_position"], log["vehicle_estimate"]
    counters = vpe["reset_counter"]
    changes = [i for i in range(1, len(counters)) if counters[i] != counters[i - 1]]
    assert [counters[i] for i in changes][-2:] == [(resets_before + 1) % 256, (resets_before + 2) % 256]
    t_back = vpe["t_rx"][changes[-1]]
    t, north = np.asarray(own["t"]), np.array([p[0] for p in own["pos_ned"]])
    around = (t > t_back - 0.1) & (t < t_back + 0.3)
    steps = np.diff(north[around])
    assert -steps.min() > 0.8 * OFFSET_NORTH_M, np.round(steps, 3)  # back south by the offset, at once
