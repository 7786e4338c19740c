"""Heading tracking and planar localization on ray-cast scans of the default arena (1 cm noise)."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import tracemalloc

import numpy as np
import pytest

from companion.config import MountConfig
from companion.health import Health
from companion.nav.height import HeightParams
from companion.nav.lidar_pipeline import LidarPipeline, LidarPipelineConfig
from companion.nav.bench_robustness import (HEIGHT_M, MOUNT, arena_path, beam_dropout_run, localizer, scan_at,
                                           tilted_scan_run)
from companion.nav.bench_stages import DEFAULT_WORLD, run_stage_bench, tiled_map
from companion.nav.corners import find_corners
from companion.nav.heading import HeadingResult, track_heading, wall_mod
from companion.nav.lidar_pipeline import planar_params
from companion.nav.lines import LineSet, extract_lines
from companion.nav.edges import occluding_ends
from companion.nav.corner_hypotheses import pose_hypotheses
from companion.nav.corner_shape import map_corner_rays, shapes_agree
from companion.nav.planar import Mount2D, PlanarFix, PlanarLocalizer, PlanarParams, _with_yaw
from companion.nav.wall_hypotheses import MapWalls
from drivers.lidar_models import UTM_30LX
from companion.messages import Scan
from sitl.raycast import WorldGeometry
from companion.world import World, load_world
from tests.scan_synthesis import square_room, walls_world

A45 = math.radians(45)
UTM30LX_ANGLES = UTM_30LX.angles_rad()


@pytest.fixture(scope="module")
def arena() -> World:
    return load_world(DEFAULT_WORLD)


@pytest.fixture(scope="module")
def geometry(arena: World) -> WorldGeometry:
    return WorldGeometry.from_world(arena)


def yaw_error(a: float, b: float) -> float:
    return abs(math.remainder(a - b, 2 * math.pi))


def assert_finite(fix: PlanarFix) -> None:
    assert all(math.isfinite(v) for v in (fix.x, fix.y, fix.yaw))
    assert fix.covariance.shape == (3, 3) and np.all(np.isfinite(fix.covariance))
    assert np.all(np.linalg.eigvalsh(fix.covariance) > 0)


def levelled_lines(geometry: WorldGeometry, x: float, y: float, yaw: float, rng: np.random.Generator) -> LineSet:
    loc = PlanarLocalizer(np.zeros((0, 2)), 45, mount=MOUNT)
    points, valid, ranges = loc.level_points(scan_at(geometry, x, y, yaw, rng))
    return extract_lines(points, valid, ranges=ranges)


# -- heading ----------------------------------------------------------------------------------

def test_paper_modulo_operator() -> None:
    assert np.allclose(wall_mod(np.radians([10, 30, 22.5, -22.5, 44, 90]), A45),
                       np.radians([10, -15, 22.5, 22.5, -1, 0]))


def test_heading_tracks_a_slowly_rotating_vehicle(geometry: WorldGeometry) -> None:
    rng = np.random.default_rng(1)
    yaw_true = np.radians(10.0) + np.radians(2.5) * np.arange(100)  # 250 deg in 100 frames
    yaw = yaw_true[0]
    errors = []
    for truth in yaw_true:
        result = track_heading(levelled_lines(geometry, 7.0, 7.0, truth, rng), yaw, A45)
        assert result.status == "ok", result.reason
        yaw = result.yaw
        errors.append(yaw_error(yaw, truth))
    assert math.degrees(math.sqrt(np.mean(np.square(errors)))) < 0.2


def test_rotation_beyond_half_the_wall_angle_is_reported(geometry: WorldGeometry) -> None:
    rng = np.random.default_rng(2)
    for turn_deg in (15.0, 30.0):  # 30 deg > A/2 aliases to -15 deg: both are flagged
        result = track_heading(levelled_lines(geometry, 2.0, 2.0, math.radians(20 + turn_deg), rng),
                               math.radians(20), A45)
        assert result.status == "near_limit" and "limit" in result.reason
        assert result.limit_rad == pytest.approx(A45 / 2)
    # The gyro's predicted change moves the prediction: the residual rotation is small.
    result = track_heading(levelled_lines(geometry, 2.0, 2.0, math.radians(50), rng), math.radians(20),
                           A45, predicted_delta=math.radians(28))
    assert result.status == "ok" and yaw_error(result.yaw, math.radians(50)) < math.radians(0.2)


def synthetic_lines(alpha_deg: list[float]) -> LineSet:
    """Lines with the given normal angles, 2 m long, 0.05 deg sigma (other fields plausible)."""
    k = len(alpha_deg)
    one = np.ones(k)
    return LineSet(np.radians(alpha_deg), one, np.zeros((k, 2)), np.zeros((k, 2)), np.zeros((k, 2)),
                   np.full(k, 100), 2 * one, 0.01 * one, np.radians(0.05) ** 2 * one, 1e-6 * one, one,
                   np.arange(k), np.arange(k))


def test_heading_mean_wraps_at_half_the_wall_angle() -> None:
    # Corrections of +22.4 and -22.4 deg (= +22.6) agree modulo 45: the mean is 22.5, not 0.
    result = track_heading(synthetic_lines([-22.4, 22.4 + 90]), 0.0, A45)
    assert abs(abs(math.degrees(result.correction)) - 22.5) < 1e-6 and result.lines_used == 2


def test_disagreeing_wall_directions_are_ambiguous_and_outliers_ignored() -> None:
    clutter = track_heading(synthetic_lines([0.0, 15.0, 30.0]), 0.0, A45)
    assert clutter.status == "ambiguous" and clutter.yaw == 0.0
    one_outlier = track_heading(synthetic_lines([1.0, 91.0, -179.0, 13.0]), 0.0, A45)
    assert one_outlier.status == "ok" and one_outlier.lines_used == 3
    assert math.degrees(one_outlier.correction) == pytest.approx(-1.0)
    assert track_heading(synthetic_lines([]), 0.3, A45).status == "no_lines"


def test_competing_wall_families_follow_the_prediction_not_the_heavier_clutter() -> None:
    """Five lines of clutter at 15 deg outweigh three walls of the building (at 0 and 90 deg): with
    the heading predicted at 0 (the gyro saw no turn) the building's family is the candidate, and
    without the consensus for it the heading is ambiguous, never flipped by 15 deg."""
    gyro = planar_params(LidarPipelineConfig(horizontal_sensor="h", vertical_sensor="v")).heading  # the pipeline's
    clutter_heavy = synthetic_lines([0.2, 90.2, -89.8, 15.0, 15.1, 105.0, -75.1, 15.2])
    result = track_heading(clutter_heavy, 0.0, A45, params=gyro)
    assert result.status == "ambiguous" and result.yaw == 0.0
    assert track_heading(clutter_heavy, 0.0, A45).measured  # no prior (no gyro): the heavier family wins
    walls_heavy = synthetic_lines([0.2, 90.2, -89.8, 180.2, 0.2, 15.0, 15.1, 105.0])
    result = track_heading(walls_heavy, 0.0, A45, params=gyro)
    assert result.status == "ok" and math.degrees(result.correction) == pytest.approx(-0.2)
    # Predicted near the clutter's family (a 15 deg turn the gyro measured): that family it is.
    result = track_heading(clutter_heavy, 0.0, A45, predicted_delta=math.radians(-15.0), params=gyro)
    assert result.measured and math.degrees(result.yaw) == pytest.approx(-15.1, abs=0.1)


def test_a_wall_family_far_off_the_gyros_prediction_is_refused() -> None:
    """With a 90 deg map, walls all seen 33 deg off the prediction agree among themselves (a wrong
    family, or the prediction's own error): more than 4 prediction sigmas (20 deg for the pipeline's
    gyro) is refused, never taken as the heading; without a gyro prior there is no bound."""
    gyro = planar_params(LidarPipelineConfig(horizontal_sensor="h", vertical_sensor="v")).heading
    a90 = math.radians(90)
    off = synthetic_lines([33.0, 123.0, -57.0])
    refused = track_heading(off, 0.0, a90, params=gyro)
    assert refused.status == "ambiguous" and refused.yaw == 0.0 and "off the gyro's prediction" in refused.reason
    assert track_heading(off, 0.0, a90).measured  # no prior: the walls say it
    near = track_heading(synthetic_lines([19.0, 109.0, -71.0]), 0.0, a90, params=gyro)
    assert near.measured and math.degrees(near.correction) == pytest.approx(-19.0)


# -- position tracking ---------------------------------------------------------------------------

def test_tracks_a_path_through_the_arena(arena: World, geometry: WorldGeometry) -> None:
    rng = np.random.default_rng(3)
    path = arena_path()
    loc = localizer(arena, geometry, tuple(path[0]))
    errors = []
    for x, y, yaw in path:
        fix = loc.update(scan_at(geometry, x, y, yaw, rng))
        assert fix is not None and fix.state == "tracking" and fix.measured, fix
        assert not fix.relocalized and fix.matched >= 2
        assert_finite(fix)
        errors.append((fix.x - x, fix.y - y, math.remainder(fix.yaw - yaw, 2 * math.pi)))
        # The covariance is not overconfident: chi-square (3 dof) below its 99.9 % point.
        assert errors[-1] @ np.linalg.solve(fix.covariance, errors[-1]) < 16.3
    e = np.array(errors)
    assert math.sqrt(np.mean(np.sum(e[:, :2] ** 2, axis=1))) < 0.02
    assert math.degrees(math.sqrt(np.mean(e[:, 2] ** 2))) < 0.2
    assert set(fix.timing_ms) >= {"lines", "corners", "heading", "match", "total"}


@pytest.mark.parametrize("dropout", [0.1, 0.3])
def test_random_beam_dropouts_keep_tracking(dropout: float) -> None:
    """A fraction of the beams invalid at random (dust, dark or glancing surfaces): still tracking
    on >= 95 % of the scans, never a jump, and as accurate (`companion bench` prints the 30 % run)."""
    run = beam_dropout_run(dropout)
    assert run.tracking >= 0.95 * run.scans and run.relocalized == 0
    assert run.position_rms_m < 0.02


def test_fast_turn_beyond_the_limit_is_resolved_by_the_corners(arena: World, geometry: WorldGeometry) -> None:
    rng = np.random.default_rng(4)
    loc = localizer(arena, geometry, (2.0, 2.0, 0.0))
    assert loc.update(scan_at(geometry, 2.0, 2.0, 0.0, rng)).state == "tracking"
    fix = loc.update(scan_at(geometry, 2.0, 2.0, math.radians(30), rng))  # aliases to -15 deg
    assert fix.heading_status == "near_limit" and fix.state == "degraded"
    assert "alias" in fix.reason and yaw_error(fix.yaw, math.radians(30)) < math.radians(0.3)
    assert math.hypot(fix.x - 2.0, fix.y - 2.0) < 0.02


def test_gyro_prior_and_pose_prior(arena: World, geometry: WorldGeometry) -> None:
    rng = np.random.default_rng(5)
    loc = localizer(arena, geometry, (2.0, 2.0, 0.0))
    fix = loc.update(scan_at(geometry, 2.1, 2.0, math.radians(40), rng), yaw_delta=math.radians(38))
    assert fix.state == "tracking" and fix.heading_status == "ok"
    assert yaw_error(fix.yaw, math.radians(40)) < math.radians(0.2)
    # A prior pose (e.g. the EKF's) replaces the held pose as the prediction: a 0.7 m move
    # between scans is outside the gate from the held pose but not from the prior.
    fix = loc.update(scan_at(geometry, 2.8, 2.0, math.radians(40), rng), prior=(2.75, 2.0, math.radians(40)))
    assert fix.state == "tracking" and math.hypot(fix.x - 2.8, fix.y - 2.0) < 0.02


def test_tilt_and_mount_are_compensated(arena: World, geometry: WorldGeometry) -> None:
    rng = np.random.default_rng(6)
    mount = Mount2D(x_m=0.1, y_m=0.05, yaw_rad=math.pi / 2, z_m=-0.15)  # scanner turned to the right
    loc = localizer(arena, geometry, None, mount)
    for roll, pitch in ((0.0, 0.0), (0.15, -0.1), (-0.2, 0.2)):
        loc.reset(2.0, 2.0, 0.5)
        fix = loc.update(scan_at(geometry, 2.0, 2.0, 0.5, rng, roll, pitch, mount), roll=roll, pitch=pitch)
        assert fix.state == "tracking"
        assert math.hypot(fix.x - 2.0, fix.y - 2.0) < 0.01 and yaw_error(fix.yaw, 0.5) < math.radians(0.2)


@pytest.mark.parametrize("tilt_deg", [20.0, 30.0])
def test_floor_hits_of_a_tilted_scanner_are_dropped_with_the_height_known(tilt_deg: float) -> None:
    """Rolled or pitched 20-30 deg at 1 m, the scanner sweeps the floor 2-3 m away and the ceiling
    (3 m) 4-6 m away: those hits are no walls. With the height given they are dropped and the
    pose holds within 5 cm (`companion bench` prints the 20 deg run)."""
    run = tilted_scan_run(tilt_deg)
    assert run.measured == run.scans == 12
    assert run.max_position_error_m < 0.05 and run.max_yaw_error_rad < math.radians(1.0)


def test_a_level_scanner_near_the_floor_keeps_its_hits(arena: World, geometry: WorldGeometry) -> None:
    """On the ground the scanner is 10 cm above the floor: its level hits are walls, not floor."""
    loc = localizer(arena, geometry, (2.0, 2.0, 0.5))
    scan = scan_at(geometry, 2.0, 2.0, 0.5, np.random.default_rng(21))
    _, everything, _ = loc.level_points(scan)
    for height in (0.0, 0.05, HEIGHT_M):
        _, kept, _ = loc.level_points(scan, height_m=height)
        np.testing.assert_array_equal(kept, everything)


def test_points_input_equals_scan_input(arena: World, geometry: WorldGeometry) -> None:
    scan = scan_at(geometry, 3.0, 2.0, 1.0, np.random.default_rng(7))
    r = np.where(scan.valid, scan.ranges_m, np.nan)
    points = np.column_stack((r * np.cos(scan.angles_rad), r * np.sin(scan.angles_rad)))
    a = localizer(arena, geometry, (3.0, 2.0, 1.0)).update(scan)
    b = localizer(arena, geometry, (3.0, 2.0, 1.0)).update(points)
    assert (a.x, a.y, a.yaw, a.matched) == pytest.approx((b.x, b.y, b.yaw, b.matched), abs=1e-9)


# -- covariance ---------------------------------------------------------------------------------

def test_covariance_grows_with_fewer_corners(arena: World, geometry: WorldGeometry) -> None:
    rng = np.random.default_rng(8)
    loc = localizer(arena, geometry, (2.0, 2.0, math.radians(30)))
    points, valid, ranges = loc.level_points(scan_at(geometry, 2.0, 2.0, math.radians(30), rng))
    lines = extract_lines(points, valid, ranges=ranges)
    corners = find_corners(lines)
    heading = track_heading(lines, math.radians(30), A45)
    assert corners.count >= 4
    traces = []
    for n in (corners.count, 3, 2, 1):
        m = loc.match(lines, corners.subset(np.arange(n)), np.array([2.0, 2.0]), heading)
        assert m.matched == n and math.hypot(*(m.xy - 2.0)) < 0.03
        assert np.all(np.linalg.eigvalsh(m.covariance) > 0)
        traces.append(np.trace(m.covariance[:2, :2]))
    assert traces == sorted(traces)  # fewer corners, larger covariance
    assert traces[-1] > 2 * traces[0]


def test_one_corner_is_a_degraded_but_usable_fix(arena: World, geometry: WorldGeometry) -> None:
    rng = np.random.default_rng(9)
    only = np.array([[5.0, 5.0]])
    loc = PlanarLocalizer(only, 45, mount=MOUNT, initial_pose=(2.0, 2.0, math.radians(30)))
    fix = loc.update(scan_at(geometry, 2.0, 2.0, math.radians(30), rng))
    assert fix.matched == 1 and fix.state == "degraded" and fix.measured
    assert "1 corner" in fix.reason and math.hypot(fix.x - 2.0, fix.y - 2.0) < 0.03
    assert_finite(fix)


# -- lost and relocalization ---------------------------------------------------------------------

@pytest.mark.parametrize("pose", [(2.0, 2.0, 30.0), (8.5, 7.5, 200.0), (6.5, 2.0, -120.0), (3.0, 7.0, 100.0)])
def test_relocalizes_from_an_unknown_start_once_consecutive_scans_agree(
        arena: World, geometry: WorldGeometry, pose: tuple[float, float, float]) -> None:
    x, y, yaw = pose[0], pose[1], math.radians(pose[2])
    loc = localizer(arena, geometry, None)
    rng = np.random.default_rng(10)
    needed = loc.params.reloc_confirm_frames
    for k in range(1, needed):  # a candidate, not yet a pose: nothing to send
        assert loc.update(scan_at(geometry, x, y, yaw, rng)) is None
        assert f"found by {k} of the {needed} scans needed" in loc.last_reason
        assert loc.candidate is not None and loc.candidate.frames == k and not loc.candidate.local
    fix = loc.update(scan_at(geometry, x, y, yaw, rng))
    assert fix is not None, loc.last_reason
    assert fix.relocalized and fix.measured and fix.matched >= 3 and loc.candidate is None
    assert math.hypot(fix.x - x, fix.y - y) < 0.03 and yaw_error(fix.yaw, yaw) < math.radians(0.3)
    assert_finite(fix)


def test_relocalizes_from_a_wrong_start(arena: World, geometry: WorldGeometry) -> None:
    rng = np.random.default_rng(11)
    loc = localizer(arena, geometry, (3.5, 3.0, 0.3))  # 2.6 m and 6 deg off: beyond the local search
    states = []
    for _ in range(10):
        fix = loc.update(scan_at(geometry, 1.5, 1.2, 0.2, rng))
        assert_finite(fix)
        states.append((fix.state, fix.relocalized, fix.measured))
    lost_at = loc.params.lost_after_frames - 1  # frames without a match: degraded, then lost
    first = states.index(("tracking", True, True))
    assert first == lost_at + loc.params.reloc_confirm_frames - 1  # the jump confirmed by consecutive scans
    assert all(s == ("degraded", False, False) for s in states[:lost_at])
    assert all(s == ("lost", False, False) for s in states[lost_at:first])  # never a confident wrong pose
    assert all(s == ("tracking", False, True) for s in states[first + 1:])
    assert math.hypot(fix.x - 1.5, fix.y - 1.2) < 0.02 and yaw_error(fix.yaw, 0.2) < math.radians(0.2)


def test_a_relocalization_that_keeps_moving_is_never_confirmed(arena: World, geometry: WorldGeometry) -> None:
    """Scans alternating between two places (a search fooled every other scan): no pose, ever."""
    loc = localizer(arena, geometry, None)
    rng = np.random.default_rng(15)
    for k in range(4 * loc.params.reloc_confirm_frames):
        x, y, yaw = (2.0, 2.0, math.radians(30.0)) if k % 2 == 0 else (8.5, 7.5, math.radians(200.0))
        assert loc.update(scan_at(geometry, x, y, yaw, rng)) is None
        assert loc.candidate is not None and loc.candidate.frames == 1


def test_a_candidate_moves_with_the_body_and_survives_scans_that_cannot_test_it(
        arena: World, geometry: WorldGeometry) -> None:
    """Scans 0.5 m apart (beyond the confirmation gate), one of them blind (every beam invalid):
    given the motion between scans (``moved_m``, body frame) the candidate is moved with it,
    carried over the blind scan, and confirmed where the body is."""
    loc = localizer(arena, geometry, None)
    rng = np.random.default_rng(17)
    yaw = math.radians(30.0)
    forward = (0.5, 0.0)
    path = [(2.0 + k * 0.5 * math.cos(yaw), 2.0 + k * 0.5 * math.sin(yaw)) for k in range(4)]
    assert loc.update(scan_at(geometry, *path[0], yaw, rng)) is None
    blind = scan_at(geometry, *path[1], yaw, rng)
    assert loc.update(Scan(blind.sensor_id, 0.0, blind.angles_rad, blind.ranges_m, np.zeros_like(blind.valid)),
                      moved_m=forward) is None
    c = loc.candidate
    assert c is not None and c.frames == 1 and c.idle == 1 and math.dist((c.x, c.y), path[1]) < 0.05
    assert loc.update(scan_at(geometry, *path[2], yaw, rng), moved_m=forward) is None
    assert loc.candidate is not None and loc.candidate.frames == 2
    fix = loc.update(scan_at(geometry, *path[3], yaw, rng), moved_m=forward)
    assert fix is not None and fix.relocalized and math.dist((fix.x, fix.y), path[3]) < 0.03
    unmoved = localizer(arena, geometry, None)  # the same scans without the motion: never confirmed
    for xy in path:
        assert unmoved.update(scan_at(geometry, *xy, yaw, rng)) is None


def test_the_held_pose_picks_between_look_alike_rooms() -> None:
    """Two identical rooms 10 m apart: the whole-map search has no clear winner, the held pose
    (0.6 m and 5 deg off, lost) says which room; the jump to it is then confirmed as usual."""
    room = square_room(4.0, 90)
    corners = np.array([(0, 0), (4, 0), (4, 4), (0, 4)], dtype=float)
    twins = np.vstack((corners, corners + (10.0, 0.0)))
    geometry = WorldGeometry.from_world(room)
    truth = (1.7, 2.2, math.radians(40))
    rng = np.random.default_rng(16)
    unknown = PlanarLocalizer(twins, 90, mount=MOUNT)
    assert unknown.update(scan_at(geometry, *truth, rng)) is None
    assert "no clear winner" in unknown.last_reason
    held = PlanarLocalizer(twins, 90, mount=MOUNT, initial_pose=(truth[0] + 0.6, truth[1], truth[2] + math.radians(5)))
    fixes = [held.update(scan_at(geometry, *truth, rng)) for _ in range(10)]
    first = next(k for k, f in enumerate(fixes) if f.relocalized)
    assert first == held.params.lost_after_frames - 1 + held.params.reloc_confirm_frames - 1
    assert all(not f.measured for f in fixes[:first]) and all(f.measured for f in fixes[first:])
    assert "local candidate" in fixes[first - 1].reason
    fix = fixes[-1]
    assert math.hypot(fix.x - truth[0], fix.y - truth[1]) < 0.03 and yaw_error(fix.yaw, truth[2]) < math.radians(0.5)


def _lost_for(loc: PlanarLocalizer, scan: Scan, scans: int) -> None:
    """Dead-reckon ``loc`` through ``scans`` scans that see nothing (every beam invalid)."""
    blank = dataclasses.replace(scan, valid=np.zeros_like(scan.valid))
    for _ in range(scans):
        fix = loc.update(blank)
        assert fix is None or not fix.measured


def test_after_a_long_loss_corners_matching_as_well_elsewhere_within_the_drift_do_not_resume_tracking() -> None:
    """Lost for 100 scans, the held position may be metres off (3 sigma of the coasting drift:
    3.5 m here). The corners seen match the twin room 3 m away as well as the one the held pose
    is in: resuming there would be a guess, so the scan is no fix. With the twin 10 m away,
    beyond that drift, the same scan resumes tracking."""
    room = square_room(4.0, 90)
    corners = np.array([(0, 0), (4, 0), (4, 4), (0, 4)], dtype=float)
    geometry = WorldGeometry.from_world(room)
    truth = (1.7, 2.2, math.radians(40))
    rng = np.random.default_rng(21)
    for apart, held_x, resumes in ((3.0, truth[0] + 3.0, False), (10.0, truth[0] + 0.2, True)):
        loc = PlanarLocalizer(np.vstack((corners, corners + (apart, 0.0))), 90, mount=MOUNT,
                              initial_pose=(held_x, truth[1], truth[2]))
        scan = scan_at(geometry, *truth, rng)
        _lost_for(loc, scan, 100)
        fix = loc.update(scan)
        if resumes:
            assert fix is not None and fix.measured and fix.matched >= 2, loc.last_reason
            assert math.hypot(fix.x - truth[0], fix.y - truth[1]) < 0.05
        else:
            assert fix is None or not fix.measured
            assert "as many 3.0 m away" in (loc.last_reason if fix is None else fix.reason)


def test_symmetric_room_has_no_clear_winner() -> None:
    size = 4.0
    c = [(0, 0), (size, 0), (size, size), (0, size)]
    room = square_room(size, 90)
    loc = PlanarLocalizer(np.array(c, dtype=float), 90, mount=MOUNT, walls=room.segments_at(1.1))
    assert loc.update(scan_at(WorldGeometry.from_world(room), 1.7, 2.2, math.radians(40),
                              np.random.default_rng(12))) is None
    assert "no clear winner" in loc.last_reason


def test_a_search_without_a_clear_winner_shows_its_best_look_alike_hypotheses_first(
        arena: World, geometry: WorldGeometry) -> None:
    """The arena tiled 3 x 3 (9 look-alike rooms), no pose held: the global search weighs many poses
    and has no clear winner. Its hypotheses (for telemetry) are the best ``reloc_hypotheses_reported``
    of them, best first: as many corners each, the wall fractions not rising, every one at the truth
    moved by whole rooms (10 m)."""
    corners, walls = tiled_map(arena, 3, HEIGHT_M - MOUNT.z_m)
    loc = PlanarLocalizer(corners, arena.wall_angle_deg, mount=MOUNT, walls=walls)
    truth = (2.0, 2.0, math.radians(30))
    assert loc.update(scan_at(geometry, *truth, np.random.default_rng(18))) is None
    weighed = re.fullmatch(r"(\d+) candidate poses, no clear winner", loc.reloc_outcome)
    assert weighed is not None, loc.reloc_outcome
    hypotheses = loc.hypotheses
    assert len(hypotheses) == loc.params.reloc_hypotheses_reported < int(weighed.group(1))
    assert all(h.source == "corners" and not h.local for h in hypotheses)
    assert {h.corners for h in hypotheses} == {hypotheses[0].corners} and hypotheses[0].corners >= 3
    fractions = [h.wall_fraction for h in hypotheses]
    assert None not in fractions and fractions == sorted(fractions, reverse=True)
    for h in hypotheses:
        rooms = np.array([h.x - truth[0], h.y - truth[1]]) / 10.0
        assert np.abs(rooms - np.round(rooms)).max() < 0.005 and yaw_error(h.yaw, truth[2]) < math.radians(0.5)


def test_a_clear_winner_is_the_first_hypothesis_and_the_candidate_and_tracking_empties_the_list(
        arena: World, geometry: WorldGeometry) -> None:
    """No pose held, one room: the search's winner is the first hypothesis, where the candidate is;
    the others match fewer corners (their wall fractions not computed). Once the candidate is
    confirmed and tracking runs, the list and the outcome are empty."""
    loc = localizer(arena, geometry, None)
    rng = np.random.default_rng(10)
    truth = (2.0, 2.0, math.radians(30))
    assert loc.update(scan_at(geometry, *truth, rng)) is None
    c = loc.candidate
    assert c is not None and loc.reloc_outcome == ""
    best, *others = loc.hypotheses
    assert (best.x, best.y, best.yaw, best.corners, best.local) == (c.x, c.y, c.yaw, c.matched, c.local)
    assert best.source == "corners" and best.wall_fraction is not None
    assert best.wall_fraction >= loc.params.reloc_min_wall_fraction
    assert others and all(h.corners < best.corners and h.wall_fraction is None for h in others)
    for _ in range(loc.params.reloc_confirm_frames):
        fix = loc.update(scan_at(geometry, *truth, rng))
    assert fix is not None and fix.measured and fix.state == "tracking"
    assert loc.hypotheses == () and loc.reloc_outcome == ""


def test_featureless_views_become_lost_without_nan(arena: World) -> None:
    wall = WorldGeometry.from_world(walls_world([(3.0, -50.0, 3.0, 50.0)]))
    straight = scan_at(wall, 1.0, 0.0, 0.3, np.random.default_rng(13))
    n = UTM30LX_ANGLES.size
    blind = Scan("h", 0.0, UTM30LX_ANGLES, np.full(n, np.nan), np.zeros(n, dtype=bool))
    for scan in (straight, blind):
        loc = PlanarLocalizer(arena.corner_array(), 45, mount=MOUNT, initial_pose=(1.0, 1.0, 0.3))
        fixes = [loc.update(scan) for _ in range(loc.params.lost_after_frames + 2)]
        for fix in fixes:
            assert fix is not None and not fix.measured and fix.matched == 0
            assert_finite(fix)
        assert [f.state for f in fixes[:loc.params.lost_after_frames - 1]] == ["degraded"] * 4
        assert all(f.state == "lost" and "relocalization" in f.reason for f in fixes[loc.params.lost_after_frames - 1:])
        assert PlanarLocalizer(arena.corner_array(), 45).update(scan) is None


def test_a_corridor_without_corners_still_measures_its_cross_track_position() -> None:
    """An 80 m corridor, 2 m wide, its ends out of the scanner's range: no corner in view. The
    walls give the cross-track position and the heading; the along-track position is reported
    unmeasured (a huge variance along the corridor) rather than the fix going lost."""
    corridor = walls_world([(-40.0, -1.0, 40.0, -1.0), (-40.0, 1.0, 40.0, 1.0)], wall_angle_deg=90)
    geometry = WorldGeometry.from_world(corridor)
    ends = np.array([(-40.0, -1.0), (-40.0, 1.0), (40.0, -1.0), (40.0, 1.0)])
    loc = PlanarLocalizer(ends, 90, mount=MOUNT, walls=corridor.segments_at(HEIGHT_M - MOUNT.z_m),
                          initial_pose=(0.0, 0.0, 0.0))
    rng = np.random.default_rng(22)
    for k in range(3 * loc.params.lost_after_frames):
        x, y, yaw = 0.05 * k, 0.3 * math.sin(0.3 * k), math.radians(3.0) * math.sin(0.2 * k)
        fix = loc.update(scan_at(geometry, x, y, yaw, rng))
        assert fix.measured and fix.state == "degraded" and fix.walls_matched >= 2 and fix.matched == 0
        assert "cross-track" in fix.reason
        assert abs(fix.y - y) < 0.01 and yaw_error(fix.yaw, yaw) < math.radians(0.3)
        assert fix.covariance[0, 0] > 0.99 * loc.params.lost_variance_m2 and fix.covariance[1, 1] < 0.01 ** 2
        assert fix.unmeasured is not None and abs(fix.unmeasured[0]) == pytest.approx(1.0)  # the corridor's axis
        assert_finite(fix)


def test_a_corridor_wall_a_little_off_its_map_line_does_not_move_the_along_track_position() -> None:
    """Real walls are not exactly where the map says: here one corridor wall is turned by 1 deg.
    Its line and the other wall's then differ by 1 deg, but both lie on map walls of one direction:
    the fix measures the cross-track position only and leaves the along-track position at the
    prediction (solving for it from the 1 deg difference threw it metres along the corridor)."""
    turn = math.radians(1.0)
    crooked = (-20.0, 1.0 - 20.0 * math.tan(turn), 20.0, 1.0 + 20.0 * math.tan(turn))
    geometry = WorldGeometry.from_world(walls_world([(-40.0, -1.0, 40.0, -1.0), crooked], wall_angle_deg=90))
    mapped = walls_world([(-40.0, -1.0, 40.0, -1.0), (-40.0, 1.0, 40.0, 1.0)], wall_angle_deg=90)
    ends = np.array([(-40.0, -1.0), (-40.0, 1.0), (40.0, -1.0), (40.0, 1.0)])
    loc = PlanarLocalizer(ends, 90, mount=MOUNT, walls=mapped.segments_at(HEIGHT_M - MOUNT.z_m))
    rng = np.random.default_rng(23)
    for x in (-3.0, 0.0, 2.0, 5.0):
        fix = loc.update(scan_at(geometry, x, 0.0, 0.0, rng), (x, 0.0, 0.0))
        assert fix.measured and fix.walls_matched == 2 and "cross-track" in fix.reason, fix
        assert abs(fix.x - x) < 1e-6 and abs(fix.y) < 0.1
        assert fix.covariance[0, 0] > 0.99 * loc.params.lost_variance_m2


def test_a_building_not_aligned_with_north_is_tracked_and_found() -> None:
    """The map frame is the autopilot's NED, so a building's walls may run at any angle: the arena
    turned by 20 deg (wall_offset_deg 20) is tracked along a path and relocalized from nothing."""
    arena = load_world(DEFAULT_WORLD)
    turn = math.radians(20.0)
    rot = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
    walls = arena.segments_at(HEIGHT_M - MOUNT.z_m)
    turned = np.hstack((walls[:, :2] @ rot.T, walls[:, 2:] @ rot.T))
    geometry = WorldGeometry.from_world(walls_world([tuple(w) for w in turned], wall_angle_deg=45))
    corners = arena.corner_array() @ rot.T
    path = [(np.array([x, y]) @ rot.T, yaw + turn) for x, y, yaw in arena_path()[::2]]
    rng = np.random.default_rng(24)
    loc = PlanarLocalizer(corners, 45, mount=MOUNT, walls=turned, wall_offset_deg=20.0,
                          initial_pose=(*path[0][0], path[0][1]))
    for xy, yaw in path:
        fix = loc.update(scan_at(geometry, xy[0], xy[1], yaw, rng))
        assert fix.state == "tracking" and math.hypot(fix.x - xy[0], fix.y - xy[1]) < 0.03, fix
        assert yaw_error(fix.yaw, yaw) < math.radians(0.3)
    unknown = PlanarLocalizer(corners, 45, mount=MOUNT, walls=turned, wall_offset_deg=20.0)
    xy, yaw = path[3]
    fixes = [unknown.update(scan_at(geometry, xy[0], xy[1], yaw, rng)) for _ in range(unknown.params.reloc_confirm_frames)]
    assert fixes[-1] is not None and fixes[-1].relocalized, unknown.last_reason
    assert math.hypot(fixes[-1].x - xy[0], fixes[-1].y - xy[1]) < 0.03
    aligned = PlanarLocalizer(corners, 45, mount=MOUNT, walls=turned, initial_pose=(*xy, yaw))
    assert not aligned.update(scan_at(geometry, xy[0], xy[1], yaw, rng)).measured  # without the offset: no heading


def test_ambiguous_walls_are_lost_at_once(arena: World) -> None:
    # Three walls at 0, 20 and 40 degrees: no consensus modulo 45 degrees.
    walls = []
    for k, deg in enumerate((0.0, 20.0, 40.0)):
        bearing, half = math.radians(-60 + 60 * k), 1.2 * np.array([math.cos(math.radians(deg)),
                                                                   math.sin(math.radians(deg))])
        centre = 3.0 * np.array([math.cos(bearing), math.sin(bearing)])
        walls.append((*(centre - half), *(centre + half)))
    clutter = WorldGeometry.from_world(walls_world(walls))
    loc = PlanarLocalizer(arena.corner_array(), 45, mount=MOUNT, initial_pose=(0.0, 0.0, 0.0))
    fix = loc.update(scan_at(clutter, 0.0, 0.0, 0.0, np.random.default_rng(14)))
    assert fix.state == "lost" and fix.heading_status == "ambiguous" and "disagree" in fix.reason
    assert_finite(fix)


def _brute_force_hypotheses(observed: np.ndarray, landmarks: np.ndarray, yaws: np.ndarray, tolerance: float,
                            min_score: int) -> np.ndarray:
    """The score of every (heading, observed i -> map a) translation by comparing it with all others."""
    k, m = observed.shape[0], landmarks.shape[0]
    rows = []
    for yaw in yaws:
        c, s_ = math.cos(yaw), math.sin(yaw)
        trans = (landmarks[None, :, :] - (observed @ np.array([[c, -s_], [s_, c]]).T)[:, None, :]).reshape(-1, 2)
        diff = trans[:, None, :] - trans[None, :, :]
        close = (diff[..., 0] ** 2 + diff[..., 1] ** 2 <= tolerance ** 2).reshape(k * m, k, m)
        score = close.any(axis=2).sum(axis=1)
        good = score >= min_score
        rows.append(np.column_stack((score[good], np.full(good.sum(), yaw), trans[good])))
    out = np.concatenate(rows)
    return out[np.argsort(-out[:, 0], kind="stable")]


def test_pose_hypotheses_score_as_the_all_pairs_comparison_does() -> None:
    rng = np.random.default_rng(17)
    for trial in range(60):
        landmarks = np.round(rng.uniform(0.0, 10.0, (int(rng.integers(1, 40)), 2)), 1)
        yaw = rng.uniform(-math.pi, math.pi)
        picked = landmarks[rng.choice(landmarks.shape[0], min(landmarks.shape[0], int(rng.integers(1, 11))), replace=False)]
        c, s_ = math.cos(yaw), math.sin(yaw)
        observed = (picked - rng.uniform(-5, 5, 2)) @ np.array([[c, -s_], [s_, c]]) + rng.normal(0, 0.05, picked.shape)
        yaws = np.array([yaw, yaw + math.pi / 2, 0.0])
        for tolerance, min_score in ((0.15, 1), (0.3, 2)):
            np.testing.assert_array_equal(pose_hypotheses(observed, landmarks, yaws, tolerance, min_score),
                                          _brute_force_hypotheses(observed, landmarks, yaws, tolerance, min_score))


def test_a_corner_proposes_no_pose_on_a_map_corner_of_another_shape() -> None:
    """Map corners 2 and 3 lie as 0 and 1 do, 3 m further north, but their walls run south where
    0's and 1's run north (the back of a recess and its mouth): only the shapes tell them apart."""
    north, east, south, west = (1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0)
    landmarks = np.array([[5.0, 5.0], [5.0, 7.0], [8.0, 5.0], [8.0, 7.0]])
    map_rays = np.array([[north, east], [north, west], [south, east], [south, west]])
    observed = np.array([[3.0, 3.0], [3.0, 5.0]])  # from (2, 2) at yaw 0: map corners 0 and 1
    shapes = (np.array([[north, east], [north, west]]), np.full((2, 2), math.cos(math.radians(20.0))), map_rays)
    blind = pose_hypotheses(observed, landmarks, np.array([0.0]), 0.3, 2)
    assert sorted(map(tuple, blind[:, 2:4].tolist())) == [(2.0, 2.0), (2.0, 2.0), (5.0, 2.0), (5.0, 2.0)]
    shaped = pose_hypotheses(observed, landmarks, np.array([0.0]), 0.3, 2, shapes)
    assert shaped[:, 2:4].tolist() == [[2.0, 2.0], [2.0, 2.0]] and shaped[:, 0].tolist() == [2.0, 2.0]


def test_relocalization_on_a_1500_corner_map_stays_small(arena: World, geometry: WorldGeometry) -> None:
    """The arena tiled 10 x 10: 100 look-alike rooms. No clear winner (honestly), in little memory."""
    corners, walls = tiled_map(arena, 10, HEIGHT_M - MOUNT.z_m)
    assert corners.shape[0] == 1500
    loc = PlanarLocalizer(corners, arena.wall_angle_deg, mount=MOUNT, walls=walls)
    scan = scan_at(geometry, 2.0, 2.0, math.radians(30), np.random.default_rng(18))
    tracemalloc.start()
    try:
        assert loc.update(scan) is None and "no clear winner" in loc.last_reason
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 50e6  # the all-pairs comparison needed ~1.4 GB here


def test_stage_bench_runs() -> None:
    result = run_stage_bench(3)
    assert "lidar.planar update (whole pipeline)" in result
    assert "lidar.relocalize, 1,500 corners (arena tiled 10x10)" in result
    assert all(math.isfinite(m) and math.isfinite(p) and 0 < m <= p for m, p in result.values())


def test_heading_result_is_reported(arena: World, geometry: WorldGeometry) -> None:
    result = track_heading(levelled_lines(geometry, 2.0, 2.0, 0.1, np.random.default_rng(15)), 0.1, A45)
    assert isinstance(result, HeadingResult) and result.measured and result.lines_used >= 3
    assert 0 < result.variance < math.radians(0.1) ** 2 and result.consensus == pytest.approx(1.0)


def test_the_configured_correspondence_gate_reaches_the_localizer() -> None:
    cfg = LidarPipelineConfig(horizontal_sensor="h", vertical_sensor="v", correspondence_gate_m=0.3)
    assert planar_params(cfg).gate_m == 0.3


def test_the_configured_noise_floors_reach_the_localizer_the_height_fix_and_the_fusion(arena: World) -> None:
    cfg = LidarPipelineConfig(horizontal_sensor="h", vertical_sensor="v", accel_noise_density=0.0015,
                              yaw_rate_noise_density=0.0002, line_model_error_m=0.0, corner_error_per_m=0.0,
                              heading_error_deg=0.0, height_model_error_m=0.001)
    params = planar_params(cfg)
    assert params.lines.model_floor_m == 0.0 and params.corners.floor_per_m == 0.0
    assert params.heading.variance_floor_rad2 == 0.0
    assert params.lines.max_missing_beams == PlanarParams().lines.max_missing_beams  # the rest as they were
    pipeline = LidarPipeline(cfg, arena, MountConfig(), MountConfig(rpy_deg=(90.0, 0.0, 0.0)), Health(lambda: 0.0))
    assert pipeline.fusion.config.accel_noise_density == 0.0015
    assert pipeline.fusion.config.yaw_rate_noise_density == 0.0002
    assert pipeline.height.params.variance_floor_m2 == pytest.approx(0.001 ** 2)
    assert pipeline.height.params.lines.model_floor_m == 0.0
    assert pipeline.height.params.lines.noise_m == HeightParams().lines.noise_m


def test_the_pipelines_snapshot_shows_the_relocalization_hypotheses_as_json(
        arena: World, geometry: WorldGeometry) -> None:
    """``system.pipelines.lidar``: the hypotheses of the newest relocalization (the winner first,
    where the candidate is) and its outcome, in plain JSON; empty lists before any search."""
    cfg = LidarPipelineConfig(horizontal_sensor="h", vertical_sensor="v")
    pipeline = LidarPipeline(cfg, arena, MountConfig(), MountConfig(rpy_deg=(90.0, 0.0, 0.0)), Health(lambda: 0.0))
    before = pipeline.snapshot()
    assert before["relocalization_hypotheses"] == [] and before["relocalization_outcome"] == ""
    scan = scan_at(geometry, 2.0, 2.0, math.radians(30), np.random.default_rng(10), mount=Mount2D())
    assert pipeline.localizer.update(scan) is None
    snapshot = json.loads(json.dumps(pipeline.snapshot(), allow_nan=False))
    candidate, hypotheses = snapshot["relocalization_candidate"], snapshot["relocalization_hypotheses"]
    assert len(hypotheses) > 1 and snapshot["relocalization_outcome"] == ""
    best = hypotheses[0]
    assert set(best) == {"position_ned_m", "yaw_rad", "source", "corners", "wall_fraction", "local"}
    assert best["position_ned_m"] == list(candidate["position_ned_m"]) and best["yaw_rad"] == candidate["yaw_rad"]
    assert best["source"] == "corners" and best["corners"] == candidate["matched"] and best["local"] is False
    assert 0.0 < best["wall_fraction"] <= 1.0 and hypotheses[1]["wall_fraction"] is None


def test_the_maps_survey_error_widens_every_fix_from_it(arena: World, geometry: WorldGeometry) -> None:
    """World.survey_error_m is the floor of every matched corner's covariance (and of every wall's)."""
    cfg = LidarPipelineConfig(horizontal_sensor="h", vertical_sensor="v")
    scan = scan_at(geometry, 2.0, 2.0, 0.5, np.random.default_rng(23))
    variances = []
    for survey in (0.005, 0.03):
        params = planar_params(cfg, survey)
        assert params.corners.floor_m == params.map_error_m == survey
        loc = PlanarLocalizer(arena.corner_array(), arena.wall_angle_deg, mount=MOUNT, params=params,
                              initial_pose=(2.0, 2.0, 0.5))
        fix = loc.update(scan)
        assert fix.state == "tracking"
        variances.append(np.trace(fix.covariance[:2, :2]))
    assert variances[1] > 4 * variances[0]


def test_the_maps_wall_direction_error_widens_every_fixs_heading_and_not_its_position(
        arena: World, geometry: WorldGeometry) -> None:
    """World.wall_direction_error_deg: the map's walls may run that far off the directions the
    heading is measured against. Every fix's yaw variance carries it; the position block and the
    position-yaw terms stay the lines' own (README, "Real buildings")."""
    cfg = LidarPipelineConfig(horizontal_sensor="h", vertical_sensor="v")
    scan = scan_at(geometry, 2.0, 2.0, 0.5, np.random.default_rng(23))
    fixes = []
    for error_deg in (0.0, 0.5):
        params = planar_params(cfg, arena.survey_error_m, error_deg)
        assert params.map_heading_error_rad == pytest.approx(math.radians(error_deg))
        loc = PlanarLocalizer(arena.corner_array(), arena.wall_angle_deg, mount=MOUNT, params=params,
                              initial_pose=(2.0, 2.0, 0.5))
        fixes.append(loc.update(scan))
    exact, turned = (f.covariance for f in fixes)
    assert fixes[1].state == "tracking" and fixes[1].yaw == fixes[0].yaw
    assert turned[2, 2] - exact[2, 2] == pytest.approx(math.radians(0.5) ** 2)
    assert np.array_equal(turned[:2, :], exact[:2, :]) and np.array_equal(turned[:2, 2], exact[:2, 2])


