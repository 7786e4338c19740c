"""Poses of a walk without poses, by scan matching (companion/nav/scan_poses.py), and `companion map
build` on such a log: on a simulated walk through the arena (truth known) and on the real
URG-04LX recording (its wheel odometry as the check)."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from companion.cli import main
from companion.messages import Scan
from companion.nav.bench_stages import DEFAULT_WORLD, make_mount, synthetic_scan
from companion.mapping import MATCHED_POSES, write_world
from companion.nav.map_build import BuiltMap, MapBuildParams, build_map
from companion.nav.scan_poses import scan_poses
from companion.recording.mcap_files import FILE_GLOB
from companion.world import load_world
from drivers.lidar_models import UTM_30LX
from drivers.lidar_replay import breezyslam_angles, breezyslam_valid, read_breezyslam, record_npz
from sitl.raycast import WorldGeometry
from tests.test_flight_recorder import recorder
from companion.nav.bench_robustness import arena_path
from tests.test_real_corridor import CALIBRATED_SCALE, CORRIDOR, odometry_heading


@pytest.fixture(scope="module")
def walk() -> tuple[np.ndarray, list[Scan]]:
    """A scanner carried along the arena path (a scan every 16 cm, turning 360 deg in all), 1 cm
    range noise: the true poses and the scans."""
    geometry = WorldGeometry.from_world(load_world(DEFAULT_WORLD))
    rng = np.random.default_rng(41)
    path = arena_path()[::2]
    scans = [synthetic_scan(geometry, UTM_30LX, make_mount((0, 0, 0), (0, 0, 0)), np.array([x, y, -1.0]), (0, 0, yaw),
                            rng, 0.01) for x, y, yaw in path]
    return path, [Scan("walk", 0.1 * k, s.angles_rad, s.ranges_m, s.valid, sequence=k) for k, s in enumerate(scans)]


def points(scan: Scan) -> tuple[np.ndarray, np.ndarray]:
    return np.column_stack((scan.ranges_m * np.cos(scan.angles_rad), scan.ranges_m * np.sin(scan.angles_rad))), scan.valid


def test_a_walk_is_placed_within_centimetres_of_its_true_path(walk: tuple[np.ndarray, list[Scan]]) -> None:
    """24 m through four rooms and their doors: every pose (in the first scan's frame) within
    5 cm and 1 deg of the truth (the drift of a matcher without loop closure, at this length)."""
    path, scans = walk
    poses = scan_poses(points(s) for s in scans)
    x0, y0, yaw0 = path[0]
    c, s = math.cos(yaw0), math.sin(yaw0)
    dx, dy = path[:, 0] - x0, path[:, 1] - y0
    truth = np.column_stack((c * dx + s * dy, -s * dx + c * dy, path[:, 2] - yaw0))  # in the first scan's frame
    error = np.hypot(poses[:, 0] - truth[:, 0], poses[:, 1] - truth[:, 1])
    heading = np.degrees(np.abs(np.angle(np.exp(1j * (poses[:, 2] - truth[:, 2])))))
    assert np.median(error) < 0.03 and error.max() < 0.05 and heading.max() < 1.0  # 2.4 cm, 4.0 cm, 0.65 deg


def test_a_log_without_poses_builds_a_map_by_scan_matching(walk: tuple[np.ndarray, list[Scan]], tmp_path: Path,
                                                         capsys: pytest.CaptureFixture) -> None:
    _, scans = walk
    log = tmp_path / "walk.npz"
    record_npz(log, scans)
    out = tmp_path / "map.yaml"
    assert main(["map", "build", str(log), "--format", "npz", "--out", str(out), "--wall-angle", "45"]) == 0
    assert "scan matching" in capsys.readouterr().out
    built = load_world(out)  # the daemon's checks accept it
    assert len(built.walls) >= 8 and len(built.corners) >= 4 and built.survey_error_m < 0.03
    assert "scan matching" in out.read_text().splitlines()[0]


def test_a_walk_recorded_by_the_daemon_builds_a_map_and_replays_on_it(walk: tuple[np.ndarray, list[Scan]],
                                                                     tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture) -> None:
    """The walk recorded by the daemon's own flight recorder (record.enabled) with a second
    scanner beside it: `map build --format companion` takes the scanner named by --scan-topic,
    refuses to guess between two, and the walk then replays on its map, relocalized or from the
    map's start (the walk's first pose); it has no reference pose to start from."""
    _, scans = walk
    rec = recorder(tmp_path)
    rec.start()
    horizontal, vertical = rec.sensor("lidar_h"), rec.sensor("lidar_v")
    for scan in scans:
        horizontal(scan)
        vertical(replace(scan, sensor_id="lidar_v"))
    rec.close(timeout_s=10)
    log = next((tmp_path / "rec").glob(FILE_GLOB))
    out = tmp_path / "map.yaml"
    assert main(["map", "build", str(log), "--format", "companion", "--out", str(out)]) == 2
    assert "/sensors/lidar_h, /sensors/lidar_v" in capsys.readouterr().err and not out.exists()
    assert main(["map", "build", str(log), "--format", "companion", "--scan-topic", "/sensors/lidar_h",
                 "--out", str(out), "--wall-angle", "45"]) == 0
    built = load_world(out)
    assert len(built.walls) >= 8 and len(built.corners) >= 4 and built.survey_error_m < 0.03
    report = tmp_path / "r.json"
    for start in ("relocalize", "map"):  # the map's start: where the walk it was built from began
        assert main(["replay", str(log), "--format", "companion", "--scan-topic", "/sensors/lidar_h", "--map", str(out),
                     "--start", start, "--report", str(report)]) == 0
        result = json.loads(report.read_text())
        assert result["scans"] == len(scans) and result["lost_fraction"] < 0.1 and result["position_median_m"] is None
    assert main(["replay", str(log), "--format", "companion", "--scan-topic", "/sensors/lidar_h", "--map", str(out)]) == 2
    assert "use --start map" in capsys.readouterr().err  # no reference pose to start from


@pytest.fixture(scope="module")
def corridor_walk(tmp_path_factory: pytest.TempPathFactory) -> tuple[np.ndarray, BuiltMap, Path]:
    """The URG-04LX recording placed by scan matching alone (what `map build` does with it, about
    half a minute): its poses, the map built from them and that map's file."""
    if not CORRIDOR.exists():
        pytest.skip(f"recording not found at {CORRIDOR}")
    _, ranges, _ = read_breezyslam(CORRIDOR)
    angles = breezyslam_angles()
    scans = [(np.column_stack((r * np.cos(angles), r * np.sin(angles))), breezyslam_valid(r)) for r in ranges]
    poses = scan_poses(scans)
    built = build_map(((p, v, tuple(pose)) for (p, v), pose in zip(scans, poses)), MapBuildParams(wall_angle_deg=90))
    path = tmp_path_factory.mktemp("corridor") / "exp2.yaml"
    write_world(built, path, CORRIDOR.name, (0.0, 0.0, 0.0), MATCHED_POSES)  # the first scan's frame
    return poses, built, path


