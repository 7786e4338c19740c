"""`companion sitl --report`: the truth-scored flight report of a lockstep run, end to end.

Each run is the real thing: ``python -m companion.cli sitl`` starts the SITL vehicle and the
daemon as separate processes talking MAVLink over loopback UDP (free ports), in lockstep, and
scores the flight against the vehicle's ground truth.
"""

from __future__ import annotations

import copy
import json
import math
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.scoring import effective_samples, heading_nees, nees_band
from sitl.harness import cpu_jiffies, steal_percent
from sitl.report import attitude_errors, cross_track_max, position_nees, wrong_resets
from tests.conftest import REPO, free_port
from tests.sitl_helpers import write_config, write_sitl_config

SCHEMA_1 = {
    "schema": None, "mission": None, "seconds": None, "lockstep": None, "seed": None,
    "estimate": {"position_rms_m", "position_max_m", "yaw_rms_deg", "attitude_rms_deg", "height_rms_m", "fix_rate_hz", "lost_seconds",
                 "nees_mean", "nees_band", "nees_max", "yaw_nees_mean", "yaw_nees_band", "cross_track_max_m",
                 "wrong_resets"},
    "autopilot": {"origin_confirmed", "external_nav_in_use", "vision_position_estimate_hz",
                  "vision_speed_estimate_hz", "setpoint_hz", "nonfinite_dropped", "firmware", "internal_errors"},
    "control": {"law", "mission_completed", "tracking_rms_m", "tracking_max_m", "failsafes_triggered", "degraded_slowdowns"},
    "timing": {"lidar_ms_p50", "lidar_ms_p99", "fusion_ms_p50", "loop_jitter_ms_p99", "cpu_percent", "rss_mb",
               "cpu_steal_percent"},
}
MACHINE_DEPENDENT = ("cpu_percent", "rss_mb", "cpu_steal_percent")  # measured on the wall clock of this machine