def test_the_yaw_sent_claims_no_less_than_the_maps_wall_direction_error(arena: World) -> None:
    """Successive fixes share the map's walls, so averaging them does not shrink that error: the
    pipeline's estimate floors its yaw variance at it (and leaves a larger one alone)."""
    turned = dataclasses.replace(arena, wall_direction_error_deg=0.5)
    floor = math.radians(0.5) ** 2
    for world, expected in ((arena, 1e-8), (turned, floor)):
        pipeline = LidarPipeline(LidarPipelineConfig(horizontal_sensor="h", vertical_sensor="v"), world,
                                 MountConfig(), MountConfig(rpy_deg=(90.0, 0.0, 0.0)), Health(lambda: 0.0))
        state = pipeline.fusion.state(0.0)
        sure = dataclasses.replace(state, yaw_variance=1e-8)
        assert pipeline._with_shared_errors(sure).yaw_variance == pytest.approx(expected)
        unsure = dataclasses.replace(state, yaw_variance=4 * floor)
        assert pipeline._with_shared_errors(unsure).yaw_variance == 4 * floor


def test_a_wall_fix_carries_the_headings_uncertainty_into_its_position() -> None:
    """Turning the scan about the scanner moves where its wall lines and their ends land on the map:
    the wall fix's position covariance holds the heading variance times that sensitivity, and its
    position-yaw covariance the sensitivity itself, as the corner fix's does (checked against the
    fix recomputed at a heading turned by +/- 0.1 mrad)."""
    corridor = load_world(DEFAULT_WORLD.parent / "corridor.yaml")
    geometry = WorldGeometry.from_world(corridor)
    for x, yaw in ((31.0, 0.0), (31.0, 0.3), (3.0, 0.2), (20.0, -0.1)):
        loc = PlanarLocalizer(corridor.corner_array(), corridor.wall_angle_deg, mount=MOUNT,
                              walls=corridor.segments_at(HEIGHT_M - MOUNT.z_m))
        points, ok, ranges = loc.level_points(scan_at(geometry, x, 1.2, yaw, np.random.default_rng(1)))
        lines = extract_lines(points, ok, loc.params.lines, ranges)
        edges = occluding_ends(lines, points, ok, ranges, np.array([MOUNT.x_m, MOUNT.y_m]), loc.params.lines)
        heading = track_heading(lines, yaw, loc.wall_angle, 0.0, loc.params.heading)
        prior = np.array([x + 0.03, 1.21])
        fixes = [loc._wall_fix(lines, edges, prior, _with_yaw(heading, heading.yaw + d), "", {}, 0.0)
                 for d in (0.0, 1e-4, -1e-4)]
        assert all(f is not None for f in fixes)
        fix, turned, back = fixes
        sensitivity = (np.array([turned.x - back.x, turned.y - back.y])) / 2e-4  # m/rad
        assert np.linalg.norm(sensitivity) > 1.0  # the lines' middles lie metres from the scanner
        np.testing.assert_allclose(fix.covariance[:2, 2], heading.variance * sensitivity, rtol=1e-6, atol=1e-15)
        assert fix.covariance[0, 0] >= heading.variance * sensitivity[0] ** 2
        assert np.all(np.linalg.eigvalsh(fix.covariance) > 0.0)


