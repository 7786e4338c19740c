"""`companion setup-autopilot`: the parameters the configured pipelines need, per firmware
generation (pure), and the whole command against a real ArduCopter SITL (skipped without it)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from companion.config import load_config
from companion.mavlink.firmware import Firmware
from companion.mavlink.requirements import differences, requirements, without_gps_arming_check
from sitl.ardupilot import ArduPilotSitl, SitlOptions, default_defaults, home_at
from tests.ardupilot_helpers import ARDUCOPTER, requires_ardupilot, write_ardupilot_config
from tests.conftest import REPO

COPTER_40 = Firmware("ArduPilot", "copter", (4, 0, 5), "rc")
COPTER_45 = Firmware("ArduPilot", "copter", (4, 5, 7))


def lidar_config(tmp_path: Path):  # noqa: ANN201
    return load_config(write_ardupilot_config(tmp_path))


def test_arducopter_40_gets_ekf2_external_navigation_and_keeps_every_arming_check_but_gps(tmp_path: Path) -> None:
    params = {"GPS_TYPE": 1, "EK2_GPS_TYPE": 0, "VISO_TYPE": 0, "COMPASS_USE": 1, "COMPASS_USE2": 1,
              "COMPASS_USE3": 1, "ARMING_CHECK": 1, "FS_EKF_ACTION": 1, "FS_THR_ENABLE": 1, "EK2_POSNE_M_NSE": 0.1}
    needed = requirements(COPTER_40, lidar_config(tmp_path), params)
    diff = {d.name: d for d in differences(needed, params)}
    assert set(diff) == {"GPS_TYPE", "EK2_GPS_TYPE", "VISO_TYPE", "COMPASS_USE", "COMPASS_USE2", "COMPASS_USE3",
                         "ARMING_CHECK", "FS_THR_ENABLE"}
    assert diff["VISO_TYPE"].reboot and diff["GPS_TYPE"].reboot and not diff["EK2_GPS_TYPE"].reboot
    assert diff["ARMING_CHECK"].wanted == 65526  # bits 1..15 without GPS (8)
    assert without_gps_arming_check(65526 | 8) == 65526 and without_gps_arming_check(0) == 0


def test_firmware_with_ekf3_source_sets_gets_them_and_the_renamed_gps_parameter(tmp_path: Path) -> None:
    params = {"GPS1_TYPE": 1, "VISO_TYPE": 0, "AHRS_EKF_TYPE": 2, "EK3_ENABLE": 0, "EK3_SRC1_POSXY": 3,
              "EK3_SRC1_VELXY": 3, "EK3_SRC1_POSZ": 1, "EK3_SRC1_VELZ": 3, "EK3_SRC1_YAW": 1, "EK2_GPS_TYPE": 0}
    names = {r.name for r in requirements(COPTER_45, lidar_config(tmp_path), params)}
    assert {"GPS1_TYPE", "EK3_SRC1_POSXY", "EK3_SRC1_YAW", "AHRS_EKF_TYPE"} <= names
    assert "EK2_GPS_TYPE" not in names and "GPS_TYPE" not in names


def test_the_companion_port_gets_mavlink_2_at_921600_when_the_config_names_it(tmp_path: Path) -> None:
    cfg = lidar_config(tmp_path)
    params = {"SERIAL2_PROTOCOL": 1, "SERIAL2_BAUD": 57, "GPS_TYPE": 0}
    assert "SERIAL2_PROTOCOL" not in {r.name for r in requirements(COPTER_40, cfg, params)}
    cfg.mavlink.autopilot_serial_port = 2
    diff = {d.name: d for d in differences(requirements(COPTER_40, cfg, params), params)}
    assert diff["SERIAL2_PROTOCOL"].wanted == 2 and diff["SERIAL2_BAUD"].wanted == 921 and diff["SERIAL2_BAUD"].reboot


def test_a_gnss_grade_pose_source_keeps_the_compass_and_gets_its_noise_in_ekf2() -> None:
    """ekf_slam follows the autopilot's heading: with the compass off, EKF2 would take its yaw from
    the SLAM and the SLAM from EKF2, and neither would know the true heading. EKF2 4.0 takes its
    position noise from EK2_POSNE_M_NSE, not the message: the SLAM's 0.7 m, not the lidar's 0.1."""
    cfg = load_config(REPO / "config" / "sitl-outdoor.yaml")
    params40 = {"GPS_TYPE": 1, "EK2_GPS_TYPE": 0, "VISO_TYPE": 0, "COMPASS_USE": 0, "COMPASS_USE2": 1,
                "COMPASS_USE3": 1, "ARMING_CHECK": 1, "EK2_POSNE_M_NSE": 0.1}
    diff = {d.name: d.wanted for d in differences(requirements(COPTER_40, cfg, params40), params40)}
    assert diff["COMPASS_USE"] == 1 and "COMPASS_USE2" not in diff and diff["EK2_GPS_TYPE"] == 3
    assert diff["EK2_POSNE_M_NSE"] == 0.7
    params45 = {"GPS1_TYPE": 1, "VISO_TYPE": 0, "AHRS_EKF_TYPE": 3, "EK3_ENABLE": 1, "EK3_SRC1_POSXY": 3,
                "EK3_SRC1_VELXY": 3, "EK3_SRC1_POSZ": 1, "EK3_SRC1_VELZ": 3, "EK3_SRC1_YAW": 6}
    diff = {d.name: d.wanted for d in differences(requirements(COPTER_45, cfg, params45), params45)}
    assert diff["EK3_SRC1_YAW"] == 1 and diff["EK3_SRC1_POSXY"] == 6


def test_a_config_without_a_position_pipeline_needs_nothing(tmp_path: Path) -> None:
    cfg = lidar_config(tmp_path)
    cfg.pipelines.enabled.clear()
    assert requirements(COPTER_40, cfg, {"GPS_TYPE": 1, "VISO_TYPE": 0}) == []


def setup_autopilot(config: Path, url: str, *flags: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "companion.cli", "setup-autopilot", "-c", str(config),
                           "--mavlink", url, *flags], cwd=REPO, capture_output=True, text=True, timeout=90)


@requires_ardupilot
def test_setup_autopilot_shows_the_difference_writes_it_and_then_finds_nothing(tmp_path: Path) -> None:
    config = write_ardupilot_config(tmp_path)
    cfg = load_config(config)
    sitl = ArduPilotSitl(SitlOptions(ARDUCOPTER, "+", default_defaults(ARDUCOPTER),
                                     home_at((cfg.origin.lat, cfg.origin.lon, cfg.origin.alt), (1.0, 1.0, 0.0))),
                         tmp_path / "ardupilot")
    sitl.start(wipe=True)
    try:
        assert sitl.wait_listening(), sitl.output.read_text()
        dry = setup_autopilot(config, sitl.url(2))
        assert dry.returncode == 3, dry.stdout + dry.stderr  # differences remain: dry run
        assert "ArduPilot copter 4.0.5-rc" in dry.stdout
        for name in ("GPS_TYPE", "EK2_GPS_TYPE", "VISO_TYPE", "COMPASS_USE", "ARMING_CHECK", "FS_THR_ENABLE"):
            assert name in dry.stdout
        assert "Dry run: nothing written" in dry.stdout

        applied = setup_autopilot(config, sitl.url(2), "--apply")
        assert applied.returncode == 0, applied.stdout + applied.stderr
        assert "VISO_TYPE: 0 -> 1 (read back)" in applied.stdout
        assert "ARMING_CHECK: 1 -> 65526 (read back)" in applied.stdout
        assert "reboot the autopilot for VISO_TYPE, GPS_TYPE" in applied.stdout

        again = setup_autopilot(config, sitl.url(2))
        assert again.returncode == 0, again.stdout + again.stderr
        assert "nothing to change" in again.stdout
    finally:
        sitl.stop()
    assert sitl.internal_errors() == []
