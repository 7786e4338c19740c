"""Laser dots in the simulated camera (sitl/laser_spots.py, sitl/camera_sim.py): where the beams of the
true rig meet the floor, an obstacle or a wall, where the camera draws them (checked against
CameraCalibration.project), their size, speckle, smear and occlusion, the gain, the settings, and the
world of the laser-dot paper's Fig. 4 (config/worlds/fig4.yaml)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import yaml

from companion.calibration import CameraCalibration
from companion.config import MountConfig
from companion.laser_beams import BeamRigConfig
from companion.schema import SchemaError, load_text
from companion.world import ARUCO_DICTIONARY, Bounds, Obstacle, Wall, World, load_world
from drivers.mount import Mount
from sitl.camera_scene import check_marker_ids
from sitl.camera_sim import SimCameraSettings, SimulatedCamera
from sitl.laser_spots import LASER_BGR
from tests.conftest import REPO
from tests.test_camera_sim import DOWN, FakeTruth, Pose, pose

FISHEYE = CameraCalibration(640, 480, np.array([[220.0, 0.0, 318.5], [0.0, 221.0, 241.0], [0.0, 0.0, 1.0]]),
                            np.array([0.03, -0.01, 0.002, -0.0005]), "equidistant")  # sees dots 55 deg off the axis
CAMERA_OFFSET_M = (-0.08, 0.05, 0.03)  # body FRD: behind, right of and below the beams' origin
EMPTY = World(name="empty", wall_angle_deg=90, bounds=Bounds((-10.0, -10.0), (10.0, 10.0)), start=(0.0, 0.0, 0.0),
              walls=())
STILL = {"noise_sigma": 0.0, "laser_speckle_px": 0.0}
DOT_RADIUS_PX = 8  # the window measured around a dot's expected pixel


def laser_camera(world: World = EMPTY, calibration: CameraCalibration = FISHEYE,
                 offset_m: tuple[float, float, float] = CAMERA_OFFSET_M, **settings: object) -> SimulatedCamera:
    """A camera looking down on the vehicle, with the nominal rig unless ``laser_beams`` is given."""
    s = SimCameraSettings(**{"laser_beams": BeamRigConfig(), **STILL, **settings})  # type: ignore[arg-type]
    mount = Mount.from_config(MountConfig(position_m=offset_m, rpy_deg=DOWN))
    return SimulatedCamera("cam", s, calibration, mount, world, FakeTruth(pose((0.0, 0.0, -1.0))))


def expected_pixels(cam: SimulatedCamera, vehicle: Pose) -> np.ndarray:
    """(3, 2) pixels where the calibration projects the beams' true hits (NaN: no hit)."""
    points, _ = cam.laser_hits(vehicle)
    rotation, origin = cam.camera_pose(vehicle)
    return cam.calibration.project((points - origin) @ rotation)


def dot_moments(image: np.ndarray, pixel: np.ndarray, radius: int = DOT_RADIUS_PX,
                ) -> tuple[np.ndarray, np.ndarray, float]:
    """(centroid (u, v), covariance (2, 2) px^2, total) of the laser light R - max(G, B) within
    ``radius`` px of ``pixel`` in a BGR ``image``."""
    u0, v0 = (int(round(c)) for c in pixel)
    window = slice(v0 - radius, v0 + radius + 1), slice(u0 - radius, u0 + radius + 1)
    weight = np.clip(laser_light(image[window]), 0, None).astype(float)
    v, u = np.mgrid[window]
    total = weight.sum()
    if total == 0:
        return np.full(2, np.nan), np.full((2, 2), np.nan), 0.0
    centroid = np.array([(weight * u).sum(), (weight * v).sum()]) / total
    d = np.stack((u - centroid[0], v - centroid[1]))
    covariance = np.einsum("iab,jab,ab->ij", d, d, weight) / total
    return centroid, covariance, float(total)


def laser_light(image: np.ndarray) -> np.ndarray:
    """R - max(G, B) of a BGR image, as int."""
    image = image.astype(int)
    return image[..., 2] - np.maximum(image[..., 0], image[..., 1])


# -- where the dots are ---------------------------------------------------------------------------


@pytest.mark.parametrize("height_m", [1.0, 2.0])
def test_each_dot_is_drawn_where_the_calibration_projects_the_beams_floor_hit(height_m: float) -> None:
    cam = laser_camera()
    vehicle = pose((0.4, -0.3, -height_m), (3.0, -4.0, 30.0))
    image = cam.render(0.0, vehicle).image
    points, lengths = cam.laser_hits(vehicle)
    assert image.shape == (480, 640, 3) and image.dtype == np.uint8
    assert points[:, 2] == pytest.approx(np.zeros(3), abs=1e-6)  # on the floor
    assert np.all((lengths > height_m) & (lengths < 2 * height_m))
    for pixel in expected_pixels(cam, vehicle):
        centroid, _, total = dot_moments(image, pixel)
        assert total > 0 and np.linalg.norm(centroid - pixel) < 0.2, (centroid, pixel)


