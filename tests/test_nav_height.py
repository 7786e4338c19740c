"""Height above the floor from the vertical scanner, on ray-cast scans of the default arena."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.nav.bench_stages import DEFAULT_WORLD, make_mount, synthetic_scan
from companion.nav.height import HeightEstimator, HeightFix, HeightParams
from companion.nav.lines import LineParams
from drivers.lidar_models import URG_04LX
from companion.messages import Scan
from sitl.raycast import WorldGeometry
from companion.world import load_world

MOUNT_POSITION = (0.05, 0.0, 0.05)  # body FRD, metres: 5 cm forward, 5 cm below the body origin
MOUNT_RPY = (math.pi / 2, 0.0, 0.0)  # scan plane = body x-z, sensor y = body down
TABLE_XY = (7.4, 1.6)  # centre of the 0.75 m table in the north-west room
URG04LX_ANGLES = URG_04LX.angles_rad()


@pytest.fixture(scope="module")
def geometry() -> WorldGeometry:
    return WorldGeometry.from_world(load_world(DEFAULT_WORLD))


def vertical_scan(geometry: WorldGeometry, x: float, y: float, height: float, rng: np.random.Generator,
                  roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0) -> Scan:
    """A URG-04LX (1 cm noise, 0.02-5.6 m) on a body ``height`` m above the floor."""
    return synthetic_scan(geometry, URG_04LX, make_mount(MOUNT_POSITION, MOUNT_RPY), np.array([x, y, -height]),
                          (roll, pitch, yaw), rng, 0.01)


def assert_finite(fix: HeightFix) -> None:
    assert math.isfinite(fix.height_m) and math.isfinite(fix.variance) and fix.variance > 0


@pytest.mark.parametrize("height", [0.3, 1.0, 2.0])
def test_height_over_the_floor(geometry: WorldGeometry, height: float) -> None:
    rng = np.random.default_rng(int(height * 10))
    est = HeightEstimator(MOUNT_POSITION, MOUNT_RPY)
    for yaw in np.radians([0.0, 60.0, 135.0, 250.0]):
        fix = est.update(vertical_scan(geometry, 2.5, 2.0, height, rng, yaw=yaw))
        assert fix.state == "ok", fix.reason
        assert abs(fix.height_m - height) < 0.01
        assert abs(fix.height_m - height) < 4 * math.sqrt(fix.variance)


@pytest.mark.parametrize("roll, pitch", [(0.1, 0.0), (0.0, -0.2), (0.15, 0.15), (-0.2, 0.1)])
def test_attitude_is_compensated(geometry: WorldGeometry, roll: float, pitch: float) -> None:
    rng = np.random.default_rng(3)
    est = HeightEstimator(MOUNT_POSITION, MOUNT_RPY)
    fix = est.update(vertical_scan(geometry, 2.5, 2.0, 1.2, rng, roll, pitch, yaw=0.4), roll, pitch)
    assert fix.state == "ok" and abs(fix.height_m - 1.2) < 0.01
    uncompensated = HeightEstimator(MOUNT_POSITION, MOUNT_RPY).update(
        vertical_scan(geometry, 2.5, 2.0, 1.2, rng, roll, pitch, yaw=0.4))
    assert abs(uncompensated.height_m - 1.2) > abs(fix.height_m - 1.2)


@pytest.mark.parametrize("yaw_deg", [0.0, 90.0, 30.0])
def test_the_floor_wins_over_the_table(geometry: WorldGeometry, yaw_deg: float) -> None:
    rng = np.random.default_rng(4)
    est = HeightEstimator(MOUNT_POSITION, MOUNT_RPY)
    fix = est.update(vertical_scan(geometry, *TABLE_XY, 1.5, rng, yaw=math.radians(yaw_deg)))
    assert fix.state == "ok" and fix.floor_lines >= 2  # the table top is floor-like too
    assert abs(fix.height_m - 1.5) < 0.01  # not 0.75 above the table


def test_table_only_in_view_is_flagged_as_a_jump(geometry: WorldGeometry) -> None:
    """Just above the table the floor is hidden: the table top is taken for the floor, which the
    paper's method cannot tell; the jump from the previous fix is reported."""
    rng = np.random.default_rng(5)
    est = HeightEstimator(MOUNT_POSITION, MOUNT_RPY)
    assert est.update(vertical_scan(geometry, 6.5, 1.6, 0.9, rng)).state == "ok"
    fix = est.update(vertical_scan(geometry, *TABLE_XY, 0.9, rng))
    assert fix.state == "degraded" and "jumped" in fix.reason
    assert fix.height_m == pytest.approx(0.9 - 0.75, abs=0.01)


