"""The simulated camera (sitl/camera_sim.py, sitl/camera_scene.py): geometry checked by detecting its
ArUco floor markers with OpenCV and projecting their world corners with cv2.projectPoints, noise,
motion blur, seeds, walls, timing and the plugin registration."""

from __future__ import annotations

import asyncio
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from companion.calibration import CameraCalibration
from companion.config import MountConfig, load_config
from companion.frames import quat_from_euler, rotation_from_euler, rotation_from_quat
from companion.health import Health
from companion.schema import SchemaError, load_text
from companion.sensors import SensorContext, build_driver, check_sensor_files
from companion.world import ARUCO_DICTIONARY, Bounds, FloorMarker, Opening, Wall, World
from drivers.mount import OPTICAL_TO_SENSOR, Mount
from sitl.camera_scene import MARKER_BLACK, PAPER_WHITE, SKY_GREY, check_marker_ids
from sitl.camera_sim import SimCameraSettings, SimulatedCamera

DISTORTION = (-0.25, 0.07, 0.001, -0.0015, -0.01)  # plumb_bob k1 k2 p1 p2 k3: a cheap wide-angle lens
DOWN = (0.0, -90.0, 0.0)  # mount rpy_deg of a camera looking down, image top towards the body's front
# v_sensor = M v_optical, written out here rather than taken from the module under test


@dataclass(frozen=True)
class Pose:
    """A truth sample: NED position (m), attitude [w, x, y, z] body FRD -> NED."""

    position_ned: np.ndarray
    quat: np.ndarray