def test_the_real_corridor_walk_turns_as_its_wheel_odometry_says(corridor_walk: tuple[np.ndarray, BuiltMap, Path]) -> None:
    """The URG-04LX recording (641 scans, 63 s, 1200 deg of gross turning) placed by scan matching
    alone: over the run it turns within 5 deg of the calibrated wheel odometry (-86.3 deg), and
    the map built from those poses has straight walls at multiples of 90 deg."""
    poses, built, _ = corridor_walk
    stamps, _, ticks = read_breezyslam(CORRIDOR)
    odometry = odometry_heading(stamps, ticks, CALIBRATED_SCALE)
    turned = np.unwrap(poses[:, 2])[-1]
    assert abs(math.degrees(turned - odometry[-1])) < 5.0
    assert len(built.walls) >= 10 and built.survey_error_m < 0.08


def test_the_real_corridor_walk_replays_on_its_map_with_its_wheel_odometry(
        corridor_walk: tuple[np.ndarray, BuiltMap, Path], tmp_path: Path) -> None:
    """Replayed from the map's start, the walk's motion between scans is its wheel odometry
    (BreezySLAM's rover, ``auto`` -> ``log``): the localizer follows the walk through its rooms
    and is lost where it sees no wall it can place (figures in the README: 57 % lost, against
    95 % without the odometry). The log has no reference: nothing is scored against one."""
    _, _, world = corridor_walk
    report_path = tmp_path / "r.json"
    lost = {}
    for odometry in ("auto", "none"):
        assert main(["replay", str(CORRIDOR), "--format", "breezyslam", "--map", str(world), "--start", "map",
                     "--odometry", odometry, "--report", str(report_path)]) == 0
        report = json.loads(report_path.read_text())
        assert report["odometry"]["mode"] == ("log" if odometry == "auto" else "none")
        assert report["position_median_m"] is None and report["wrong_resets"] is None
        lost[odometry] = report["lost_fraction"]
    assert lost["auto"] < 0.65 and lost["none"] > 0.9