def test_level_over_the_floor_the_nominal_beams_are_height_times_sqrt3_long() -> None:
    _, lengths = laser_camera().laser_hits(pose((1.0, 2.0, -1.5)))
    assert lengths == pytest.approx(np.full(3, 1.5 * math.sqrt(3.0)), rel=1e-6)  # 54.74 deg off the vertical


def test_a_dot_on_an_obstacle_top_is_drawn_where_the_top_meets_the_beam() -> None:
    table = Obstacle("table", (0.5, -0.6), (1.6, 0.6), 0.7)  # under beam 0 (forward), not under 1 and 2
    world = World(name="table", wall_angle_deg=90, bounds=Bounds((-5.0, -5.0), (5.0, 5.0)), start=(-1.0, 0.0, 0.0),
                  walls=(), obstacles=(table,))
    cam = laser_camera(world)
    vehicle = pose((0.0, 0.0, -1.5))
    points, lengths = cam.laser_hits(vehicle)
    assert points[0, 2] == pytest.approx(-0.7, abs=1e-6) and table.covers(*points[0, :2])
    assert lengths[0] == pytest.approx(0.8 * math.sqrt(3.0), rel=1e-6)
    assert points[1:, 2] == pytest.approx([0.0, 0.0], abs=1e-6)
    image = cam.render(0.0, vehicle).image
    for pixel in expected_pixels(cam, vehicle):
        assert np.linalg.norm(dot_moments(image, pixel)[0] - pixel) < 0.2


def test_a_beam_meets_the_side_of_a_box_or_a_wall_before_the_floor_and_nothing_when_it_points_up() -> None:
    world = World(name="walls", wall_angle_deg=90, bounds=Bounds((-5.0, -5.0), (5.0, 5.0)), start=(0.0, 0.0, 0.0),
                  walls=(Wall((1.0, -5.0), (1.0, 5.0), 3.0),),
                  obstacles=(Obstacle("crate", (-2.0, -0.4), (-0.5, 0.4), 2.0),))
    cam = laser_camera(world)
    points, _ = cam.laser_hits(pose((0.0, 0.0, -1.5), (0.0, 0.0, 0.0)))
    assert points[0, 0] == pytest.approx(1.0, abs=1e-6) and -1.5 < points[0, 2] < 0.0  # on the wall, above the floor
    assert points[1:, 2] == pytest.approx([0.0, 0.0], abs=1e-6)  # beams 1 and 2 pass beside the crate
    points, _ = cam.laser_hits(pose((0.0, 0.0, -1.5), (0.0, 0.0, 180.0)))  # turned: beam 0 towards the crate
    assert points[0, 0] == pytest.approx(-0.5, abs=1e-6) and points[0, 2] < 0.0  # its north side, above the floor
    _, lengths = cam.laser_hits(pose((-4.0, 0.0, -1.5), (0.0, 180.0, 0.0)))  # upside down in the open: no dots
    assert np.isnan(lengths).all()


def test_a_dot_hidden_from_the_camera_by_an_obstacle_is_not_drawn() -> None:
    rig = BeamRigConfig(origins_m=[(0.5, 0.0, 0.0)] * 3,  # beam 0 straight down 0.5 m ahead of the camera
                        directions=[(0.0, 0.0, 1.0), (0.0, 1.0, 1.0), (0.0, -1.0, 1.0)])
    screen = Obstacle("screen", (0.2, -0.1), (0.3, 0.1), 0.8)  # between the camera and beam 0's dot, beside the beam
    world = World(name="screen", wall_angle_deg=90, bounds=Bounds((-5.0, -5.0), (5.0, 5.0)), start=(-1.0, 0.0, 0.0),
                  walls=(), obstacles=(screen,))
    vehicle = pose((0.0, 0.0, -1.0))
    hidden, seen = (laser_camera(w, offset_m=(0.0, 0.0, 0.0), laser_beams=rig) for w in (world, EMPTY))
    assert hidden.laser_hits(vehicle)[0][0] == pytest.approx([0.5, 0.0, 0.0], abs=1e-6)  # on the floor either way
    pixel = expected_pixels(hidden, vehicle)[0]
    assert dot_moments(seen.render(0.0, vehicle).image, pixel)[2] > 0
    assert dot_moments(hidden.render(0.0, vehicle).image, pixel)[2] == 0


# -- what the dots look like ----------------------------------------------------------------------


