"""Lidar models, mounts, the simulated backend and the replay backend (drivers/lidar_*.py, drivers/mount.py).

The real-data tests read ../shared/data/real/urg04lx-corridor-exp2.dat (outside the repository,
see its README) and are skipped when it is absent.
"""

from __future__ import annotations

import asyncio
import gzip
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from companion.config import MountConfig
from companion.frames import planar_rotation, quat_from_euler
from companion.health import Health, State
from companion.schema import SchemaError, load_text
from drivers.base import Backend, EndOfData, SensorDriver
from drivers.checks import sensor_driver
from drivers.lidar_models import MODELS, URG_04LX, UTM_30LX
from drivers.lidar_replay import (MINES_ROVER, ReplayLidar, ReplayLidarSettings, breezyslam_angles, carmen_valid,
                                  parse_carmen_line, read_breezyslam, read_carmen, record_npz, wheel_odometry)
from sitl.lidar_sim import SimLidarSettings, SimulatedLidar
from drivers.mount import Mount
from companion.messages import Scan
from companion.world import World, load_world
from tests.conftest import REPO

REAL_FILE = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "urg04lx-corridor-exp2.dat"
needs_real_file = pytest.mark.skipif(not REAL_FILE.exists(), reason=f"real URG-04LX recording not found at {REAL_FILE}")
CARMEN_DIR = REAL_FILE.parent / "carmen"
CARMEN_LOGS = {"intel": CARMEN_DIR / "intel-corrected.log.gz", "aces": CARMEN_DIR / "aces-corrected.log.gz"}


@dataclass(frozen=True)
class Pose:
    position_ned: np.ndarray
    quat: np.ndarray


class FakeTruth:
    """TruthSource-like: a fixed pose, known from daemon time ``available_from`` on."""

    def __init__(self, position: tuple[float, float, float], yaw_deg: float = 0.0,
                 available_from: float = -math.inf) -> None:
        self.pose = Pose(np.array(position, dtype=float), quat_from_euler(0.0, 0.0, math.radians(yaw_deg)))
        self.available_from = available_from

    def at(self, t: float) -> Pose | None:
        return self.pose if t >= self.available_from else None


@pytest.fixture(scope="module")
def arena() -> World:
    return load_world(REPO / "config" / "worlds" / "arena.yaml")


def make_sim(world: World, *, model: str = "UTM-30LX", rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0),
             truth: FakeTruth | None = None, **settings: object) -> SimulatedLidar:
    mount = Mount.from_config(MountConfig(rpy_deg=rpy_deg))
    return SimulatedLidar("lidar", SimLidarSettings(model=model, **settings), mount, world,
                          truth or FakeTruth((2.0, 1.0, -1.0)))


def beam_at(model_angles: np.ndarray, degrees: float) -> int:
    """Index of the beam closest to ``degrees`` (sensor frame, positive to the right)."""
    return int(np.argmin(np.abs(model_angles - math.radians(degrees))))


def render(sim: SimulatedLidar, position: tuple[float, float, float], yaw_deg: float = 0.0) -> Scan:
    return sim.render(0.0, np.array(position), quat_from_euler(0.0, 0.0, math.radians(yaw_deg)))


# -- models and mounts ------------------------------------------------------------------------


def test_models_follow_scip() -> None:
    assert (UTM_30LX.beams, URG_04LX.beams) == (1081, 682)
    utm = UTM_30LX.angles_rad()
    assert utm[540] == 0.0  # step AFRT is the front
    assert (utm[0], utm[-1]) == pytest.approx((math.radians(135), math.radians(-135)))  # first step on the right
    assert np.diff(utm) == pytest.approx(-math.radians(0.25))  # step order runs right to left
    urg = URG_04LX.angles_rad()
    assert urg[340] == 0.0 and math.degrees(urg[0] - urg[-1]) == pytest.approx(681 * 360 / 1024)
    assert UTM_30LX.sweep_s == pytest.approx(0.025 * 1080 / 1440)
    assert MODELS["URG-04LX"] is URG_04LX and SimLidarSettings(model="URG-04LX").lidar_model is URG_04LX
    np.testing.assert_allclose(URG_04LX.accuracy_bound_m(np.array([0.5, 3.0])), [0.01, 0.03])
    np.testing.assert_allclose(UTM_30LX.range_sigma_m(np.array([5.0, 20.0])), [0.01, 0.05 / 3])