def test_the_ends_of_a_corridors_walls_measure_the_along_track_position() -> None:
    """Between two door recesses of config/worlds/corridor.yaml no corner is in view, but the walls
    end at the recesses: where a wall line is the nearer surface at a range jump its end is a real
    edge (companion/nav/edges.py), and the map wall's end says where it is along the corridor.
    From a prediction drifted 0.2 m along the corridor every fix there measures the position in
    both directions, within its reported sigma. The scanner mixes no pixels at depth edges (with
    mixed pixels an end 8 m ahead seen 9 deg off the wall is known to 0.3 m, and where it is the only
    one in view the along-track direction is unmeasured: tests/test_nav_edges.py)."""
    corridor = load_world(DEFAULT_WORLD.parent / "corridor.yaml")
    geometry = WorldGeometry.from_world(corridor)
    rng = np.random.default_rng(5)
    unmixed = PlanarParams(edges=dataclasses.replace(PlanarParams().edges, mixed_pixels=False))
    ended = 0
    for x in np.arange(29.5, 33.6, 0.25):
        loc = PlanarLocalizer(corridor.corner_array(), corridor.wall_angle_deg, mount=MOUNT, params=unmixed,
                              walls=corridor.segments_at(HEIGHT_M - MOUNT.z_m), initial_pose=(x + 0.2, 1.2, 0.0))
        fix = loc.update(scan_at(geometry, x, 1.2, 0.0, rng))
        assert fix is not None and fix.measured and fix.unmeasured is None, fix.reason
        assert abs(fix.x - x) < max(3.0 * math.sqrt(fix.covariance[0, 0]), 0.01) and fix.covariance[0, 0] < 0.1 ** 2
        assert abs(fix.y - 1.2) < 0.02
        if "of their ends" in fix.reason:
            ended += 1
            assert fix.ends_only is not None and abs(fix.ends_only[0]) > 0.999  # the corridor's axis, north
    assert ended >= 14  # (of 17) the walls' ends, not a corner, measured it


