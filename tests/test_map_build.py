"""`companion map build`: a lidar map from scans at known poses, on the arena and on real logs."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from companion.cli import main
from companion.nav.bench_stages import DEFAULT_WORLD, make_mount, synthetic_scan
from companion.nav.map_build import MapBuildParams, build_map
from companion.nav.planar import PlanarLocalizer
from companion.world import load_world
from drivers.lidar_models import UTM_30LX
from drivers.lidar_replay import carmen_valid, read_carmen
from sitl.raycast import WorldGeometry
from tests.scan_synthesis import walls_world
from companion.nav.bench_robustness import arena_path

CARMEN_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "carmen"


def _arena_scans(geometry: WorldGeometry, turn_rad: float = 0.0) -> list[tuple[np.ndarray, np.ndarray, tuple]]:
    """Scans along the arena path (turned by ``turn_rad`` about the origin), with their true poses."""
    rng = np.random.default_rng(30)
    c, s = math.cos(turn_rad), math.sin(turn_rad)
    scans = []
    for x, y, yaw in arena_path()[::4]:
        x, y = c * x - s * y, s * x + c * y
        scan = synthetic_scan(geometry, UTM_30LX, make_mount((0, 0, 0), (0, 0, 0)), np.array([x, y, -1.0]),
                              (0, 0, yaw + turn_rad), rng, 0.01)
        points = np.column_stack((scan.ranges_m * np.cos(scan.angles_rad), scan.ranges_m * np.sin(scan.angles_rad)))
        scans.append((points, scan.valid, (x, y, yaw + turn_rad)))
    return scans


def test_the_map_of_arena_scans_has_its_walls_and_corners() -> None:
    arena = load_world(DEFAULT_WORLD)
    built = build_map(_arena_scans(WorldGeometry.from_world(arena)), MapBuildParams(wall_angle_deg=45))
    assert abs(built.wall_offset_deg) < 0.05 and built.survey_error_m < 0.005
    true = arena.corner_array()
    found = [np.min(np.hypot(*(true - c).T)) for c in built.corners]
    assert len(found) >= 10 and max(found) < 0.01  # every corner built is a true one, to 1 cm
    walls = arena.segments_at(1.0)
    ends = np.vstack((built.walls[:, 0:2], built.walls[:, 2:4]))
    on_a_wall = [min(_to_segment(p, w) for w in walls) for p in ends]
    assert max(on_a_wall) < 0.02


def test_the_map_of_a_turned_building_has_its_wall_offset() -> None:
    arena = load_world(DEFAULT_WORLD)
    turn = math.radians(20.0)
    rot = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
    segments = arena.segments_at(1.0)
    turned = np.hstack((segments[:, :2] @ rot.T, segments[:, 2:] @ rot.T))
    geometry = WorldGeometry.from_world(walls_world([tuple(w) for w in turned], wall_angle_deg=45))
    built = build_map(_arena_scans(geometry, turn), MapBuildParams(wall_angle_deg=45))
    assert built.wall_offset_deg == pytest.approx(20.0, abs=0.05)


def test_the_map_measures_how_far_its_walls_run_from_the_wall_angle() -> None:
    """A building whose walls each run 0.5 deg off the nearest multiple of the wall angle (turned
    about their middles, alternately either way) is mapped at the exact directions, with a wall
    direction error of about 0.5 deg; the drawn arena's walls give nearly none."""
    arena = load_world(DEFAULT_WORLD)
    exact = build_map(_arena_scans(WorldGeometry.from_world(arena)), MapBuildParams(wall_angle_deg=45))
    assert exact.wall_direction_error_deg < 0.1
    segments = arena.segments_at(1.0)
    turned = []
    for k, (x0, y0, x1, y1) in enumerate(segments):
        mid, half = np.array([x0 + x1, y0 + y1]) / 2, np.array([x1 - x0, y1 - y0]) / 2
        a = math.radians(0.5 if k % 2 else -0.5)
        half = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]) @ half
        turned.append((*(mid - half), *(mid + half)))
    geometry = WorldGeometry.from_world(walls_world(turned, wall_angle_deg=45))
    built = build_map(_arena_scans(geometry), MapBuildParams(wall_angle_deg=45))
    assert built.wall_direction_error_deg == pytest.approx(0.5, abs=0.1)


def _to_segment(p: np.ndarray, wall: np.ndarray) -> float:
    a, b = wall[0:2], wall[2:4]
    u = np.clip((p - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
    return float(np.hypot(*(p - a - u * (b - a))))


@pytest.mark.parametrize("log", ["intel", "aces"])
def test_a_map_built_from_a_real_log_loads_and_locates_its_scans(log: str, tmp_path: Path) -> None:
    """The CARMEN log's own reference poses build the map; the daemon's world checks accept it;
    the localizer, each scan given its reference pose as the prediction, lands within a few
    centimetres of it on most scans (map and scans agree: a consistency check, not an
    independent accuracy figure)."""
    path = CARMEN_DIR / f"{log}-corrected.log.gz"
    if not path.exists():
        pytest.skip(f"CARMEN log not found at {path}")
    out = tmp_path / "map.yaml"
    assert main(["map", "build", str(path), "--format", "carmen", "--out", str(out)]) == 0
    world = load_world(out)
    assert len(world.walls) >= 80 and len(world.corners) >= 15 and world.survey_error_m < 0.1
    scans = read_carmen(path)
    log_max = max(float(s.ranges_m.max()) for s in scans)
    loc = PlanarLocalizer(world.corner_array(), world.wall_angle_deg, walls=world.segments(),
                          wall_offset_deg=world.wall_offset_deg)
    errors = []
    for s in scans:
        points = np.column_stack((s.ranges_m * np.cos(s.angles_rad), s.ranges_m * np.sin(s.angles_rad)))
        fix = loc.update(points, s.pose_ned, valid=carmen_valid(s, log_max))
        if fix is not None and fix.measured:
            errors.append(math.hypot(fix.x - s.pose_ned[0], fix.y - s.pose_ned[1]))
    assert len(errors) >= 0.7 * len(scans) and np.median(errors) < 0.06


def test_an_empty_log_is_refused_with_a_clear_error_and_nothing_written(tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture) -> None:
    log = tmp_path / "walk.dat"
    log.write_text("")
    assert main(["map", "build", str(log), "--format", "breezyslam", "--out", str(tmp_path / "m.yaml")]) == 2
    assert "walk.dat: no scan" in capsys.readouterr().err
    assert not (tmp_path / "m.yaml").exists()