def test_mount_rotations() -> None:
    yawed = Mount.from_config(MountConfig(position_m=(0.1, 0.0, -0.2), rpy_deg=(0, 0, 90)))
    np.testing.assert_allclose(yawed.to_body(np.array([[1.0, 0.0]])), [[0.1, 1.0, -0.2]], atol=1e-12)  # front -> right
    vertical = Mount.from_config(MountConfig(rpy_deg=(90, 0, 0)))
    np.testing.assert_allclose(vertical.to_body(np.array([[1.0, 0.0], [0.0, 1.0]])), [[1, 0, 0], [0, 0, 1]], atol=1e-12)
    # Vehicle at (1, 2, -3) facing east: body front = east, so the yawed sensor's front = south.
    world = yawed.to_world(np.array([[2.0, 0.0, 0.0]]), np.array([1.0, 2.0, -3.0]), quat_from_euler(0, 0, math.pi / 2))
    np.testing.assert_allclose(world, [[1.0 - 2.0, 2.0 + 0.1, -3.2]], atol=1e-12)


# -- simulated backend: geometry ----------------------------------------------------------------


def test_sim_scan_sees_the_room(arena: World) -> None:
    sim = make_sim(arena, noise_scale=0.0)
    scan = render(sim, (2.0, 1.0, -1.0))  # SW room: walls 2 m behind, 3 m ahead, 1 m left, 4 m right
    angles = scan.angles_rad
    assert len(angles) == len(scan.ranges_m) == 1081 and scan.valid.all()
    assert scan.ranges_m[beam_at(angles, 0)] == pytest.approx(3.0, abs=1e-5)  # north, wall x = 5
    assert scan.ranges_m[beam_at(angles, 90)] == pytest.approx(4.0, abs=1e-5)  # right = east, wall y = 5
    assert scan.ranges_m[beam_at(angles, -90)] == pytest.approx(1.0, abs=1e-5)  # left = west, wall y = 0
    # Facing east, the scanner's front sees the east wall.
    assert render(sim, (2.0, 1.0, -1.0), yaw_deg=90).ranges_m[beam_at(angles, 0)] == pytest.approx(4.0, abs=1e-5)


def test_mount_yawed_90_sees_the_right_wall_ahead(arena: World) -> None:
    sim = make_sim(arena, rpy_deg=(0, 0, 90), noise_scale=0.0)
    scan = render(sim, (2.0, 1.0, -1.0))
    assert scan.ranges_m[beam_at(scan.angles_rad, 0)] == pytest.approx(4.0, abs=1e-5)  # the body's right wall
    assert scan.ranges_m[beam_at(scan.angles_rad, -90)] == pytest.approx(3.0, abs=1e-5)  # the body's front wall


def test_vertical_scanner_sees_floor_and_table(arena: World) -> None:
    sim = make_sim(arena, model="URG-04LX", rpy_deg=(90, 0, 0))
    down = beam_at(sim.model.angles_rad(), 90)  # exactly +90 deg: step 128
    assert sim.model.angles_rad()[down] == pytest.approx(math.pi / 2)
    beside = render(sim, (6.5, 1.6, -1.0))
    over = render(sim, (7.4, 1.6, -1.0))
    assert beside.ranges_m[down] == pytest.approx(1.0, abs=0.01)  # the floor, +/-10 mm up to 1 m
    assert over.ranges_m[down] == pytest.approx(0.25, abs=0.01)  # the 0.75 m table top
    assert beside.ranges_m[beam_at(beside.angles_rad, -90)] == pytest.approx(2.0, abs=0.02)  # ceiling at 3 m