def _room_without_corners(shift_east_wall_m: float = 0.0) -> tuple[WorldGeometry, np.ndarray]:
    """A 4 m x 5 m room seen by the scanner (its east wall moved by ``shift_east_wall_m``) and its
    map walls as planned (no corners listed: only walls can place the vehicle)."""
    planned = [(0.0, 0.0, 4.0, 0.0), (4.0, 0.0, 4.0, 5.0), (4.0, 5.0, 0.0, 5.0), (0.0, 5.0, 0.0, 0.0)]
    built = [(x0, y0 + shift_east_wall_m * (y0 == 5.0), x1, y1 + shift_east_wall_m * (y1 == 5.0))
             for x0, y0, x1, y1 in planned]
    return WorldGeometry.from_world(walls_world(built, wall_angle_deg=90)), np.array(planned)


def test_after_a_loss_the_walls_near_the_held_pose_resume_tracking() -> None:
    """Lost for 20 scans (nothing seen), the held position is 1 m off the truth: beyond the wall
    gate, and no corner is mapped. The walls of both directions in view put the vehicle at one
    position near the held one; that jump is confirmed over scans like a relocalization, then
    tracking resumes there, a reset."""
    geometry, walls = _room_without_corners()
    truth = (1.6, 2.3, math.radians(20))
    loc = PlanarLocalizer(np.zeros((0, 2)), 90, mount=MOUNT, walls=walls,
                          initial_pose=(truth[0] + 0.8, truth[1] - 0.6, truth[2]))
    rng = np.random.default_rng(31)
    _lost_for(loc, scan_at(geometry, *truth, rng), 20)
    fixes = [loc.update(scan_at(geometry, *truth, rng)) for _ in range(loc.params.reloc_confirm_frames + 1)]
    waiting, resumed, tracking = fixes[:-2], fixes[-2], fixes[-1]
    assert all(not f.measured and "walls: found by" in f.reason for f in waiting), [f.reason for f in waiting]
    assert resumed.measured and resumed.relocalized and "resumed on the walls" in resumed.reason
    assert tracking.measured and not tracking.relocalized and tracking.walls_matched == 4
    for fix in (resumed, tracking):
        assert math.hypot(fix.x - truth[0], fix.y - truth[1]) < 0.02 and fix.unmeasured is None
        assert_finite(fix)