def pose(position: tuple[float, float, float], rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Pose:
    return Pose(np.array(position, dtype=float), quat_from_euler(*np.radians(rpy_deg)))


class FakeTruth:
    """TruthSource-like: a fixed pose, known from daemon time ``available_from`` on."""

    def __init__(self, sample: Pose, available_from: float = -math.inf) -> None:
        self.sample = sample
        self.available_from = available_from

    def at(self, t: float) -> Pose | None:
        return self.sample if t >= self.available_from else None


MARKERS = (FloorMarker(7, (0.0, 0.0), 0.3, 25.0), FloorMarker(3, (0.8, 0.5), 0.3, -70.0),
           FloorMarker(11, (1.4, -0.6), 0.4, 180.0))
FLOOR_WORLD = World(name="markers", wall_angle_deg=90, bounds=Bounds((-10.0, -10.0), (10.0, 10.0)),
                    start=(0.0, 0.0, 0.0), walls=(), floor_markers=MARKERS)


def camera(world: World = FLOOR_WORLD, rpy_deg: tuple[float, float, float] = DOWN, truth: FakeTruth | None = None,
           **settings: object) -> SimulatedCamera:
    s = SimCameraSettings(**{"noise_sigma": 0.0, **settings})  # type: ignore[arg-type]
    return SimulatedCamera("cam", s, s.intrinsics(), Mount.from_config(MountConfig(rpy_deg=rpy_deg)), world,
                           truth or FakeTruth(pose((0.0, 0.0, -2.0))))


def marker_corners_ned(marker: FloorMarker) -> np.ndarray:
    """(4, 3) corners of the black square in ArUco's order (top-left, top-right, bottom-right,
    bottom-left as printed): the top edge faces yaw_deg, the right side yaw_deg + 90 seen from above."""
    yaw = math.radians(marker.yaw_deg)
    top, right = np.array([math.cos(yaw), math.sin(yaw), 0.0]), np.array([-math.sin(yaw), math.cos(yaw), 0.0])
    centre, h = np.array([*marker.position, 0.0]), marker.size_m / 2
    return np.array([centre + h * (a * top + b * right) for a, b in ((1, -1), (1, 1), (-1, 1), (-1, -1))])


def corner_errors(image: np.ndarray, world_from_optical: np.ndarray, centre: np.ndarray,
                  calibration: CameraCalibration) -> dict[int, float]:
    """Mean distance (px) per detected marker between ArUco's corners and cv2.projectPoints of its
    world corners through the camera pose (rotation optical -> NED, centre NED m)."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(ARUCO_DICTIONARY), params)
    corners, ids, _ = detector.detectMarkers(image)
    rvec = cv2.Rodrigues(world_from_optical.T)[0]
    tvec = -world_from_optical.T @ centre
    errors = {}
    for found, marker_id in zip(corners, [] if ids is None else ids.ravel()):
        points = marker_corners_ned(next(m for m in MARKERS if m.id == marker_id))
        if calibration.model == "equidistant":
            expected, _ = cv2.fisheye.projectPoints(points[:, None, :], rvec, tvec, calibration.K, calibration.D)
        else:
            expected, _ = cv2.projectPoints(points, rvec, tvec, calibration.K, calibration.D)
        errors[int(marker_id)] = float(np.linalg.norm(found.reshape(4, 2) - expected.reshape(4, 2), axis=1).mean())
    return errors


# -- geometry ---------------------------------------------------------------------------------


def test_markers_seen_from_2m_straight_down_land_on_the_pinhole_model_with_distortion() -> None:
    cam = camera(distortion=DISTORTION)
    frame = cam.render(0.0, pose((0.1, 0.05, -2.0)))
    # looking down with the vehicle facing north: image right = east, image down = south, optical axis down
    world_from_optical = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    errors = corner_errors(frame.image, world_from_optical, np.array([0.1, 0.05, -2.0]), cam.calibration)
    assert sorted(errors) == [3, 7, 11]
    assert max(errors.values()) < 0.5, errors


def test_markers_in_a_tilted_view_land_on_the_pinhole_model_with_distortion() -> None:
    mount_rpy, vehicle = (0.0, -60.0, 0.0), pose((-0.8, -0.4, -1.5), (5.7, -2.9, 34.4))
    cam = camera(rpy_deg=mount_rpy, distortion=DISTORTION)
    frame = cam.render(0.0, vehicle)
    world_from_optical = (rotation_from_quat(vehicle.quat) @ rotation_from_euler(*np.radians(mount_rpy))
                          @ OPTICAL_TO_SENSOR)
    errors = corner_errors(frame.image, world_from_optical, vehicle.position_ned, cam.calibration)
    assert sorted(errors) == [3, 7, 11]
    assert max(errors.values()) < 0.5, errors


def test_markers_through_a_fisheye_land_on_opencvs_fisheye_model() -> None:
    calibration = CameraCalibration(640, 480, np.array([[240.0, 0.0, 321.0], [0.0, 241.0, 238.5], [0.0, 0.0, 1.0]]),
                                    np.array([0.04, -0.01, 0.002, -0.0005]), "equidistant")
    s = SimCameraSettings(noise_sigma=0.0)
    vehicle = pose((0.3, 0.1, -1.2), (0.0, 0.0, -15.0))
    cam = SimulatedCamera("cam", s, calibration, Mount.from_config(MountConfig(rpy_deg=DOWN)), FLOOR_WORLD,
                          FakeTruth(vehicle))
    frame = cam.render(0.0, vehicle)
    world_from_optical = rotation_from_quat(vehicle.quat) @ rotation_from_euler(*np.radians(DOWN)) @ OPTICAL_TO_SENSOR
    errors = corner_errors(frame.image, world_from_optical, vehicle.position_ned, calibration)
    assert sorted(errors) == [3, 7, 11]
    assert max(errors.values()) < 0.5, errors


def test_every_pixel_ray_reprojects_onto_its_pixel_and_pixels_beyond_the_lens_fold_are_black() -> None:
    cam = camera(width=160, height=120, distortion=DISTORTION)
    rays, calibration = cam.rays, cam.calibration
    v, u = np.nonzero(rays.reached)
    points = np.column_stack((rays.x[v, u], rays.y[v, u], np.ones(len(u))))
    pixels, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), calibration.K, calibration.D)
    assert np.abs(pixels.reshape(-1, 2) - np.column_stack((u, v))).max() < 1e-3
    assert rays.reached[60, 80] and not rays.reached[0, 0]  # this lens folds back before the image corners
    image = cam.render(0.0, pose((0.0, 0.0, -2.0))).image
    assert np.all(image[~rays.reached] == 0) and np.all(image[rays.reached] > 0)


def test_a_wall_hides_what_is_behind_it_except_through_its_door() -> None:
    world = World(name="wall", wall_angle_deg=90, bounds=Bounds((-5.0, -5.0), (5.0, 5.0)), start=(0.0, 0.0, 0.0),
                  walls=(Wall((2.0, -3.0), (2.0, 3.0), 2.5),),
                  openings=(Opening("door", "door", (2.0, 1.0), 1.0, 0.0, 2.0),))
    cam = camera(world, rpy_deg=(0.0, 0.0, 0.0), width=160, height=120, hfov_deg=60)
    image = cam.render(0.0, pose((0.0, 0.0, -1.0))).image  # 1 m up, 2 m south of the wall, facing it (north)
    wall = 110  # the grey of a wall running east-west (110 + 50 |cos direction|)
    f, cx = cam.calibration.K[0, 0], cam.calibration.K[0, 2]
    door_u = round(cx + f * 1.0 / 2.0)  # the door's centre: 1 m east, 2 m ahead
    assert image[60, 80] == wall  # the optical axis meets the wall 0.5 m west of the door
    assert np.all(image[0:120, 40] == wall)  # beside the door: wall down to where the floor in front shows
    assert np.all(image[10:50, door_u] == int(SKY_GREY))  # through the door, above the horizon: nothing
    assert image[75:115, door_u].std() > 5  # through the door, below the horizon: the floor beyond


# -- image formation ----------------------------------------------------------------------------


def test_noise_adds_independent_gaussian_grey_levels_of_noise_sigma() -> None:
    clean = camera(width=320, height=240).render(0.0, pose((0.0, 0.0, -2.0))).image.astype(float)
    noisy = camera(width=320, height=240, noise_sigma=4.0).render(0.0, pose((0.0, 0.0, -2.0))).image.astype(float)
    unclipped = (clean > 20) & (clean < 235)
    difference = (noisy - clean)[unclipped]
    assert abs(difference.mean()) < 0.05
    assert difference.std() == pytest.approx(math.sqrt(4.0 ** 2 + 1 / 12), rel=0.03)  # plus rounding
    neighbours = np.corrcoef((noisy - clean)[:, :-1].ravel(), (noisy - clean)[:, 1:].ravel())[0, 1]
    assert abs(neighbours) < 0.02


def test_motion_blur_smears_along_the_image_motion_by_speed_times_exposure() -> None:
    # 2 m up, looking down (f = 160 px), flying north at 8 m/s with a 10 ms exposure: 8 cm, 6.4 px up the image
    kwargs = dict(width=320, height=240, hfov_deg=90, exposure_s=0.01, fps=20)
    blurred_cam = camera(motion_blur=True, **kwargs)
    start, end = pose((-0.04, 0.0, -2.0)), pose((0.04, 0.0, -2.0))
    blurred = blurred_cam.render(0.0, start, end).image.astype(np.float32)
    still = camera(**kwargs).render(0.0, pose((0.0, 0.0, -2.0))).image.astype(np.float32)
    length = 0.08 * blurred_cam.calibration.K[1, 1] / 2.0  # pixels
    assert length == pytest.approx(6.4, rel=1e-6)

    def box(axis: int) -> np.ndarray:
        half = length / 2
        taps = np.arange(-math.ceil(half), math.ceil(half) + 1)
        weights = np.clip(half + 0.5 - np.abs(taps), 0.0, 1.0)
        kernel = (weights / weights.sum()).astype(np.float32)
        return cv2.filter2D(still, -1, kernel.reshape(-1, 1) if axis == 0 else kernel.reshape(1, -1))

    inner = (slice(20, -20), slice(20, -20))
    along = np.sqrt(np.mean((blurred - box(0))[inner] ** 2))  # smeared along the image's columns (north)
    across = np.sqrt(np.mean((blurred - box(1))[inner] ** 2))
    unblurred = np.sqrt(np.mean((blurred - still)[inner] ** 2))
    assert along < 1.5 and across > 4 * along and unblurred > 4 * along, (along, across, unblurred)
    # motion_blur off: the image at the mid-exposure pose, however the vehicle moves
    assert np.array_equal(camera(**kwargs).render(0.0, pose((0.0, 0.0, -2.0))).image, still.astype(np.uint8))


def test_a_seed_gives_identical_images_and_another_seed_other_noise() -> None:
    kwargs = dict(width=160, height=120, noise_sigma=3.0)
    view = pose((0.3, -0.2, -1.5), (0.0, 0.0, 20.0))
    first = camera(seed=5, **kwargs).render(0.0, view, sequence=9).image
    assert np.array_equal(first, camera(seed=5, **kwargs).render(0.0, view, sequence=9).image)
    assert not np.array_equal(first, camera(seed=6, **kwargs).render(0.0, view, sequence=9).image)
    assert not np.array_equal(first, camera(seed=5, **kwargs).render(0.0, view, sequence=10).image)  # fresh noise
    other_floor = camera(seed=5, floor_seed=1, **kwargs).render(0.0, view, sequence=9).image
    assert np.abs(other_floor.astype(int) - first).mean() > 10


def test_markers_come_from_the_worlds_dictionary_and_an_id_beyond_it_is_refused() -> None:
    last = FloorMarker(249, (0.0, 0.0), 0.3, 40.0)  # DICT_4X4_250's last marker
    world = World(name="last", wall_angle_deg=90, bounds=Bounds((-5.0, -5.0), (5.0, 5.0)), start=(1.0, 1.0, 0.0),
                  walls=(), floor_markers=(last,))
    image = camera(world, width=320, height=240).render(0.0, pose((0.0, 0.0, -1.0))).image
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(ARUCO_DICTIONARY))
    _, ids, _ = detector.detectMarkers(image)
    assert ids is not None and ids.ravel().tolist() == [249]
    beyond = World(name="beyond", wall_angle_deg=90, bounds=world.bounds, start=world.start, walls=(),
                   floor_markers=(FloorMarker(250, (0.0, 0.0), 0.3),))
    with pytest.raises(ValueError, match=r"floor_markers\[0\]: id 250 .* DICT_4X4_250 \(ids 0-249\)"):
        check_marker_ids(beyond)


def test_markers_are_black_on_white_paper() -> None:
    image = camera(width=160, height=120, hfov_deg=20).render(0.0, pose((0.0, 0.0, -1.0))).image
    assert image.min() == MARKER_BLACK and image.max() == PAPER_WHITE  # 0.35 m of floor: all marker and paper


# -- settings, timing, registration --------------------------------------------------------------


def test_settings_are_checked_by_the_schema() -> None:
    K = SimCameraSettings().intrinsics().K  # 640 x 480, 90 degrees across
    assert K == pytest.approx(np.array([[320.0, 0.0, 319.5], [0.0, 320.0, 239.5], [0.0, 0.0, 1.0]]))
    s = load_text("{width: 320, height: 240, fx: 200, distortion: [-0.1, 0.01, 0, 0], motion_blur: true}",
                  SimCameraSettings)
    assert s.intrinsics().K[1, 1] == 200.0 and s.intrinsics().D.tolist() == [-0.1, 0.01, 0.0, 0.0] and s.motion_blur
    for bad in ({"calibration": "c.yaml", "fx": 300}, {"fx": 300, "hfov_deg": 60}, {"fy": 300},
                {"distortion": [0.1, 0.2, 0.3]}, {"distortion": [0.0] * 14}, {"fps": 100, "exposure_s": 0.02},
                {"width": 320, "cx": 400}, {"noise_sigma": -1}):
        with pytest.raises(SchemaError):
            load_text(yaml.safe_dump(bad), SimCameraSettings)


def test_frames_follow_the_grid_arrive_after_exposure_and_latency_and_wait_for_truth() -> None:
    async def run() -> tuple[list, list[float], float]:
        loop = asyncio.get_running_loop()
        truth = FakeTruth(pose((0.0, 0.0, -2.0)), available_from=math.inf)
        cam = camera(truth=truth, width=64, height=48, fps=20, exposure_s=0.01, latency_s=0.03)
        await cam.open()
        truth.available_from = loop.time() + 0.12
        frames, arrived = [], []
        for _ in range(3):
            frames.append(await cam.read())
            arrived.append(loop.time())
        await cam.close()
        return frames, arrived, truth.available_from

    frames, arrived, available_from = asyncio.run(run())
    assert frames[0].t_capture >= available_from and frames[0].sequence >= 3
    assert [f.sequence for f in frames] == list(range(frames[0].sequence, frames[0].sequence + 3))
    assert np.diff([f.t_capture for f in frames]) == pytest.approx(0.05)
    assert all(a >= f.t_capture + 0.005 + 0.03 - 1e-6 for f, a in zip(frames, arrived))
    assert all(f.exposure_s == 0.01 and f.image.shape == (48, 64) and f.image.dtype == np.uint8 for f in frames)


class _Link:
    """Stands in for the autopilot link: the truth source subscribes to it; nothing is sent."""

    def subscribe(self, name: str, handler: object) -> None:
        pass


def test_the_plugin_builds_a_camera_from_a_calibration_file(tmp_path: Path) -> None:
    (tmp_path / "cam.yaml").write_text(
        "image_width: 320\nimage_height: 240\ncamera_name: down\n"
        "camera_matrix: {rows: 3, cols: 3, data: [250, 0, 160.5, 0, 251, 119.0, 0, 0, 1]}\n"
        "distortion_model: plumb_bob\n"
        "distortion_coefficients: {rows: 1, cols: 5, data: [-0.2, 0.05, 0.0, 0.0, 0.0]}\n")
    world = Path(__file__).resolve().parents[1] / "config" / "worlds" / "arena.yaml"
    (tmp_path / "c.yaml").write_text(
        "origin: {lat: 1.2966, lon: 103.7764, alt: 10.0}\nplugins: [sitl.sim_backends]\n"
        f"mavlink: {{streams: {{sim_state: 50}}}}\nsitl: {{world: {world}}}\n"
        "sensors:\n  down:\n    kind: camera\n    backend: sim\n    mount: {rpy_deg: [0, -90, 0]}\n"
        "    settings: {calibration: cam.yaml, fps: 10}\n")
    cfg = load_config(tmp_path / "c.yaml")
    check_sensor_files(cfg)
    cam = build_driver("down", cfg.sensors["down"], SensorContext(cfg, Health(lambda: 0.0), _Link())).backend
    assert isinstance(cam, SimulatedCamera) and cam.settings.fps == 10
    assert cam.calibration.K[0, 2] == 160.5 and cam.calibration.D[0] == -0.2
    frame = cam.render(0.0, pose((2.5, 2.5, -1.0)))  # above marker 0 of the arena
    assert frame.image.shape == (240, 320)