def test_noise_within_spec_and_seeded(arena: World) -> None:
    exact = render(make_sim(arena, noise_scale=0.0), (2.5, 2.5, -1.0))
    noisy = [render(make_sim(arena, seed=7), (2.5, 2.5, -1.0)), render(make_sim(arena, seed=7), (2.5, 2.5, -1.0))]
    np.testing.assert_array_equal(noisy[0].ranges_m, noisy[1].ranges_m)  # same seed, same scan
    error = noisy[0].ranges_m - exact.ranges_m
    assert np.abs(error).max() <= 0.030 + 1e-9  # UTM-30LX: +/-30 mm up to 10 m (all ranges here are)
    assert 0.008 < error.std() < 0.012  # sigma = bound / 3 = 10 mm
    other = render(make_sim(arena, seed=8), (2.5, 2.5, -1.0))
    assert not np.array_equal(other.ranges_m, noisy[0].ranges_m)


def test_beyond_max_range_and_dropouts_are_invalid(arena: World) -> None:
    # URG-04LX (5.6 m): from (2.5, 2.5) the beam north flies through the door to x = 10, 7.5 m away.
    scan = render(make_sim(arena, model="URG-04LX"), (2.5, 2.5, -1.0))
    ahead = beam_at(scan.angles_rad, 0)
    assert not scan.valid[ahead] and scan.ranges_m[ahead] == 0.0
    assert scan.valid[beam_at(scan.angles_rad, 90)]  # 2.5 m to the wall y = 5
    dropped = render(make_sim(arena, noise_scale=0.0, dropout_prob=0.3), (2.0, 1.0, -1.0))
    assert 0.25 < 1 - dropped.valid.mean() < 0.35
    assert (dropped.ranges_m[~dropped.valid] == 0).all()


def test_settings_are_schema_dataclasses() -> None:
    """The config loads the settings dicts through companion.schema (the backend registry, companion/plugins.py)."""
    sim = load_text(yaml.safe_dump({"model": "URG-04LX", "rate_hz": 20, "seed": 4}), SimLidarSettings)
    assert sim == SimLidarSettings(model="URG-04LX", rate_hz=20.0, seed=4)
    for bad in ({"port": "/dev/ttyACM0"}, {"model": "LMS-111"}, {"dropout_prob": 1.5}, {"seed": 1.5},
                {"noise_scale": -1}, {"rate_hz": 0}):
        with pytest.raises(SchemaError):
            load_text(yaml.safe_dump(bad), SimLidarSettings)
    assert load_text("file: a.dat\nformat: breezyslam\n", ReplayLidarSettings).rate_scale == 1.0
    for bad in ({}, {"file": "x", "format": "csv"}, {"file": "x", "rate_scale": 0}, {"file": "x", "loop": "yes"}):
        with pytest.raises(SchemaError):
            load_text(yaml.safe_dump(bad), ReplayLidarSettings)


# -- simulated backend: timing ------------------------------------------------------------------


def test_sim_paces_scans_and_waits_for_truth(arena: World) -> None:
    async def run() -> tuple[list[Scan], list[float], float]:
        loop = asyncio.get_running_loop()
        truth = FakeTruth((2.0, 1.0, -1.0), available_from=loop.time() + 0.12)
        sim = make_sim(arena, truth=truth, rate_hz=20)
        await sim.open()
        scans, delivered = [], []
        for _ in range(4):
            scans.append(await sim.read())
            delivered.append(loop.time())
        await sim.close()
        return scans, delivered, truth.available_from

    scans, delivered, available_from = asyncio.run(run())
    sweep = UTM_30LX.sweep_s
    assert scans[0].t_capture >= available_from and scans[0].sequence >= 3  # no scan invented before truth
    assert [s.sequence for s in scans] == list(range(scans[0].sequence, scans[0].sequence + 4))
    assert np.diff([s.t_capture for s in scans]) == pytest.approx(0.05)
    assert all(d >= s.t_capture + sweep - 1e-6 for s, d in zip(scans, delivered))  # delivered after the sweep
    assert all(s.sweep_s == 0.0 and len(s.ranges_m) == 1081 for s in scans)