def test_walls_that_fit_as_well_elsewhere_within_the_drift_do_not_resume_tracking() -> None:
    """The same loss, but the map also holds the room's walls 1 m further east (a look-alike within
    the drift): both positions put every point on a wall, so the walls resume nothing. With the
    look-alike 6 m away, beyond the drift, they do."""
    geometry, walls = _room_without_corners()
    truth = (1.6, 2.3, math.radians(20))
    for apart, resumes in ((1.0, False), (6.0, True)):
        look_alike = walls + np.array([0.0, apart, 0.0, apart])
        loc = PlanarLocalizer(np.zeros((0, 2)), 90, mount=MOUNT, walls=np.vstack((walls, look_alike)),
                              initial_pose=(truth[0] + 0.3, truth[1] + 0.5, truth[2]))
        rng = np.random.default_rng(32)
        _lost_for(loc, scan_at(geometry, *truth, rng), 20)
        fixes = [loc.update(scan_at(geometry, *truth, rng)) for _ in range(2 * loc.params.reloc_confirm_frames)]
        if resumes:
            assert fixes[-1].measured and math.hypot(fixes[-1].x - truth[0], fixes[-1].y - truth[1]) < 0.02
        else:
            assert all(not f.measured and "no clear winner" in f.reason for f in fixes), [f.reason for f in fixes]


