"""ArduPilot SITL runs put the origin at the take-off point (sitl/frame_shift.py): every position of
the world, map, mission and config moves with it, and nothing moves on the ground."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from companion.config import load_config
from companion.frames import geodetic_from_ned, ned_from_geodetic
from companion.mission.steps import load_mission
from sitl.frame_shift import shift_mission, shift_world
from sitl.harness import write_run_config
from companion.world import load_world
from tests.conftest import REPO

ARENA = REPO / "config" / "worlds" / "arena.yaml"
PATROL = REPO / "config" / "missions" / "patrol.yaml"


def write(tmp_path: Path, name: str, doc: dict) -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(doc))
    return path


def test_the_walkers_of_a_world_move_with_it(tmp_path: Path) -> None:
    as_built = ARENA.with_name("arena-as-built.yaml")
    before = load_world(as_built)
    after = load_world(write(tmp_path, "w.yaml", shift_world(yaml.safe_load(as_built.read_text()), (-1.0, -2.0))))
    assert len(after.walkers) == len(before.walkers) == 2
    for a, b in zip(after.walkers, before.walkers):
        np.testing.assert_allclose([a.start, a.end], np.array([b.start, b.end]) + (-1.0, -2.0))
        assert (a.speed_mps, a.radius_m, a.height_m) == (b.speed_mps, b.radius_m, b.height_m)


def test_every_position_of_a_world_moves_and_nothing_else(tmp_path: Path) -> None:
    before = load_world(ARENA)
    after = load_world(write(tmp_path, "w.yaml", shift_world(yaml.safe_load(ARENA.read_text()), (-1.0, -2.0))))
    d = np.array([-1.0, -2.0])
    np.testing.assert_allclose(after.segments(), before.segments() + np.tile(d, 2))
    np.testing.assert_allclose(after.corner_array(), before.corner_array() + d)
    assert after.start == (before.start[0] - 1.0, before.start[1] - 2.0, before.start[2])
    np.testing.assert_allclose([after.bounds.min, after.bounds.max], np.array([before.bounds.min, before.bounds.max]) + d)
    for a, b in zip(after.openings, before.openings):
        np.testing.assert_allclose(a.center, np.array(b.center) + d)
        assert (a.width_m, a.bottom_m, a.top_m) == (b.width_m, b.bottom_m, b.top_m)
    for a, b in zip(after.obstacles, before.obstacles):
        np.testing.assert_allclose([a.min, a.max], np.array([b.min, b.max]) + d)
    for a, b in zip(after.floor_markers, before.floor_markers):
        np.testing.assert_allclose(a.position, np.array(b.position) + d)
        assert a.yaw_deg == b.yaw_deg


def test_mission_waypoints_move_horizontally_only(tmp_path: Path) -> None:
    before = load_mission(PATROL)
    after = load_mission(write(tmp_path, "m.yaml", shift_mission(yaml.safe_load(PATROL.read_text()), (-1.0, -1.0))))
    old = [w.position for s in before.steps if s.fly for w in s.fly.waypoints]
    new = [w.position for s in after.steps if s.fly for w in s.fly.waypoints]
    np.testing.assert_allclose(np.array(new), np.array(old) - [1.0, 1.0, 0.0])
    assert [s.kind for s in after.steps] == [s.kind for s in before.steps]


def test_the_run_config_puts_the_origin_under_the_take_off_point_and_the_walls_stay_put(tmp_path: Path) -> None:
    cfg = load_config(REPO / "config" / "sitl.yaml")
    run = load_config(write_run_config(cfg, "patrol", tmp_path, "tcp:127.0.0.1:1", origin_at_takeoff=True))
    old_origin = (cfg.origin.lat, cfg.origin.lon, cfg.origin.alt)
    new_origin = (run.origin.lat, run.origin.lon, run.origin.alt)
    np.testing.assert_allclose(ned_from_geodetic(*new_origin, old_origin), [1.0, 1.0, 0.0], atol=1e-6)
    world = load_world(run.resolve(run.sitl.world))
    assert world.start[:2] == (0.0, 0.0)
    assert run.resolve(run.pipelines.enabled["lidar"].map) == run.resolve(run.sitl.world)
    # the corner at (5, 5) of the arena is at the same place on Earth in both frames
    corner = geodetic_from_ned(np.array([5.0, 5.0, 0.0]), old_origin)
    np.testing.assert_allclose(ned_from_geodetic(*corner, new_origin), [4.0, 4.0, 0.0], atol=1e-6)
    assert any(np.allclose(c, [4.0, 4.0]) for c in world.corner_array())
    assert load_mission(run.resolve(run.mission.file)).steps[4].fly.waypoints[0].position == (1.5, 1.5, -1.0)
