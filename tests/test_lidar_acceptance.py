"""Issue acceptance for the two-lidar localization and for flight control: lockstep, seeded SITL
runs of config/sitl.yaml (two simulated Hokuyos, no GPS, the autopilot fusing the companion's
estimate, trajectories flown with the RPT controller), scored by the flight report against
simulator ground truth.

Thresholds are the issues' (survey-points: position and height RMS <= 3 cm, yaw RMS <= 0.5 deg,
no lost time, the paper reports 4-13 cm; patrol: tracking RMS <= 0.10 m, max <= 0.25 m,
estimate RMS <= 0.05 m, no failsafe). Runs are deterministic for a seed, so these are behaviour
checks, not timing checks; speed figures live in `companion bench`.
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.conftest import REPO, free_port
from tests.sitl_helpers import write_sitl_config


def fly(tmp_path: Path, mission: str, seconds: float | None, seed: int = 1, initial_pose: bool = True,
        config: str = "sitl.yaml") -> dict:
    """The flight report of ``mission`` flown with config/``config`` (``seconds`` None: until the
    mission is over)."""
    cfg = write_sitl_config(tmp_path / "sitl.yaml", vehicle_port=free_port(), gcs_port=free_port(),
                            zenoh_port=free_port(socket.SOCK_STREAM), mission=None, source=config)
    if not initial_pose:
        raw = yaml.safe_load(cfg.read_text())
        raw["pipelines"]["lidar"]["initial_pose"] = None
        cfg.write_text(yaml.safe_dump(raw, sort_keys=False))
    report = tmp_path / "report.json"
    proc = subprocess.run(
        [sys.executable, "-m", "companion.cli", "sitl", "-c", str(cfg), "--mission", mission, "--lockstep",
         "--seed", str(seed), "--report", str(report), *(["--seconds", str(seconds)] if seconds else [])],
        cwd=REPO, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(report.read_text())


@pytest.fixture(autouse=True)
def missions_beside_the_config(tmp_path: Path) -> None:
    """`--mission NAME` looks in missions/ beside the config file."""
    (tmp_path / "missions").symlink_to(REPO / "config" / "missions")


def test_survey_points_meets_the_accuracy_targets_against_truth(tmp_path: Path) -> None:
    r = fly(tmp_path, "survey-points", 140)
    est, ap = r["estimate"], r["autopilot"]
    assert r["control"]["mission_completed"]
    assert ap["external_nav_in_use"] and ap["origin_confirmed"]
    assert est["position_rms_m"] <= 0.03
    assert est["height_rms_m"] <= 0.03  # includes the hold over the table
    assert est["yaw_rms_deg"] <= 0.5
    assert est["lost_seconds"] == 0.0
    assert ap["nonfinite_dropped"] == 0
    assert 28.0 <= ap["vision_position_estimate_hz"] <= 31.0
    assert est["fix_rate_hz"] >= 10.0  # the paper's 10 Hz; a UTM-30LX gives 40


def test_patrol_flies_every_room_on_the_lidar_estimate_with_the_rpt_controller(tmp_path: Path) -> None:
    r = fly(tmp_path, "patrol", 150)
    control = r["control"]
    assert control["mission_completed"] and control["law"] == "rpt"
    assert r["autopilot"]["external_nav_in_use"]
    assert control["tracking_rms_m"] <= 0.10
    assert control["tracking_max_m"] <= 0.25
    assert control["failsafes_triggered"] == []
    assert r["estimate"]["position_rms_m"] <= 0.03  # the issue asks 0.05; the localization issue 0.03
    assert r["estimate"]["lost_seconds"] == 0.0
    assert r["autopilot"]["setpoint_hz"] >= 45.0  # the 50 Hz control loop streams its setpoints


@pytest.mark.parametrize(("config", "mission", "seconds"), [("sitl-declared.yaml", "patrol", 150),
                                                        ("sitl-corridor-declared.yaml", "corridor", None)])
def test_told_the_simulator_s_noise_the_estimate_s_covariance_is_consistent(
        tmp_path: Path, config: str, mission: str, seconds: float | None) -> None:
    """With the built-in vehicle's and the clean world's noise declared (config/sitl-declared.yaml),
    the NEES of the estimates sent is inside its 95 % band: the covariance is honest when its noise
    models are (with config/sitl.yaml's real-vehicle defaults it is cautious, about 0.08)."""
    r = fly(tmp_path, mission, seconds, config=config)
    est = r["estimate"]
    assert r["control"]["mission_completed"] and est["wrong_resets"] == 0
    low, high = est["nees_band"]
    assert low <= est["nees_mean"] <= high, est


def test_an_unknown_start_pose_is_found_by_global_relocalization(tmp_path: Path) -> None:
    r = fly(tmp_path, "hover", 30, seed=3, initial_pose=False)
    assert r["control"]["mission_completed"]
    assert r["estimate"]["position_rms_m"] <= 0.03
    assert r["estimate"]["yaw_rms_deg"] <= 0.5


def test_the_realistic_arena_patrol_meets_the_localization_targets(tmp_path: Path) -> None:
    """config/sitl-realistic.yaml: the arena as built (walls 1-3 cm off the map, a glass panel,
    furniture, two people walking) localized in the surveyed map (2 cm survey error, a corner
    missing), scanners with mixed pixels, a 1 deg mounting error, motion distortion and dropouts.
    The localization issue's targets: position RMS <= 5 cm, max <= 20 cm, yaw RMS <= 1 deg, no
    wrong reset, NEES inside its 95 % band, the yaw's too (0.46 in 0.34-1.66 on 2026-12-06; 0.15,
    cautious, with the fusion's yaw process noise at 0.005 rad/sqrt(s))."""
    r = fly(tmp_path, "patrol", None, config="sitl-realistic.yaml")
    est = r["estimate"]
    assert r["control"]["mission_completed"] and r["control"]["failsafes_triggered"] == []
    assert est["position_rms_m"] <= 0.05 and est["position_max_m"] <= 0.20
    assert est["yaw_rms_deg"] <= 1.0 and est["wrong_resets"] == 0
    low, high = est["nees_band"]
    assert low <= est["nees_mean"] <= high, est
    low, high = est["yaw_nees_band"]
    assert low <= est["yaw_nees_mean"] <= high, est


def test_the_corridor_slows_down_while_no_corner_is_in_view_and_never_flies_on_a_confident_wrong_pose(
        tmp_path: Path) -> None:
    """config/sitl-corridor.yaml: a 60 m corridor whose only corners are door recesses, with a
    stretch between them where no corner is in view. The walls keep the cross-track position and
    the ends of the walls at the recesses' edges the along-track one (without them the along-track
    variance grows on the IMU and, this slowly through that stretch, passed the 1 m withdrawal:
    tests/test_nav_planar.py has the unmeasured case); the mission slows down while no corner is
    matched and reaches the north end. Whole-millimetre ranges, as SCIP reports them: without the
    wall ends that alone decided whether this flight got through."""
    r = fly(tmp_path, "corridor", None, config="sitl-corridor.yaml")
    est, control = r["estimate"], r["control"]
    assert control["mission_completed"] and control["failsafes_triggered"] == []
    # Slowed down: a few times per recess (24-31 on 2026-12-03), not with every flickering scan (299
    # before the mission waited 1 s of a healthy estimate to speed up again).
    assert 1 <= control["degraded_slowdowns"] <= 40
    assert est["cross_track_max_m"] <= 0.05 and est["wrong_resets"] == 0
    # 5-7 cm on 2026-12-03; 0.42-0.5 m while the along-track position went unmeasured between the recesses.
    assert est["position_max_m"] <= 0.2 and est["lost_seconds"] == 0.0
    low, high = est["nees_band"]
    assert est["nees_mean"] <= high, est  # never over-confident


def test_the_realistic_corridor_keeps_its_cross_track_position_and_is_never_over_confident(tmp_path: Path) -> None:
    """config/sitl-corridor-realistic.yaml: the corridor as built (walls 1-3 cm off the map, things
    on the walls, a person walking, an uneven floor) localized in the surveyed map (2 cm survey
    error, a recess's back corner missing), with the realistic scanners' errors. The recess's back
    corners lie 20 cm from its mouth's: paired by distance alone, the flight locked 21 cm off across
    the corridor (NEES 4.45) until only corners whose walls run the same ways were paired. No single
    estimate is confidently wrong: a recess edge 7 m ahead seen through mixed pixels put seed 2's
    0.23 m off along the corridor at a 2.6 cm sigma (NEES 79) until its end's variance said so."""
    r = fly(tmp_path, "corridor", None, config="sitl-corridor-realistic.yaml")
    est, control = r["estimate"], r["control"]
    assert control["mission_completed"] and control["failsafes_triggered"] == []
    assert est["cross_track_max_m"] <= 0.05 and est["wrong_resets"] == 0 and est["lost_seconds"] == 0.0
    assert est["position_rms_m"] <= 0.05 and est["position_max_m"] <= 0.2
    low, high = est["nees_band"]
    assert low <= est["nees_mean"] <= high, est
    assert est["nees_max"] < 25.0, est  # 15-18 for seeds 1-3 on 2026-12-06; 3 dof: 25 is passed once in 60,000
    assert est["yaw_nees_mean"] <= est["yaw_nees_band"][1], est  # 1.3-1.7 for seeds 1-3, bands up to 2.0-2.1