def test_the_wall_search_shows_the_look_alike_positions_it_weighed() -> None:
    """Lost in a room without mapped corners whose walls the map also holds 1 m further east: the
    wall search near the held pose weighs both positions, as good as each other, and shows them
    (source walls, no corners, local) best first, the truth among them."""
    geometry, walls = _room_without_corners()
    truth = (1.6, 2.3, math.radians(20))
    look_alike = walls + np.array([0.0, 1.0, 0.0, 1.0])
    loc = PlanarLocalizer(np.zeros((0, 2)), 90, mount=MOUNT, walls=np.vstack((walls, look_alike)),
                          initial_pose=(truth[0] + 0.3, truth[1] + 0.5, truth[2]))
    rng = np.random.default_rng(32)
    _lost_for(loc, scan_at(geometry, *truth, rng), 20)
    fix = loc.update(scan_at(geometry, *truth, rng))
    assert not fix.measured and "by walls:" in loc.reloc_outcome and "no clear winner" in loc.reloc_outcome
    hypotheses = loc.hypotheses
    assert len(hypotheses) >= 2 and all(h.source == "walls" and h.corners == 0 and h.local for h in hypotheses)
    fractions = [h.wall_fraction for h in hypotheses]
    assert None not in fractions and fractions == sorted(fractions, reverse=True)
    assert fractions[0] - fractions[1] < loc.params.reloc_wall_margin
    assert min(math.hypot(h.x - truth[0], h.y - truth[1]) for h in hypotheses[:2]) < 0.05