@pytest.fixture(scope="module")
def sitl_config(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A config on free ports, beside a copy of config/missions (``--mission NAME`` looks there)."""
    directory = tmp_path_factory.mktemp("sitl-report")
    shutil.copytree(REPO / "config" / "missions", directory / "missions")
    return write_config(directory / "companion.yaml", vehicle_port=free_port(),
                        zenoh_port=free_port(socket.SOCK_STREAM))


def run_sitl(config: Path, seed: int, out: Path) -> dict:
    """`companion sitl --mission hover --lockstep --seed S --seconds 30 --report`; the report."""
    report = out / f"report-seed{seed}-{len(list(out.glob('report-*')))}.json"
    proc = subprocess.run(
        [sys.executable, "-m", "companion.cli", "sitl", "--mission", "hover", "--lockstep", "--seed", str(seed),
         "--seconds", "30", "--report", str(report), "-c", str(config)],
        cwd=REPO, capture_output=True, text=True, timeout=50)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return json.loads(report.read_text())


@pytest.fixture(scope="module")
def reports(sitl_config: Path) -> dict[str, dict]:
    """Three runs: seed 1 twice and seed 2 once."""
    out = sitl_config.parent
    return {"first": run_sitl(sitl_config, 1, out), "again": run_sitl(sitl_config, 1, out),
            "other_seed": run_sitl(sitl_config, 2, out)}


def without_machine_figures(report: dict) -> dict:
    report = copy.deepcopy(report)
    for key in MACHINE_DEPENDENT:
        report["timing"].pop(key)
    return report


def test_report_has_exactly_the_schema_1_keys(reports: dict[str, dict]) -> None:
    report = reports["first"]
    assert set(report) == set(SCHEMA_1)
    for section, keys in SCHEMA_1.items():
        if keys is not None:
            assert set(report[section]) == keys, section
    assert report["schema"] == 1
    assert (report["mission"], report["seconds"], report["lockstep"], report["seed"]) == ("hover", 30.0, True, 1)


def test_the_machine_figures_say_how_busy_the_host_was(reports: dict[str, dict]) -> None:
    timing = reports["first"]["timing"]
    assert timing["cpu_percent"] > 0.0 and timing["rss_mb"] > 0.0
    assert 0.0 <= timing["cpu_steal_percent"] <= 100.0  # Linux: /proc/stat has a steal column


def test_steal_percent_is_the_stolen_share_of_the_cpu_time_between_two_readings() -> None:
    assert steal_percent((100, 10_000), (150, 11_000)) == 5.0
    assert steal_percent(None, (150, 11_000)) is None and steal_percent((100, 10_000), (100, 10_000)) is None
    steal, total = cpu_jiffies()
    assert 0 <= steal <= total


def test_hover_mission_completes_with_confirmed_origin_and_setpoint_keepalive(reports: dict[str, dict]) -> None:
    report = reports["first"]
    assert report["control"]["mission_completed"] is True
    assert report["autopilot"]["origin_confirmed"] is True
    assert report["autopilot"]["setpoint_hz"] >= 10.0 * (1 - 1e-9)  # the >= 10 Hz keepalive
    assert isinstance(report["control"]["tracking_rms_m"], float)
    assert 0.0 < report["control"]["tracking_rms_m"] <= report["control"]["tracking_max_m"] < 2.0
    assert report["autopilot"]["nonfinite_dropped"] == 0


def test_estimate_figures_are_null_without_a_pipeline(reports: dict[str, dict]) -> None:
    """No navigation pipeline yet: nothing is invented, every estimate figure is null."""
    report = reports["first"]
    assert all(value is None for value in report["estimate"].values()), report["estimate"]
    assert report["autopilot"]["vision_position_estimate_hz"] is None
    assert report["autopilot"]["vision_speed_estimate_hz"] is None
    assert report["autopilot"]["external_nav_in_use"] is False  # the vehicle flew on its simulated GPS
    assert report["timing"]["lidar_ms_p50"] is None and report["timing"]["fusion_ms_p50"] is None


def test_same_seed_gives_the_identical_report(reports: dict[str, dict]) -> None:
    assert without_machine_figures(reports["first"]) == without_machine_figures(reports["again"])


def test_another_seed_gives_other_tracking_figures(reports: dict[str, dict]) -> None:
    first, other = reports["first"]["control"], reports["other_seed"]["control"]
    assert other["mission_completed"] is True
    assert other["tracking_rms_m"] != first["tracking_rms_m"]
    assert other["tracking_max_m"] != first["tracking_max_m"]


def test_without_seconds_a_report_run_ends_when_the_mission_is_over(sitl_config: Path) -> None:
    report = sitl_config.parent / "report-until-mission-end.json"
    proc = subprocess.run(
        [sys.executable, "-m", "companion.cli", "sitl", "--mission", "hover", "--lockstep", "--seed", "1",
         "--report", str(report), "-c", str(sitl_config)],
        cwd=REPO, capture_output=True, text=True, timeout=90)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    result = json.loads(report.read_text())
    assert result["control"]["mission_completed"] is True
    assert 15.0 < result["seconds"] < 60.0  # the hover takes about 20 s of simulation


def test_a_second_run_on_the_same_ports_is_refused(tmp_path: Path) -> None:
    vehicle_port, zenoh_port = free_port(), free_port(socket.SOCK_STREAM)
    config = write_sitl_config(tmp_path / "sitl.yaml", vehicle_port=vehicle_port, gcs_port=free_port(),
                               zenoh_port=zenoh_port, mission=None)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other_vehicle:
        other_vehicle.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as pymavlink's udpin does
        other_vehicle.bind(("127.0.0.1", vehicle_port))
        proc = subprocess.run([sys.executable, "-m", "companion.cli", "sitl", "-c", str(config), "--seconds", "1"],
                              cwd=REPO, capture_output=True, text=True, timeout=30)
    assert proc.returncode == 2
    assert f"UDP 127.0.0.1:{vehicle_port} (sitl.vehicle_url)" in proc.stderr


def test_nees_is_3_for_errors_drawn_from_the_sent_covariance_and_scales_with_it() -> None:
    rng = np.random.default_rng(1)
    cov = np.array([[4e-4, 1e-4, 0.0], [1e-4, 2e-4, 0.0], [0.0, 0.0, 1e-4]])
    errors = rng.multivariate_normal(np.zeros(3), cov, 20000)
    triangle = [cov[0, 0], cov[0, 1], cov[0, 2], cov[1, 1], cov[1, 2], cov[2, 2]]
    assert np.mean(position_nees(errors, [triangle] * len(errors))) == pytest.approx(3.0, abs=0.1)
    assert np.mean(position_nees(errors, [[4 * v for v in triangle]] * len(errors))) == pytest.approx(0.75, abs=0.03)
    assert position_nees(errors[:2], [[None] * 6, [None] * 6]).size == 0


def test_the_yaw_nees_is_1_for_errors_drawn_from_the_sent_variance_and_skips_estimates_without_one() -> None:
    rng = np.random.default_rng(3)
    errors = rng.normal(0.0, 0.01, 20000)
    assert np.mean(heading_nees(errors, [1e-4] * len(errors))) == pytest.approx(1.0, abs=0.05)
    assert np.mean(heading_nees(errors, [4e-4] * len(errors))) == pytest.approx(0.25, abs=0.02)
    assert heading_nees(errors[:3], [None, 0.0, float("nan")]).size == 0


def test_the_nees_band_counts_correlated_estimates_as_the_independent_ones_they_are_worth() -> None:
    """Independent samples count one each; the same samples each repeated 30 times (estimates at
    30 Hz of a once-a-second error) are worth about the original number, so the band is as wide."""
    rng = np.random.default_rng(2)
    independent = rng.chisquare(3, 200)
    repeated = np.repeat(independent, 30)
    assert effective_samples(independent) == pytest.approx(200, rel=0.3)
    assert effective_samples(repeated) == pytest.approx(200, rel=0.5)
    lo, hi = nees_band(repeated, 3)
    assert lo < 3 < hi and hi - lo == pytest.approx(2 * 1.96 * np.sqrt(6 / effective_samples(repeated)))
    assert hi - lo > 4 * (nees_band(np.tile(independent, 30), 3)[1] - 3)  # shuffled repeats: 6000 independent


def test_a_reset_far_from_the_truth_is_a_wrong_one() -> None:
    truth = np.zeros((6, 3))
    estimate = np.array([[0.0, 0, 0], [0.1, 0, 0], [3.0, 0, 0], [3.0, 0, 0], [0.2, 0.0, 0], [0.0, 0.1, 0]])
    counter = np.array([0, 0, 1, 1, 2, 2])  # reset to 3 m off (wrong), then back within 0.2 m (right)
    assert wrong_resets(counter, estimate, truth) == 1


def test_the_cross_track_error_is_taken_along_the_direction_the_estimate_is_sure_of() -> None:
    """A corridor running north: the covariance is sure of east (cross-track), not of north; a
    2 m north error and a 3 cm east error give 3 cm. Turned by 90 deg, the same error gives 2 m."""
    corridor = [100.0, 0.0, 0.0, 1e-4, 0.0, 1e-4]
    turned = [1e-4, 0.0, 0.0, 100.0, 0.0, 1e-4]
    errors = np.array([[2.0, 0.03], [-1.0, -0.01]])
    assert cross_track_max(errors, [corridor, corridor]) == pytest.approx(0.03)
    assert cross_track_max(errors, [turned, turned]) == pytest.approx(2.0)
    assert cross_track_max(errors, [[None] * 6, [float("nan")] * 6]) is None


def test_attitude_error_combines_roll_pitch_and_yaw_as_one_rotation_angle() -> None:
    t = np.array([0.0, 1.0])
    truth = np.array([[0.0, 0.0, math.radians(179.9)], [0.0, 0.0, math.radians(179.9)]])
    estimate = np.array([[math.radians(0.3), math.radians(0.4), math.radians(179.9)],  # 0.5 deg tilt error
                         [0.0, 0.0, math.radians(-179.9)]])  # 0.2 deg of yaw across the wrap
    errors = np.degrees(attitude_errors(estimate, t, t, truth))
    assert errors == pytest.approx([0.5, 0.2], abs=2e-3)