def test_a_far_noisy_floor_line_a_few_degrees_off_does_not_lever_the_height() -> None:
    """The only floor line 2.3-3.0 m ahead, 1 m down, its 25 points 3 cm apart from a level floor
    and fitted 5 deg off (as a recorded realistic-arena scan's, with mixed pixels where the floor
    meets a wall): the paper's perpendicular distance would put the floor 1.23 m down; levelled
    by the attitude (0.3 deg) the fit's direction weighs little and the height stays within 2 cm."""
    u = np.linspace(2.3, 3.0, 25)
    scatter = np.where(np.arange(25) % 2 == 0, 0.03, -0.03)
    v = 1.0 - (u - u.mean()) * math.tan(math.radians(5.0)) + scatter  # sensor y = body down
    fix = HeightEstimator().update(np.column_stack((u, v)))
    assert fix.height_m == pytest.approx(1.0, abs=0.02)
    assert abs(fix.height_m - 1.0) < 3.0 * math.sqrt(fix.variance) < 0.05


def test_with_the_fused_height_known_a_table_top_alone_is_no_floor(geometry: WorldGeometry) -> None:
    """The same view with the fused height given (the IMU carried it since the last fixes): a
    surface 0.75 m above the expected floor is refused (lost: the floor is not in view) instead of
    becoming a confident 0.15 m height; the floor, or a floor lower than expected, is taken."""
    rng = np.random.default_rng(5)
    est = HeightEstimator(MOUNT_POSITION, MOUNT_RPY)
    fix = est.update(vertical_scan(geometry, *TABLE_XY, 0.9, rng), expected=(0.9, 0.03))
    assert fix.state == "lost" and "table top" in fix.reason and fix.floor_lines >= 1
    assert_finite(fix)
    # The table in view beside the floor, and a floor lower than the (drifted) expectation.
    assert est.update(vertical_scan(geometry, *TABLE_XY, 1.5, rng), expected=(1.5, 0.03)).state == "ok"
    low = est.update(vertical_scan(geometry, 2.5, 2.0, 1.0, rng), expected=(0.6, 0.03))
    assert low.state != "lost" and low.height_m == pytest.approx(1.0, abs=0.01)
    # Unsure of its own height (sigma 0.3 m), the fusion's expectation refuses nothing 0.75 m off.
    assert est.update(vertical_scan(geometry, *TABLE_XY, 0.9, rng), expected=(0.9, 0.3)).state != "lost"


def test_a_table_top_seen_beside_the_floor_stands_in_for_it_with_its_step(geometry: WorldGeometry) -> None:
    """Seen beside the floor on three scans (the fused height known), the table's step (0.75 m
    above the floor) is remembered; with the floor hidden its top then gives a degraded fix of the
    height above the floor, not a lost one, nor the 0.15 m above the table."""
    rng = np.random.default_rng(6)
    est = HeightEstimator(MOUNT_POSITION, MOUNT_RPY)
    for _ in range(3):
        assert est.update(vertical_scan(geometry, 6.5, 1.6, 0.9, rng), expected=(0.9, 0.01)).state != "lost"
    fix = est.update(vertical_scan(geometry, *TABLE_XY, 0.9, rng), expected=(0.9, 0.03))
    assert fix.state == "degraded" and "stands in" in fix.reason
    assert fix.height_m == pytest.approx(0.9, abs=0.02) and 0.0 < fix.variance < 0.02 ** 2
    # A surface that matches no remembered step stays refused: the table top 0.3 m below, expected 1.35 m up.
    assert est.update(vertical_scan(geometry, *TABLE_XY, 1.05, rng), expected=(1.35, 0.03)).state == "lost"