def test_a_dot_is_as_large_as_the_beam_at_that_range_stretched_on_an_oblique_surface_plus_the_bloom() -> None:
    pinhole = SimCameraSettings().intrinsics()  # 640 x 480, f = 320 px, looking straight down on the floor
    spot_m, bloom_px, height_m, tilt = 0.05, 1.5, 1.0, math.radians(30.0)
    down, east = (0.0, 0.0, 1.0), (0.0, math.sin(tilt), math.cos(tilt))  # body = NED here (level, facing north)
    rig = BeamRigConfig(origins_m=[(0.0, 0.0, 0.0)] * 3, directions=[down, east, (0.0, -0.5, 1.0)])
    cam = laser_camera(calibration=pinhole, offset_m=(0.0, 0.0, 0.0), laser_beams=rig, laser_spot_m=spot_m,
                       laser_bloom_px=bloom_px, gain=0.5, laser_peak=200.0)  # a darker scene: no saturation
    vehicle = pose((0.0, 0.0, -height_m))
    image = cam.render(0.0, vehicle).image
    pixels = expected_pixels(cam, vehicle)
    across = (spot_m / 4.0) * 320.0 / height_m  # px: a floor parallel to the image plane is f / height px per m
    blur = bloom_px ** 2
    _, covariance, _ = dot_moments(image, pixels[0], radius=20)  # straight down: round
    assert covariance == pytest.approx(np.diag([across ** 2 + blur] * 2), rel=0.05, abs=0.2)
    _, covariance, _ = dot_moments(image, pixels[1], radius=20)  # 30 deg off: stretched along its trace (east, u)
    assert covariance == pytest.approx(np.diag([(across / math.cos(tilt)) ** 2 + blur, across ** 2 + blur]),
                                       rel=0.05, abs=0.2)


def test_a_dot_saturates_red_and_adds_a_little_green_and_blue() -> None:
    vehicle = pose((0.0, 0.0, -0.5))
    cam = laser_camera()
    image = cam.render(0.0, vehicle).image.astype(int)
    added = image - laser_camera(laser_peak=0.0).render(0.0, vehicle).image
    for pixel in expected_pixels(cam, vehicle):
        u, v = (int(round(c)) for c in pixel)
        window = added[v - DOT_RADIUS_PX:v + DOT_RADIUS_PX + 1, u - DOT_RADIUS_PX:u + DOT_RADIUS_PX + 1]
        assert image[v, u, 2] == 255 and image[v, u, 1] < 255  # the core saturates in red only (laser_peak 400)
        blue, green, _ = window.reshape(-1, 3).sum(axis=0)
        assert green / blue == pytest.approx(LASER_BGR[1] / LASER_BGR[0], rel=0.1)


def test_speckle_moves_each_dot_by_laser_speckle_px_per_frame_and_the_seed_repeats_it() -> None:
    small = FISHEYE.scaled(320, 240)
    cam = laser_camera(calibration=small, laser_speckle_px=0.5, seed=3)
    vehicle = pose((0.0, 0.0, -1.0))
    pixels = expected_pixels(cam, vehicle)
    errors = np.array([[dot_moments(cam.render(0.0, vehicle, sequence=k).image, p)[0] - p for p in pixels]
                       for k in range(25)])
    assert errors.std() == pytest.approx(0.5, rel=0.2) and abs(errors.mean()) < 0.15
    again = cam.render(0.0, vehicle, sequence=4).image
    for seed, same in ((3, True), (4, False)):
        other = laser_camera(calibration=small, laser_speckle_px=0.5, seed=seed).render(0.0, vehicle, sequence=4)
        assert np.array_equal(again, other.image) == same


def test_with_motion_blur_a_dot_smears_between_its_places_at_the_start_and_end_of_the_exposure() -> None:
    # the camera 0.3 m east of the beams' origin: as the vehicle drops, the dots move in the image by parallax
    kwargs = dict(offset_m=(0.0, 0.3, 0.0), exposure_s=0.02, fps=20)
    start, end = pose((0.0, 0.0, -1.0)), pose((0.0, 0.0, -0.8))
    cam = laser_camera(motion_blur=True, **kwargs)
    image = cam.render(0.0, start, end).image
    samples = len(cam.exposure_views(start, end))  # the heights the renderer averages over
    places = np.array([expected_pixels(cam, pose((0.0, 0.0, -1.0 + 0.2 * (k + 0.5) / samples)))
                       for k in range(samples)])
    streak = places[-1, 0] - places[0, 0]
    assert samples > 8 and np.linalg.norm(streak) > 5
    centroid, covariance, _ = dot_moments(image, places[:, 0].mean(axis=0), radius=12)
    assert np.linalg.norm(centroid - places[:, 0].mean(axis=0)) < 0.3
    still = dot_moments(laser_camera(**kwargs).render(0.0, start).image, places[0, 0])[1]
    along = streak / np.linalg.norm(streak)
    assert along @ covariance @ along > along @ still @ along + 0.8 * (streak @ streak) / 12  # plus a box of the streak