# -- replay backend -----------------------------------------------------------------------------


@needs_real_file
def test_read_breezyslam_real_file() -> None:
    stamps, ranges, odometry = read_breezyslam(REAL_FILE)
    assert stamps.shape == (641,) and ranges.shape == (641, 682) and odometry.shape == (641, 2)
    assert (np.diff(stamps) > 0).all() and np.median(np.diff(stamps)) == pytest.approx(0.1, abs=0.005)
    assert ranges.min() == 0.0 and ranges.max() <= URG_04LX.max_range_m
    assert odometry[-1, 0] > odometry[0, 0] and odometry[-1, 1] > odometry[0, 1]  # both wheels drove forward


@needs_real_file
def test_breezyslam_sweep_direction_matches_odometry() -> None:
    """Scans a few apart, placed with the wheel odometry, overlap with the driver's beam angles and
    not with the mirrored ones (see drivers/lidar_replay.py)."""
    stamps, ranges, ticks = read_breezyslam(REAL_FILE)
    poses = wheel_odometry(ticks)  # the scanner's, FRD

    def points(k: int, angles: np.ndarray) -> np.ndarray:
        ok = (ranges[k] > 0.02) & (ranges[k] < 4.0)
        r, a = ranges[k][ok], angles[ok]
        x, y, yaw = poses[k]
        return np.array([x, y]) + np.column_stack((r * np.cos(a), r * np.sin(a))) @ planar_rotation(yaw).T

    def misfit(k: int, angles: np.ndarray) -> float:
        p, q = points(k, angles), points(k + 3, angles)
        return float(np.median(np.sqrt(((q[:, None] - p[None]) ** 2).sum(-1)).min(axis=1)))

    driver = breezyslam_angles()
    turning = [k for k in range(0, len(stamps) - 3, 7) if abs(poses[k + 3, 2] - poses[k, 2]) > math.radians(10)]
    wins = [misfit(k, driver) < misfit(k, -driver) for k in turning]
    assert len(turning) >= 15 and sum(wins) >= 0.8 * len(wins)


def test_wheel_odometry_places_the_scanner_ahead_of_the_axle_and_turns_clockwise_when_the_left_wheel_leads() -> None:
    """BreezySLAM's model of the rover (drivers/lidar_replay.py, MINES_ROVER): equal ticks drive
    straight ahead by the wheel arc; the left wheel rolling further turns right (FRD yaw grows) by
    the arc difference over the axle, and the scanner, 145 mm ahead, swings with it."""
    per_m = MINES_ROVER.ticks_per_wheel_turn / (2 * math.pi * MINES_ROVER.wheel_radius_m)  # ticks per metre of arc
    arc = MINES_ROVER.half_axle_m * math.pi / 2  # each wheel's arc, opposite ways, for a quarter turn in place
    ticks = np.array([[0.0, 0.0], [per_m, per_m], [per_m * (1 + arc), per_m * (1 - arc)]])
    poses = wheel_odometry(ticks)
    assert poses[0] == pytest.approx([0.145, 0.0, 0.0])
    assert poses[1] == pytest.approx([1.145, 0.0, 0.0])  # one metre straight ahead
    assert poses[2] == pytest.approx([1.0, 0.145, math.pi / 2])  # turned right in place: the scanner east of the axle


def _carmen_world_points(scan: object, log_max: float) -> np.ndarray:
    """A CARMEN scan's returns in the map (NED) frame, placed with the log's reference pose."""
    ok = carmen_valid(scan, log_max) & (scan.ranges_m < 15.0)
    r, a = scan.ranges_m[ok], scan.angles_rad[ok]
    x, y, yaw = scan.pose_ned
    c, s_ = math.cos(yaw), math.sin(yaw)
    q = np.column_stack((r * np.cos(a), r * np.sin(a)))  # FRD: x forward, y right
    return np.array([x, y]) + q @ np.array([[c, -s_], [s_, c]]).T