def profile_scan(surfaces: list[tuple[float, ...]]) -> np.ndarray:
    """(N, 2) sensor-plane points of a URG-04LX (scan plane = body x-z, level, no noise) over
    ``surfaces`` (depth below the scanner m, from u, to u m ahead[, rising ahead by degrees about
    its middle; level if not given]): each beam's nearest hit, NaN where it hits none."""
    c, s = np.cos(URG04LX_ANGLES), np.sin(URG04LX_ANGLES)  # sensor y = body down
    r = np.full(URG04LX_ANGLES.size, np.inf)
    for depth, u0, u1, *rise_deg in surfaces:
        slope = -math.tan(math.radians(rise_deg[0])) if rise_deg else 0.0  # depth change per metre ahead
        with np.errstate(divide="ignore", invalid="ignore"):  # v = depth + slope (u - middle) on it
            t = (depth - slope * (u0 + u1) / 2) / (s - slope * c)
        u = t * c
        hit = (s > 1e-6) & (u >= u0) & (u <= u1)
        r = np.where(hit & (t < r), t, r)
    r = np.where(np.isfinite(r), r, np.nan)
    return np.column_stack((r * c, r * s))


def test_unsure_of_its_height_a_remembered_table_alone_is_no_floor_but_the_floor_elsewhere_is(
        geometry: WorldGeometry) -> None:
    """With the fused height unsure (sigma 0.3 m: 0.75 m off is within its 3 sigma), a table top
    alone in view where a table was remembered may be the floor or that table: no fix (lost), where
    before it became a confident 0.15 m height. The open floor (a line longer than the table ever
    gave), the floor beside the table, and with nothing known of the height (sigma 1 km) a short
    floor line by a wall far from the table are still taken; the last is refused only when where
    the vehicle is is unknown too."""
    rng = np.random.default_rng(7)
    est = HeightEstimator(MOUNT_POSITION, MOUNT_RPY)
    for _ in range(3):
        beside = est.update(vertical_scan(geometry, 6.5, 1.6, 0.9, rng), expected=(0.9, 0.01), pose=(6.5, 1.6, 0.0))
        assert beside.state != "lost"
    alone = est.update(vertical_scan(geometry, *TABLE_XY, 0.9, rng), expected=(0.9, 0.3), pose=(*TABLE_XY, 0.0))
    assert alone.state == "lost" and "may be the floor or the surface seen 0.75 m above it" in alone.reason
    assert_finite(alone)
    open_floor = est.update(vertical_scan(geometry, 2.5, 2.0, 1.0, rng), expected=(1.0, 0.3), pose=(2.5, 2.0, 0.0))
    assert open_floor.state != "lost" and open_floor.height_m == pytest.approx(1.0, abs=0.01)
    beside = est.update(vertical_scan(geometry, 6.5, 1.6, 0.9, rng), expected=(0.9, 0.3), pose=(6.5, 1.6, 0.0))
    assert beside.state != "lost" and beside.height_m == pytest.approx(0.9, abs=0.01)
    by_a_wall = vertical_scan(geometry, 4.8, 4.8, 1.0, rng)  # a 0.7 m floor line, 3 m from the table
    far = est.update(by_a_wall, expected=(0.0, 1000.0), pose=(4.8, 4.8, 0.0))
    assert far.state != "lost" and far.height_m == pytest.approx(1.0, abs=0.01)
    assert est.update(by_a_wall, expected=(0.0, 1000.0)).state == "lost"