def test_a_lost_corridor_is_not_resumed_by_its_parallel_walls() -> None:
    """Walls of one direction fix the cross-track position only: after a loss they propose no
    position (the along-track one would be a guess)."""
    corridor = walls_world([(-40.0, -1.0, 40.0, -1.0), (-40.0, 1.0, 40.0, 1.0)], wall_angle_deg=90)
    geometry = WorldGeometry.from_world(corridor)
    loc = PlanarLocalizer(np.zeros((0, 2)), 90, mount=MOUNT, walls=corridor.segments_at(HEIGHT_M - MOUNT.z_m),
                          initial_pose=(0.5, 0.4, 0.0))
    rng = np.random.default_rng(33)
    _lost_for(loc, scan_at(geometry, 0.0, 0.0, 0.0, rng), 20)
    for _ in range(5):
        fix = loc.update(scan_at(geometry, 0.0, 0.0, 0.0, rng))
        assert not fix.measured and "no lines of two wall directions" in fix.reason


def test_walls_that_disagree_widen_the_wall_fix() -> None:
    """The room's east wall stands 10 cm east of its map line: the two east-west measurements
    disagree, the fix lands between them, and its variance grows with that disagreement (the
    residual chi-square per degree of freedom, as for corners) so that it still covers the error.
    Where the walls agree the fix keeps its millimetres."""
    truth = (1.6, 2.3, math.radians(20))
    errors = {}
    for shift in (0.0, 0.1):
        geometry, walls = _room_without_corners(shift)
        loc = PlanarLocalizer(np.zeros((0, 2)), 90, mount=MOUNT, walls=walls, initial_pose=truth)
        fix = loc.update(scan_at(geometry, *truth, np.random.default_rng(34)))
        assert fix.measured and fix.walls_matched == 4 and fix.unmeasured is None
        errors[shift] = (fix.y - truth[1], math.sqrt(fix.covariance[1, 1]))
    (clean_error, clean_sigma), (error, sigma) = errors[0.0], errors[0.1]
    assert abs(clean_error) < 0.005 and clean_sigma < 0.01
    assert 0.03 < abs(error) < 0.07 and abs(error) < 2.0 * sigma


def test_more_wall_positions_than_the_cap_resume_nothing() -> None:
    """The walls are never searched among a cut list: with more positions near the held pose than
    ``reloc_wall_positions_max`` (a long drift among repeated walls) the walls resume nothing."""
    geometry, walls = _room_without_corners()
    truth = (1.6, 2.3, math.radians(20))
    params = dataclasses.replace(PlanarParams(), reloc_wall_positions_max=1)  # the look-alike makes two
    look_alike = walls + np.array([0.0, 1.0, 0.0, 1.0])
    loc = PlanarLocalizer(np.zeros((0, 2)), 90, mount=MOUNT, walls=np.vstack((walls, look_alike)), params=params,
                          initial_pose=(truth[0] + 0.8, truth[1] - 0.6, truth[2]))
    rng = np.random.default_rng(35)
    _lost_for(loc, scan_at(geometry, *truth, rng), 20)
    for _ in range(2 * loc.params.reloc_confirm_frames):
        fix = loc.update(scan_at(geometry, *truth, rng))
        assert not fix.measured and "too many look-alikes" in fix.reason, fix.reason