# -- gain, compatibility, settings -----------------------------------------------------------------


def test_a_high_gain_saturates_the_camera_and_drowns_the_dots() -> None:
    vehicle = pose((0.0, 0.0, -1.0))
    cam = laser_camera(gain=10.0)
    image = cam.render(0.0, vehicle).image
    assert np.mean(image[cam.rays.reached] == 255) > 0.999 and np.all(laser_light(image) == 0)  # but the darkest texels
    half = laser_camera(gain=0.5, laser_peak=0.0).render(0.0, vehicle).image.astype(int)
    full = laser_camera(laser_peak=0.0).render(0.0, vehicle).image.astype(int)
    assert np.abs(2 * half - full).max() <= 1  # rounding


def test_without_laser_beams_the_image_is_the_grey_scene_and_the_dots_add_only_red_light_around_them() -> None:
    vehicle = pose((0.2, 0.1, -1.0), (2.0, 1.0, 10.0))
    grey = laser_camera(laser_beams=None).render(0.0, vehicle).image
    dark = laser_camera(laser_peak=0.0).render(0.0, vehicle).image
    lit = laser_camera().render(0.0, vehicle).image
    assert grey.shape == (480, 640) and grey.dtype == np.uint8
    assert all(np.array_equal(dark[..., c], grey) for c in range(3))
    changed = np.any(lit != dark, axis=2)
    pixels = expected_pixels(laser_camera(), vehicle)
    near = np.zeros_like(changed)
    for u, v in np.rint(pixels).astype(int):
        near[v - DOT_RADIUS_PX:v + DOT_RADIUS_PX + 1, u - DOT_RADIUS_PX:u + DOT_RADIUS_PX + 1] = True
    assert changed.any() and not (changed & ~near).any()
    with pytest.raises(ValueError, match="laser_beams"):
        laser_camera(laser_beams=None).laser_hits(vehicle)


def test_laser_settings_are_checked_by_the_schema() -> None:
    s = load_text("{laser_beams: {angle_deg: 89, azimuth_deg: 5}, laser_spot_m: 0.004, laser_peak: 900, "
                  "laser_speckle_px: 0.2, laser_bloom_px: 1.5, gain: 2.5}", SimCameraSettings)
    assert s.laser_beams is not None and s.laser_beams.rig().angle_deg(0, 1) == pytest.approx(89.0)
    assert (s.laser_spot_m, s.laser_peak, s.laser_speckle_px, s.laser_bloom_px, s.gain) == (0.004, 900, 0.2, 1.5, 2.5)
    defaults = SimCameraSettings()
    assert defaults.laser_beams is None and defaults.gain == 1.0
    for bad in ({"laser_beams": {"origin_m": [0, 0, 9]}}, {"laser_beams": {"angle_deg": 130}},
                {"laser_spot_m": 0}, {"laser_speckle_px": -1}, {"gain": 0}, {"laser_beams": {"beams": 3}}):
        with pytest.raises(SchemaError):
            load_text(yaml.safe_dump(bad), SimCameraSettings)


# -- the world of the paper's Fig. 4 -------------------------------------------------------------


def test_the_fig4_world_loads_and_its_two_marker_rows_render_and_are_detected() -> None:
    world = check_marker_ids(load_world(REPO / "config" / "worlds" / "fig4.yaml"))
    xs = {y: sorted(m.position[0] for m in world.floor_markers if m.position[1] == y) for y in (-0.5, 2.0)}
    assert [len(v) for v in xs.values()] == [45, 45] and sum(map(len, xs.values())) == len(world.floor_markers)
    assert all(np.allclose(np.diff(v), 1.5) for v in xs.values()) and xs[2.0][0] - xs[-0.5][0] == 0.75
    assert len({m.id for m in world.floor_markers}) == 90 and max(m.id for m in world.floor_markers) < 250
    assert xs[-0.5][0] < 0.0 and min(xs[2.0][-1], xs[-0.5][-1]) > 62.0  # the whole flight, x 0..62 m
    assert world.start == (0.0, 0.0, 0.0) and all(m.size_m == 0.3 and m.yaw_deg == 0.0 for m in world.floor_markers)
    assert all(world.bounds.contains(x, y, margin=3.0) for x in (0.0, 62.0) for y in (0.0, 1.5))  # walls far away
    cam = laser_camera(world, calibration=SimCameraSettings(hfov_deg=120).intrinsics())  # both rows in view
    image = cam.render(0.0, pose((30.0, 1.5, -1.63))).image  # after the sidestep, at the second height
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(ARUCO_DICTIONARY))
    _, ids, _ = detector.detectMarkers(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))
    expected = {m.id for m in world.floor_markers if abs(m.position[0] - 30.0) < 1.6}
    assert len(expected) == 5 and expected <= set(ids.ravel().tolist())