@pytest.mark.parametrize("log", sorted(CARMEN_LOGS))
def test_carmen_scans_placed_with_their_reference_poses_overlap(log: str) -> None:
    """The mirrored frames (beam angles and poses) are right: consecutive scans of the real log,
    each placed with its own reference pose, land on the same walls; the unmirrored beam angles
    with the same poses do not."""
    path = CARMEN_LOGS[log]
    if not path.exists():
        pytest.skip(f"CARMEN log not found at {path}")
    scans = read_carmen(path)
    assert len(scans) == {"intel": 910, "aces": 440}[log]
    assert all(s.angles_rad.size == 180 and s.laser == "front" for s in scans)
    assert scans[0].angles_rad[0] == pytest.approx(math.pi / 2)  # the first beam looks right
    log_max = max(float(s.ranges_m.max()) for s in scans)

    def misfit(a: object, b: object) -> float:
        p, q = _carmen_world_points(a, log_max), _carmen_world_points(b, log_max)
        return float(np.median(np.sqrt(((q[:, None] - p[None]) ** 2).sum(-1)).min(axis=1)))

    pairs = range(0, len(scans) - 1, max(1, len(scans) // 40))
    good = [misfit(scans[k], scans[k + 1]) for k in pairs]
    mirrored = [misfit(scans[k], replace(scans[k], angles_rad=-scans[k].angles_rad)) for k in pairs]
    assert np.median(good) < 0.05 and np.median(mirrored) > 4 * np.median(good)


def test_carmen_lines_are_parsed_and_malformed_ones_named() -> None:
    flaser = "FLASER 4 1.0 2.0 81.9 0 1.5 -2.0 0.5 1.25 -2.5 0.75 12.25 host 12.3"
    scan = parse_carmen_line(flaser)
    assert scan is not None and scan.laser == "front" and scan.t_s == 12.25
    np.testing.assert_allclose(scan.angles_rad, [math.pi / 2, math.pi / 4, 0.0, -math.pi / 4])
    assert scan.pose_ned == (1.5, 2.0, -0.5) and scan.odometry_ned == (1.25, 2.5, -0.75)
    np.testing.assert_array_equal(carmen_valid(scan, 81.9), [True, True, False, False])
    rear = parse_carmen_line(flaser.replace("FLASER", "RLASER"))
    np.testing.assert_allclose(np.exp(1j * rear.angles_rad),  # turned by 180 deg (+/- pi alike)
                               np.exp(1j * np.array([-math.pi / 2, -3 * math.pi / 4, math.pi, 3 * math.pi / 4])), atol=1e-12)
    robot = parse_carmen_line("ROBOTLASER1 0 -1.5708 3.1416 1.5708 30.0 0.01 0 3 1.0 30.0 2.0 0 "
                              "0.1 0 0 1.0 2.0 0.25 0 0 0 0 0 7.5 host 7.6")
    assert robot is not None and robot.max_range_m == 30.0 and robot.pose_ned == (1.0, -2.0, -0.25)
    assert robot.odometry_ned is None
    np.testing.assert_array_equal(carmen_valid(robot, 99.0), [True, False, True])
    assert parse_carmen_line("ODOM 0 0 0 0 0 0 1.0 host 1.0") is None
    with pytest.raises(ValueError, match="FLASER"):
        parse_carmen_line("FLASER 4 1.0 2.0 0 1.5 -2.0 0.5 1.5 -2.0 0.5 12.25 host 12.3")  # a reading short


def test_carmen_replay_through_the_driver_frontend(tmp_path: Path) -> None:
    lines = [f"FLASER 3 1.0 {2.0 + k} 50.0 {0.1 * k} 0 0 0 0 0 {10.0 + 0.05 * k} host 0" for k in range(4)]
    lines.insert(2, "FLASER 3 1.0 nan 2.0 0 0 0 0 0 0 10.07 host 0")
    log = tmp_path / "walk.log.gz"
    log.write_bytes(gzip.compress(("\n".join(["PARAM x 1 host 0", *lines]) + "\n").encode()))
    with pytest.raises(OSError, match=r"walk.log.gz:4: .*not a finite number"):  # refused, the line named
        asyncio.run(ReplayLidar("h", ReplayLidarSettings(file=str(log), format="carmen")).open())
    log.write_bytes(gzip.compress(("\n".join(lines[:2] + lines[3:]) + "\n").encode()))

    async def run() -> list[Scan]:
        backend = ReplayLidar("h", ReplayLidarSettings(file=str(log), format="carmen", rate_scale=50.0))
        await backend.open()
        scans = []
        with pytest.raises(EndOfData):
            while True:
                scans.append(await backend.read())
        return scans

    scans = asyncio.run(run())
    assert len(scans) == 4 and [s.sequence for s in scans] == [0, 1, 2, 3]
    np.testing.assert_allclose(np.diff([s.t_capture for s in scans]), 0.05 / 50.0, atol=1e-6)
    assert [s.valid.tolist() for s in scans[:1]] == [[True, True, False]]  # 50 m: the log's maximum


def breezyslam_excerpt(tmp_path: Path, lines: int, corrupt_at: int | None = None) -> Path:
    text = REAL_FILE.read_text().splitlines()[:lines]
    if corrupt_at is not None:
        text.insert(corrupt_at, " ".join(text[corrupt_at].split()[:300]))  # a truncated line
    path = tmp_path / "excerpt.dat"
    path.write_text("\n".join(text) + "\n")
    return path


@needs_real_file
def test_replay_through_the_driver_frontend(tmp_path: Path) -> None:
    path = breezyslam_excerpt(tmp_path, 10, corrupt_at=4)
    stamps, ranges, _ = read_breezyslam(REAL_FILE)

    async def run() -> tuple[SensorDriver, list[Scan], list[float], float, Health]:
        loop = asyncio.get_running_loop()
        health = Health(loop.time)
        scans: list[Scan] = []
        delivered: list[float] = []
        backend = ReplayLidar("vertical", ReplayLidarSettings(file=str(path), format="breezyslam", rate_scale=20.0))
        driver = sensor_driver("lidar", "vertical", backend, health)
        driver.subscribe(lambda s: (scans.append(s), delivered.append(loop.time())))
        started = loop.time()
        task = asyncio.create_task(driver.run())
        while (h := health.get("sensor:vertical")) is None or h.state != State.LOST:
            await asyncio.sleep(0.01)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        return driver, scans, delivered, started, health

    driver, scans, delivered, started, health = asyncio.run(run())
    assert driver.stats.corrupt_frames == 1 and driver.stats.messages == 10 and len(scans) == 10
    assert "line 5" in (driver.stats.last_error or "")
    assert health.get("sensor:vertical").reason == "replay finished"
    offsets = np.array([s.t_capture for s in scans]) - scans[0].t_capture
    np.testing.assert_allclose(offsets, (stamps[:10] - stamps[0]) / 20.0, atol=1e-9)
    assert scans[0].t_capture == pytest.approx(started, abs=0.05)
    assert all(d >= s.t_capture + s.sweep_s - 1e-6 for s, d in zip(scans, delivered))
    assert scans[0].sweep_s == pytest.approx(URG_04LX.sweep_s / 20.0)
    assert [s.sequence for s in scans] == [0, 1, 2, 3, 5, 6, 7, 8, 9, 10]  # the corrupt line is a gap
    expected_valid = (ranges[:10] >= 0.02) & (ranges[:10] <= 5.6)
    np.testing.assert_array_equal(np.stack([s.valid for s in scans]), expected_valid)
    np.testing.assert_allclose(np.stack([s.ranges_m for s in scans]), np.where(expected_valid, ranges[:10], 0.0))


@needs_real_file
def test_replay_end_and_loop(tmp_path: Path) -> None:
    path = breezyslam_excerpt(tmp_path, 3)

    async def run(loop_replay: bool) -> list[Scan]:
        backend = ReplayLidar("v", ReplayLidarSettings(file=str(path), format="breezyslam", rate_scale=50.0,
                                                       loop=loop_replay))
        await backend.open()
        scans = [await backend.read() for _ in range(3 if not loop_replay else 7)]
        if not loop_replay:
            with pytest.raises(EndOfData):
                await backend.read()
        await backend.close()
        return scans

    assert len(asyncio.run(run(False))) == 3
    looped = asyncio.run(run(True))
    assert [s.sequence for s in looped] == list(range(7))
    assert (np.diff([s.t_capture for s in looped]) > 0).all()
    np.testing.assert_array_equal(looped[3].ranges_m, looped[0].ranges_m)


def test_npz_record_and_replay(tmp_path: Path, arena: World) -> None:
    sim = make_sim(arena, model="URG-04LX", seed=3)
    recorded = [sim.render(10.0 + 0.1 * k, np.array([2.0, 1.0 + 0.1 * k, -1.0]), quat_from_euler(0, 0, 0), k)
                for k in range(4)]
    path = tmp_path / "scans.npz"
    record_npz(path, recorded)

    async def run() -> list[Scan]:
        backend = ReplayLidar("lidar", ReplayLidarSettings(file=path.name, format="npz", rate_scale=10.0),
                              base_dir=tmp_path)
        await backend.open()
        scans = [await backend.read() for _ in range(4)]
        with pytest.raises(EndOfData):
            await backend.read()
        return scans

    replayed = asyncio.run(run())
    for a, b in zip(recorded, replayed):
        np.testing.assert_array_equal(a.ranges_m, b.ranges_m)
        np.testing.assert_array_equal(a.valid, b.valid)
        np.testing.assert_array_equal(a.angles_rad, b.angles_rad)
    np.testing.assert_allclose(np.diff([s.t_capture for s in replayed]), 0.01, atol=1e-9)
    with pytest.raises(OSError):
        asyncio.run(ReplayLidar("x", ReplayLidarSettings(file=str(tmp_path / "missing.npz"))).open())
    np.savez(tmp_path / "bad.npz", t_capture=np.zeros(2), angles_rad=np.zeros(5), ranges_m=np.zeros((2, 4)),
             valid=np.zeros((2, 4), bool))
    with pytest.raises(OSError, match="inconsistent"):
        asyncio.run(ReplayLidar("x", ReplayLidarSettings(file=str(tmp_path / "bad.npz"))).open())


class _Scripted(Backend[Scan]):
    """A backend that plays the given scans, then ends."""

    description = "scripted"

    def __init__(self, scans: list[Scan]) -> None:
        self.scans = list(scans)

    async def open(self) -> None:
        pass

    async def read(self) -> Scan:
        if not self.scans:
            raise EndOfData
        return self.scans.pop(0)

    async def close(self) -> None:
        pass


def _scan(t: float, ranges: list[float]) -> Scan:
    n = len(ranges)
    return Scan("s", t, np.linspace(-1.0, 1.0, n), np.array(ranges, dtype=float), np.ones(n, dtype=bool))


def test_nonfinite_and_backwards_scans_are_dropped_and_counted_before_any_pipeline() -> None:
    scans = [_scan(1.0, [1.0, 2.0]), _scan(1.1, [1.0, math.nan]), _scan(math.inf, [1.0, 2.0]),
             _scan(1.1, [1.0, 2.0]), _scan(1.05, [1.0, 2.0]), _scan(1.2, [1.0, math.inf])]
    got: list[Scan] = []
    driver = sensor_driver("lidar", "s", _Scripted(scans), Health(lambda: 0.0))
    driver.subscribe(got.append)

    async def run() -> None:
        task = asyncio.ensure_future(driver.run())
        while driver.health.get("sensor:s") is None or driver.health.get("sensor:s").reason != "replay finished":
            await asyncio.sleep(0.01)
        task.cancel()

    asyncio.run(run())
    assert [s.t_capture for s in got] == [1.0, 1.1]
    assert driver.stats.rejected == {"non-finite range or angle": 2, "non-finite capture time": 1,
                                           "capture time not after the previous one's": 1}