@pytest.mark.parametrize("pose", [(2.0, 2.0, math.radians(30)), (3.0, 7.5, math.radians(170))])
def test_fix_covariance_matches_the_spread_of_fixes_from_noisy_scans(arena: World, geometry: WorldGeometry,
                                                                      pose: tuple[float, float, float]) -> None:
    """With the floors off (an exact map, ideal beams) a fix's position covariance is what the line
    fits' errors make it: corners and heading from the same lines, propagated jointly
    (companion/nav/corner_fix.py). Scored against the spread of fixes over many noisy scans."""
    params = PlanarParams(corners=dataclasses.replace(PlanarParams().corners, floor_m=0.0, floor_per_m=0.0),
                          heading=dataclasses.replace(PlanarParams().heading, variance_floor_rad2=0.0),
                          lines=dataclasses.replace(PlanarParams().lines, model_floor_m=0.0))
    loc = PlanarLocalizer(arena.corner_array(), arena.wall_angle_deg, mount=MOUNT, params=params)
    rng = np.random.default_rng(1)
    errors, covariances = [], []
    for _ in range(250):
        points, valid, ranges = loc.level_points(scan_at(geometry, *pose, rng))
        lines = extract_lines(points, valid, params.lines, ranges)
        heading = track_heading(lines, pose[2], A45, 0.0, params.heading)
        m = loc.match(lines, find_corners(lines, params.corners), np.array(pose[:2]), heading)
        assert m.matched >= 3
        errors.append([m.xy[0], m.xy[1], math.remainder(heading.yaw - pose[2], 2 * math.pi)])
        covariances.append(m.covariance)
    e = np.array(errors) - np.mean(errors, axis=0)  # the scanner's mount offset is a constant, not noise
    cov = np.array(covariances)
    per_axis = np.mean(e[:, :2] ** 2 / cov[:, [0, 1], [0, 1]], axis=0)  # north, east: 1 if consistent
    assert np.all((per_axis > 0.7) & (per_axis < 1.3)), per_axis  # shared errors counted twice: 0.54-0.66
    position = np.einsum("ni,nij,nj->n", e[:, :2], np.linalg.inv(cov[:, :2, :2]), e[:, :2])
    assert 1.45 < position.mean() < 2.6  # 2 if consistent; the residual scaling leans cautious


RECESSED_CORRIDOR = [(-10.0, 0.0, 20.0, 0.0), (-10.0, 2.4, 4.0, 2.4), (4.0, 2.4, 4.0, 2.6), (4.0, 2.6, 5.0, 2.6),
                     (5.0, 2.6, 5.0, 2.4), (5.0, 2.4, 20.0, 2.4)]  # a corridor along x, a door recess on its east side


def test_a_map_corners_rays_run_along_the_walls_ending_at_it_and_both_ways_along_one_passing_through() -> None:
    leaving = (4.5, 2.6, 4.5, 3.6)  # a wall leaving the recess's back: a T
    walls = MapWalls.from_segments(np.array(RECESSED_CORRIDOR + [leaving]), math.pi / 2, 0.0)
    rays = map_corner_rays(np.array([[4.0, 2.4], [4.5, 2.6], [30.0, 0.0]]), walls, 0.1)
    def directions(m: int) -> set[tuple[int, int]]:
        return {(round(float(x)), round(float(y))) for x, y in rays[m] if not math.isnan(x)}
    assert directions(0) == {(-1, 0), (0, 1)}  # the recess's mouth: back along the corridor, into the recess
    assert directions(1) == {(-1, 0), (1, 0), (0, 1)}  # the T on the recess's back wall
    assert directions(2) == set()  # no wall reaches it: any observed corner agrees


def test_a_ray_along_a_short_line_vetoes_a_pair_only_when_it_runs_the_wrong_way() -> None:
    walls = MapWalls.from_segments(np.array(RECESSED_CORRIDOR), math.pi / 2, 0.0)
    mouth = map_corner_rays(np.array([[4.0, 2.4]]), walls, 0.1)  # rays (-1, 0), (0, 1)
    long_lines = np.full((1, 2), math.cos(math.radians(20.0)))
    short_first = np.array([[math.cos(math.radians(70.0)), math.cos(math.radians(20.0))]])
    back = np.array([[[1.0, 0.0], [0.0, -1.0]]])  # a recess's back corner: along the back wall, out of the recess
    mouth_seen = np.array([[[-0.97, 0.24], [0.0, 1.0]]])  # the mouth, one line 14 deg off
    assert not shapes_agree(back, long_lines, mouth)[0] and shapes_agree(mouth_seen, long_lines, mouth)[0]
    slanted = np.array([[[-0.6, 0.8], [0.0, 1.0]]])  # the mouth, its first line 53 deg off
    assert not shapes_agree(slanted, long_lines, mouth)[0]
    assert shapes_agree(slanted, short_first, mouth)[0]  # a short line's direction is that poor
    assert not shapes_agree(back, short_first, mouth)[0]  # but not the wrong way
    both_short = np.full((1, 2), math.cos(math.radians(70.0)))
    assert not shapes_agree(back, both_short, mouth)[0]  # the recess's back seen from across the corridor
    assert shapes_agree(back, long_lines, np.full((1, 1, 2), np.nan))[0]  # a map corner no wall reaches: any shape


def test_a_corner_pairs_only_with_a_map_corner_whose_walls_run_the_same_ways() -> None:
    """A door recess's back corners lie 20 cm from its mouth's, inside the association gate, and
    the survey missed one of them (as in config/sitl-corridor-realistic.yaml). From a held position
    20 cm off across the corridor, away from the recess, each back corner lands on a mouth corner
    (the observed corners are placed 20 cm short of where they are): paired by distance alone
    they confirm the wrong position (the realistic corridor flew 3 m with its cross-track position
    21 cm off that way); their walls run other ways, so they are not paired and the fix comes back."""
    geometry = WorldGeometry.from_world(walls_world(RECESSED_CORRIDOR, wall_angle_deg=90))
    mapped = walls_world(RECESSED_CORRIDOR, wall_angle_deg=90)
    corners = np.array([(4.0, 2.4), (4.0, 2.6), (5.0, 2.4)])  # the recess's back corner (5.0, 2.6) not surveyed
    rng = np.random.default_rng(31)
    for x in (1.0, 1.5, 2.0):
        scan = scan_at(geometry, x, 1.2, 0.0, rng)
        for tolerance, short, off in ((20.0, 70.0, False), (180.0, 180.0, True)):  # 180 deg: by distance alone
            params = PlanarParams(corner_shape_tolerance_deg=tolerance, corner_shape_short_tolerance_deg=short)
            loc = PlanarLocalizer(corners, 90, mount=MOUNT, walls=mapped.segments_at(HEIGHT_M - MOUNT.z_m),
                                  params=params)
            fix = loc.update(scan, (x, 1.0, 0.0))
            assert fix is not None and fix.measured
            assert (abs(fix.y - 1.2) > 0.1) is off, (tolerance, fix)


def test_a_fix_names_the_corner_pairs_it_used_and_not_the_one_its_outlier_test_dropped(
        arena: World, geometry: WorldGeometry) -> None:
    rng = np.random.default_rng(5)
    pose = (2.0, 2.0, math.radians(30.0))
    truth = localizer(arena, geometry, pose).update(scan_at(geometry, *pose, rng))
    assert truth is not None and truth.matched >= 4
    moved = truth.corner_pairs[0][1]  # a map corner this view pairs with, surveyed 10 cm off:
    shifted = arena.corner_array().copy()
    shifted[moved] += (0.1, 0.0)  # within the gate and the shape test, beyond the outlier test
    loc = PlanarLocalizer(shifted, arena.wall_angle_deg, mount=MOUNT, walls=arena.segments_at(HEIGHT_M - MOUNT.z_m),
                          initial_pose=pose, ceiling_m=-geometry.ceiling_z)
    fix = loc.update(scan_at(geometry, *pose, rng))
    assert fix is not None and fix.state == "tracking"
    assert len(fix.corner_pairs) == fix.matched == truth.matched - 1
    assert moved not in {known for _, known in fix.corner_pairs}
    observed = loc.last_corners.xy
    c, s = math.cos(fix.yaw), math.sin(fix.yaw)
    for i, known in fix.corner_pairs:  # each observed corner placed with the fix lands on its map corner
        q = observed[i]
        assert math.dist((fix.x + c * q[0] - s * q[1], fix.y + s * q[0] + c * q[1]), shifted[known]) < 0.05