def test_unsure_of_its_height_the_floor_in_two_pieces_is_as_long_as_its_longest() -> None:
    """A table (0.75 m above the floor, 1 m of it seen) remembered; the fused height unsure (sigma
    0.3 m). The floor in view as 0.8 m under the vehicle and 3 m further ahead: the piece under the
    vehicle is the fix (the least variance), but that the surface is longer than the table ever
    was, the evidence that it is the floor, is the longer piece's."""
    est = HeightEstimator()
    for _ in range(3):
        assert est.update(profile_scan([(0.25, 1.0, 2.0), (1.0, -0.5, 4.0)]), expected=(1.0, 0.01)).state != "lost"
    fix = est.update(profile_scan([(1.0, -0.4, 0.4), (1.0, 1.0, 4.0)]), expected=(1.0, 0.3))
    assert fix.state != "lost", fix.reason
    assert fix.height_m == pytest.approx(1.0, abs=0.005)


def test_a_hidden_floor_stands_in_with_the_remembered_step_at_that_place() -> None:
    """Two tables at about the same height in two places (0.75 m above the floor here, 0.70 m ten
    metres east) are two steps; the floor hidden at the first, its step alone stands in, the other
    being elsewhere (without the pose both would match: no fix)."""
    est = HeightEstimator()
    floor = (1.0, -0.5, 4.0)
    for table, east in (((0.25, 1.0, 2.0), 0.0), ((0.30, 1.0, 2.0), 10.0)):
        for _ in range(3):
            assert est.update(profile_scan([table, floor]), expected=(1.0, 0.01), pose=(0.0, east, 0.0)).state != "lost"
    hidden = profile_scan([(0.26, 0.5, 2.5)])
    fix = est.update(hidden, expected=(1.0, 0.03), pose=(0.0, 0.0, 0.0))
    assert fix.state == "degraded" and fix.height_m == pytest.approx(1.01, abs=0.01)
    assert est.update(hidden, expected=(1.0, 0.03)).state == "lost"


def test_a_hidden_floor_matching_two_remembered_steps_gives_no_fix() -> None:
    """Two tables seen beside the floor (0.75 and 0.70 m above it) are two remembered steps; a
    surface alone in view that either could be (0.73 m above the expected floor, the fused height
    known to 3 cm) gives no fix, while one that only the first matches (known to 1 cm) stands in."""
    est = HeightEstimator()
    floor = (1.0, -0.5, 4.0)
    for table in ((0.25, 1.0, 2.0), (0.30, 1.0, 2.0)):
        for _ in range(3):
            assert est.update(profile_scan([table, floor]), expected=(1.0, 0.01)).state != "lost"
    hidden = profile_scan([(0.27, -10.0, 10.0)])
    ambiguous = est.update(hidden, expected=(1.0, 0.03))
    assert ambiguous.state == "lost" and "more than one remembered surface" in ambiguous.reason
    one = est.update(profile_scan([(0.25, -10.0, 10.0)]), expected=(1.0, 0.01))
    assert one.state == "degraded" and one.height_m == pytest.approx(1.0, abs=0.01)


def test_exact_sightings_of_a_step_keep_it_finite_and_standing_in() -> None:
    """Noise-free scans with no noise or model error declared (every variance 0): a second sighting
    of the step no longer divides by zero, and the step stands in for the hidden floor."""
    exact = LineParams(noise_m=0.0, noise_per_m=0.0, break_grazing_deg=0.0, model_floor_m=0.0)
    est = HeightEstimator(params=HeightParams(lines=exact, variance_floor_m2=0.0, attitude_sd_deg=0.0))
    for _ in range(3):
        assert est.update(profile_scan([(0.25, 1.0, 2.0), (1.0, -0.5, 4.0)]), expected=(1.0, 0.0)).state != "lost"
    fix = est.update(profile_scan([(0.25, -10.0, 10.0)]), expected=(1.0, 0.001))
    assert fix.state == "degraded" and fix.height_m == pytest.approx(1.0, abs=1e-6)
    assert math.isfinite(fix.variance)


def test_a_short_floor_line_is_a_fix_like_any_other() -> None:
    """The floor seen only 2.0-2.45 m ahead (a 0.45 m line, the rest hidden by a box under the
    vehicle reaching 1.9 m ahead): an ok fix at the true height, its variance saying how good it is,
    not a degraded one (every such scan slowed the realistic patrol's mission)."""
    fix = HeightEstimator().update(profile_scan([(1.0, 2.0, 2.45), (0.5, -0.5, 0.95)]), expected=(1.0, 0.01))
    assert fix.state == "ok" and fix.height_m == pytest.approx(1.0, abs=0.01)
    assert 0.005 ** 2 <= fix.variance < 0.02 ** 2


def test_a_floor_line_on_an_uneven_floor_carried_to_under_the_vehicle_says_how_far_it_may_be_off() -> None:
    """The floor seen only 1.5-4.0 m ahead, rising 0.3 deg there (a finished floor's 4 mm in 1 m is
    0.23 deg): its own direction carries it 14 mm off to under the vehicle; with the floor's tilt
    in the fit's variance the fix leans on the attitude too and says it may be off by that much
    (the floor taken as flat: 14 mm off at a 5 mm sigma)."""
    fix = HeightEstimator().update(profile_scan([(1.0, 1.5, 4.0, 0.3)]))
    assert fix.state == "ok"
    assert abs(fix.height_m - 1.0) < 1.5 * math.sqrt(fix.variance)
    flat = HeightEstimator(params=HeightParams(floor_tilt_sd_deg=0.0)).update(profile_scan([(1.0, 1.5, 4.0, 0.3)]))
    assert abs(flat.height_m - 1.0) > 2.5 * math.sqrt(flat.variance)  # a floor taken as flat: over-confident


def test_the_floor_under_the_vehicle_is_taken_over_a_longer_line_further_ahead() -> None:
    """Level floor under the vehicle (1.2 m of it) and 3.5 m of floor 1-4.5 m ahead rising 0.5 deg,
    both as far down at their middles: the fix is the one with the least variance, the line under
    the vehicle (the longest, carried 2.75 m, put it 12 mm off)."""
    fix = HeightEstimator().update(profile_scan([(1.0, -0.6, 0.6), (1.0, 1.0, 4.5, 0.5)]))
    assert fix.state == "ok" and fix.floor_lines == 2
    assert fix.height_m == pytest.approx(1.0, abs=0.002)


def test_no_floor_is_lost_without_nan(geometry: WorldGeometry) -> None:
    est = HeightEstimator(MOUNT_POSITION, MOUNT_RPY)
    n = URG04LX_ANGLES.size
    blind = Scan("v", 0.0, URG04LX_ANGLES, np.full(n, np.inf), np.zeros(n, dtype=bool))
    level = vertical_scan(geometry, 2.5, 2.0, 1.0, np.random.default_rng(6))
    wall_only = np.column_stack((np.full(200, 2.0), np.linspace(-1.0, 1.0, 200)))  # 2 m ahead
    for fix, why in ((est.update(blind), "no floor-like line"),
                     (est.update(level, roll=math.pi / 2), "too flat"),  # scan plane horizontal
                     (est.update(wall_only), "no floor-like line")):
        assert fix.state == "lost" and why in fix.reason
        assert_finite(fix)


def test_points_input(geometry: WorldGeometry) -> None:
    scan = vertical_scan(geometry, 2.5, 2.0, 1.0, np.random.default_rng(8))
    r = np.where(scan.valid, scan.ranges_m, np.nan)
    points = np.column_stack((r * np.cos(scan.angles_rad), r * np.sin(scan.angles_rad)))
    a = HeightEstimator(MOUNT_POSITION, MOUNT_RPY).update(scan)
    b = HeightEstimator(MOUNT_POSITION, MOUNT_RPY).update(points)
    assert a.height_m == pytest.approx(b.height_m) and a.state == b.state == "ok"
