"""The EKF-SLAM's camera path (companion/nav/ekf_slam/markers.py and its wiring in the ``ekf_slam``
pipeline): ArUco markers rendered by the simulated camera (sitl/camera_sim.py) on a test world of
large floor markers at landmark positions, seen from 30-80 m, turned into range / azimuth /
elevation in the level heading frame and compared with the truth from the vehicle's pose
(model.py's ``observe``). 80 m is the highest tested: the renderer draws nothing beyond 100 m
(sitl/camera_scene.py MAX_RANGE_M), so a tilted view from 100 m would see sky."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion import plugins
from companion.calibration import CameraCalibration
from companion.config import Config, ConfigError, MountConfig, load_config
from companion.frames import geodetic_from_ned, quat_from_euler, wrap_pi
from companion.health import Health
from companion.messages import Frame, GnssFix, ImuSample
from companion.nav.ekf_slam.markers import MarkerFrame, MarkerParams, MarkerSighter
from companion.nav.ekf_slam.model import observe
from companion.nav.ekf_slam.pipeline import EkfSlamPipeline, EkfSlamPipelineConfig
from companion.pipeline import PipelineContext
from companion.schema import SchemaError, load_text
from companion.world import Bounds, FloorMarker, World
from drivers.mount import OPTICAL_TO_SENSOR, Mount
from sitl.camera_sim import SimCameraSettings, SimulatedCamera
from sitl.truth import TruthSample

SIDE_M = 4.0
# landmark positions (north, east m) carrying markers of the landmark's id; 250 is outside DICT_4X4_250
MARKERS = (FloorMarker(12, (0.0, 0.0), SIDE_M, 0.0), FloorMarker(40, (12.0, 9.0), SIDE_M, 30.0),
           FloorMarker(77, (-10.0, -14.0), SIDE_M, 200.0), FloorMarker(200, (8.0, -15.0), SIDE_M, 100.0))


def world_of(markers: tuple[FloorMarker, ...], dictionary: str = "DICT_4X4_250") -> World:
    """A test world of large floor markers (no walls) drawn from ``dictionary``."""
    return World(name="marker-landmarks", wall_angle_deg=90, bounds=Bounds((-300.0, -300.0), (300.0, 300.0)),
                 start=(0.0, 0.0, 0.0), floor_markers=markers, marker_dictionary=dictionary)


WORLD = world_of(MARKERS)
DOWN = (0.0, -90.0, 0.0)  # mount rpy_deg: looking down, the image's top towards the body's front
CAMERA_OFFSET_M = (0.15, -0.05, 0.1)  # the camera's origin in body FRD: the sightings start at the body origin
SETTINGS = SimCameraSettings(hfov_deg=40.0, distortion=(-0.05, 0.01, 0.0, 0.0, 0.0), noise_sigma=2.0)
MOUNT = Mount.from_config(MountConfig(position_m=CAMERA_OFFSET_M, rpy_deg=DOWN))


def sighter(world: World = WORLD, **params: object) -> tuple[MarkerSighter, SimulatedCamera]:
    calibration = SETTINGS.intrinsics()
    camera = SimulatedCamera("cam", SETTINGS, calibration, MOUNT, world, truth=None)  # type: ignore[arg-type]
    marker_params = MarkerParams(SIDE_M, **params)  # type: ignore[arg-type]
    return MarkerSighter(calibration, MOUNT.rotation @ OPTICAL_TO_SENSOR, MOUNT.offset_m, marker_params, "cam"), camera


def look(position: tuple[float, float, float], rpy_deg: tuple[float, float, float], world: World = WORLD,
         **params: object) -> MarkerFrame:
    """What the sighter makes of the frame the simulated camera renders at this vehicle pose
    (NED m; roll, pitch, yaw deg), levelled with the true roll and pitch."""
    marker_sighter, camera = sighter(world, **params)
    roll, pitch, yaw = np.radians(rpy_deg)
    truth = TruthSample(0.0, np.array(position, dtype=float), np.zeros(3), quat_from_euler(roll, pitch, yaw))
    return marker_sighter.sightings(camera.render(1.5, truth, sequence=7), roll, pitch)


def truth_of(position: tuple[float, float, float], yaw_deg: float, marker_id: int) -> np.ndarray:
    """(range m, azimuth rad, elevation rad) of the marker's centre from the body origin."""
    marker = next(m for m in MARKERS + MORE if m.id == marker_id)
    n, e, d = position
    return observe(np.array([n, e, math.radians(yaw_deg)]), d, np.array([*marker.position, 0.0]))


def errors(frame: MarkerFrame, position: tuple[float, float, float], yaw_deg: float) -> np.ndarray:
    """(N, 3) measured minus true (range m, azimuth rad, elevation rad), rows as the sightings'."""
    s = frame.sightings
    measured = np.column_stack((s.range_m, s.azimuth_rad, s.elevation_rad))
    truth = np.array([truth_of(position, yaw_deg, int(i)) for i in s.ids]).reshape(-1, 3)
    out = measured - truth
    out[:, 1] = [wrap_pi(a) for a in out[:, 1]]
    return out


def test_a_marker_ahead_and_right_below_has_a_positive_azimuth_a_negative_elevation_and_its_range() -> None:
    position = (-4.0, -5.0, -50.0)  # marker 12 at (0, 0) is 4 m ahead, 5 m right, 50 m below
    frame = look(position, (0.0, 0.0, 0.0), world=world_of(MARKERS[:1]))
    s = frame.sightings
    assert list(s.ids) == [12] and s.t_capture == 1.5 and s.sequence == 7 and s.sensor_id == "cam"
    assert s.azimuth_rad[0] == pytest.approx(math.atan2(5.0, 4.0), abs=1e-3)  # clockwise from the nose
    assert s.elevation_rad[0] == pytest.approx(-math.atan2(50.0, math.hypot(4.0, 5.0)), abs=1e-3)  # below
    assert s.range_m[0] == pytest.approx(math.sqrt(4 ** 2 + 5 ** 2 + 50 ** 2), abs=0.5)
    left = look((-4.0, 5.0, -50.0), (0.0, 0.0, 0.0), world=world_of(MARKERS[:1])).sightings
    assert left.azimuth_rad[0] == pytest.approx(-s.azimuth_rad[0], abs=1e-3)
    turned = look(position, (0.0, 0.0, 20.0), world=world_of(MARKERS[:1])).sightings  # nose 20 deg right
    assert turned.azimuth_rad[0] == pytest.approx(s.azimuth_rad[0] - math.radians(20.0), abs=1e-3)
    assert turned.elevation_rad[0] == pytest.approx(s.elevation_rad[0], abs=1e-3)


@pytest.mark.parametrize("rpy_deg", [(6.0, 0.0, 0.0), (0.0, -5.0, 0.0), (-4.0, 5.0, 0.0)])
def test_rolled_or_pitched_the_same_marker_gives_the_same_level_bearings(rpy_deg: tuple[float, float, float]) -> None:
    position = (-4.0, -5.0, -50.0)
    level = look(position, (0.0, 0.0, 0.0), world=world_of(MARKERS[:1])).sightings
    tilted = look(position, rpy_deg, world=world_of(MARKERS[:1])).sightings
    # the marker moves ~35 px across the image; 1e-3 rad is 0.9 px of the 880 px focal length
    assert tilted.azimuth_rad[0] == pytest.approx(level.azimuth_rad[0], abs=1e-3)
    assert tilted.elevation_rad[0] == pytest.approx(level.elevation_rad[0], abs=1e-3)
    assert tilted.range_m[0] == pytest.approx(level.range_m[0], rel=0.01)


POSES = [((2.0, -1.0, -30.0), (0.0, 0.0, 0.0)), ((2.0, -1.0, -30.0), (4.0, -3.0, 30.0)),
         ((3.0, 2.0, -60.0), (0.0, 0.0, 0.0)), ((3.0, 2.0, -60.0), (-5.0, 6.0, 120.0)),
         ((-2.0, 1.0, -80.0), (3.0, 4.0, -70.0)), ((-2.0, 1.0, -80.0), (-4.0, -4.0, 200.0))]


def test_rendered_markers_from_30_to_80_m_give_range_and_bearings_within_3_sigma_of_the_truth() -> None:
    """Measured (2026-12-02, 640x480, 40 deg field of view, 4 m markers, 2 grey levels of pixel
    noise, a little barrel distortion, 0.5 px corner sigma stated): 16 sightings from 30, 60 and
    80 m; range errors +0.05 to +0.84 m, all positive (+0.2 to +1.0 % of the range: sub-pixel
    corners of a blurred convex corner sit a little inside it, the marker looks small), azimuth
    within 0.08 deg, elevation within 0.006 deg; the largest error / stated sigma 0.61 (range),
    0.17 (azimuth), 0.18 (elevation). Stated range sigma 0.18 m at 30 m, 0.72-0.79 m at 60 m,
    1.29-1.38 m at 80 m; bearing sigma 0.033 deg."""
    normalised = []
    for position, rpy in POSES:
        frame = look(position, rpy)
        assert len(frame.sightings.ids) >= 1 and frame.outside_id_range == frame.ambiguous == frame.failed == 0
        normalised.append(np.abs(errors(frame, position, rpy[2])) / frame.sightings.sigmas)
        assert np.all(frame.sightings.sigmas <= np.array(frame.sightings.sigma))  # the frame states its largest
    worst = np.concatenate(normalised)
    assert len(worst) >= 12
    assert worst.max() < 3.0, worst.max(axis=0)


def test_markers_outside_the_id_range_are_skipped_and_counted() -> None:
    frame = look((3.0, 2.0, -60.0), (0.0, 0.0, 0.0), id_range=(0, 50))
    assert sorted(frame.sightings.ids) == [12, 40] and frame.outside_id_range == 2  # 77 and 200


def test_a_marker_id_seen_twice_is_skipped_and_counted() -> None:
    twice = (*MARKERS[:2], FloorMarker(40, (-10.0, -14.0), SIDE_M, 0.0))
    frame = look((3.0, 2.0, -60.0), (0.0, 0.0, 0.0), world=world_of(twice))
    assert list(frame.sightings.ids) == [12] and frame.ambiguous == 2


MORE = (FloorMarker(300, (-6.0, 8.0), SIDE_M, 45.0), FloorMarker(640, (10.0, -8.0), SIDE_M, 0.0))


def test_a_world_may_draw_its_markers_from_a_larger_dictionary_for_landmark_ids_beyond_250() -> None:
    """The outdoor world's landmarks have ids 0-640: DICT_4X4_250 (the laser-dot floor's) cannot
    carry them, DICT_4X4_1000 can (its first 250 markers are DICT_4X4_250's)."""
    position, rpy = (0.0, 0.0, -50.0), (2.0, -3.0, 10.0)
    world = world_of(MARKERS[:1] + MORE, "DICT_4X4_1000")
    frame = look(position, rpy, world=world, dictionary=cv2.aruco.DICT_4X4_1000)
    assert sorted(frame.sightings.ids) == [12, 300, 640]
    assert np.all(np.abs(errors(frame, position, rpy[2])) < 3.0 * frame.sightings.sigmas)
    with pytest.raises(ValueError, match=r"floor_markers\[1\]: id 300 .* DICT_4X4_250 \(ids 0-249\)"):
        sighter(world_of(MARKERS[:1] + MORE))
    with pytest.raises(SchemaError, match="marker_dictionary: 'DICT_4X4_2000' is not an OpenCV ArUco dictionary"):
        load_text("name: w\nwall_angle_deg: 90\nbounds: {min: [-9, -9], max: [9, 9]}\nstart: [0, 0, 0]\n"
                  "marker_dictionary: DICT_4X4_2000\n", World)


def test_a_frame_without_markers_gives_an_empty_sightings_message() -> None:
    marker_sighter, _ = sighter()
    frame = marker_sighter.sightings(Frame("cam", 2.0, np.full((480, 640, 3), 128, np.uint8), 3), 0.0, 0.0)
    s = frame.sightings
    assert len(s.ids) == len(s.range_m) == len(s.azimuth_rad) == len(s.elevation_rad) == 0
    assert s.t_capture == 2.0 and s.sequence == 3 and s.sigma == (0.0, 0.0, 0.0) and frame.sightings.sigmas.shape == (0, 3)


# -- the pipeline --------------------------------------------------------------------------------

ORIGIN = (47.3977, 8.5456, 488.0)
ALTITUDE_M = 60.0


def calibration_file(path: Path, calibration: CameraCalibration) -> Path:
    """``calibration`` written as ROS camera_info YAML."""
    k = ", ".join(f"{v:.6f}" for v in calibration.K.ravel())
    d = ", ".join(f"{v:g}" for v in calibration.D)
    path.write_text(f"image_width: {calibration.width}\nimage_height: {calibration.height}\n"
                    f"camera_matrix: {{rows: 3, cols: 3, data: [{k}]}}\ndistortion_model: plumb_bob\n"
                    f"distortion_coefficients: {{rows: 1, cols: {len(calibration.D)}, data: [{d}]}}\n")
    return path


def config_text(section: str) -> str:
    return f"""
origin: {{lat: {ORIGIN[0]}, lon: {ORIGIN[1]}, alt: {ORIGIN[2]}}}
mavlink: {{url: "udpout:127.0.0.1:14555", streams: {{sim_state: 50}}}}
plugins: [sitl.sim_backends]
sensors:
  imu: {{kind: imu, backend: autopilot}}
  gnss: {{kind: gnss, backend: sim}}
  down:
    kind: camera
    backend: sim
    mount: {{position_m: {list(CAMERA_OFFSET_M)}, rpy_deg: {list(DOWN)}}}
    settings: {{hfov_deg: 40, distortion: {list(SETTINGS.distortion or ())}, fps: 5}}
pipelines:
  ekf_slam:
    gnss: gnss
    base_ne: [0, 0]
    slam: {{altitude_m: {ALTITUDE_M}}}
    planner: {{altitude_m: {ALTITUDE_M}}}
{section}
"""


def load(tmp_path: Path, section: str) -> Config:
    calibration_file(tmp_path / "down.yaml", SETTINGS.intrinsics())
    file = tmp_path / "config.yaml"
    file.write_text(config_text(section))
    return load_config(file)


@pytest.mark.parametrize(("section", "key", "says"), [
    ("", "pipelines.ekf_slam.landmarks", "marker camera"),
    ("    marker_camera: down", "pipelines.ekf_slam.marker_calibration", "required with marker_camera"),
    ("    marker_camera: imu\n    marker_calibration: down.yaml", "pipelines.ekf_slam.marker_camera", "not a camera"),
    ("    marker_camera: down\n    marker_calibration: down.yaml\n    marker_dictionary: DICT_9X9",
     "pipelines.ekf_slam.marker_dictionary", "not an OpenCV ArUco dictionary"),
    ("    marker_camera: down\n    marker_calibration: down.yaml\n    marker_id_range: [10, 5]",
     "pipelines.ekf_slam.marker_id_range", "lowest <= highest"),
])
def test_config_errors_name_the_key(tmp_path: Path, section: str, key: str, says: str) -> None:
    with pytest.raises(ConfigError) as error:
        load(tmp_path, section)
    assert error.value.key_path == key and says in str(error.value)


def test_a_marker_camera_section_builds_and_its_frames_map_the_markers_in_the_slam(tmp_path: Path) -> None:
    """The pipeline built from a config with a marker camera (no landmark sensor) is fed as the
    daemon would through its subscriptions: IMU at 50 Hz, GNSS and rendered camera frames at 5 Hz
    while hovering at 60 m over the markers; the markers become the SLAM's landmarks where they are."""
    cfg = load(tmp_path, "    marker_camera: down\n    marker_calibration: down.yaml\n    marker_size_m: 4.0")
    section = cfg.pipelines.enabled["ekf_slam"]
    entry = plugins.pipeline("ekf_slam")
    assert entry is not None
    assert section.sensor_inputs() == {"gnss": "gnss", "imu_sensor": "imu", "marker_camera": "camera"}
    pipeline = entry.build(section, PipelineContext(cfg, Health(lambda: 0.0)))
    assert isinstance(pipeline, EkfSlamPipeline)
    handlers = pipeline.subscriptions()
    assert set(handlers) == {"gnss", "imu", "down"}
    _, camera = sighter()
    position = np.array([5.0, -3.0, -ALTITUDE_M])
    rng = np.random.default_rng(1)
    for k in range(1, 101):  # 2 s
        t = k * 0.02
        roll, pitch, yaw = math.radians(3.0 * math.sin(t)), math.radians(-2.0), math.radians(30.0)
        handlers["imu"](ImuSample(t, np.array([0.0, 0.0, -9.81]), np.zeros(3), (roll, pitch, yaw), np.zeros(3),
                                  20.0 - position[2]))
        if k % 10 == 0:
            lat, lon, alt = geodetic_from_ned(position + rng.normal(0.0, 0.2, 3), ORIGIN)
            handlers["gnss"](GnssFix("gnss", t, 3, lat, lon, alt, np.zeros(3), 0.2, 0.3))
            truth = TruthSample(t, position, np.zeros(3), quat_from_euler(roll, pitch, yaw))
            handlers["down"](camera.render(t, truth, sequence=k // 10))
        if k % 2 == 0:
            pipeline.step(t + 0.01)
    stats = pipeline.stats
    assert stats.marker_frames >= 8 and stats.frames == stats.marker_frames and stats.markers_skipped == 0
    assert pipeline.slam is not None
    mapped = pipeline.slam.landmarks()
    assert set(mapped) == {12, 40, 200}  # 77 is out of view
    for marker in MARKERS[:2] + MARKERS[3:]:
        assert np.linalg.norm(mapped[marker.id] - [*marker.position, 0.0]) < 1.0  # GNSS 0.2 m, range sigma ~0.7 m


def test_a_frame_is_levelled_with_the_imu_attitude_at_its_time_and_dropped_without_one_within_0_1_s(
        monkeypatch: pytest.MonkeyPatch) -> None:
    section = load_text("gnss: gnss\nbase_ne: [0, 0]\nmarker_camera: down\nmarker_calibration: down.yaml\n",
                        EkfSlamPipelineConfig)
    marker_sighter, _ = sighter()
    pipeline = EkfSlamPipeline(section, ORIGIN, Health(lambda: 0.0), marker_sighter)
    levelled: list[tuple[float, float]] = []
    original = marker_sighter.sightings

    def recording(frame: Frame, roll: float, pitch: float) -> MarkerFrame:
        levelled.append((roll, pitch))
        return original(frame, roll, pitch)

    monkeypatch.setattr(marker_sighter, "sightings", recording)
    handlers = pipeline.subscriptions()
    blank = np.full((480, 640), 128, np.uint8)
    for t, roll in ((1.00, 0.0), (1.02, 0.1), (1.04, 0.2)):
        handlers["imu"](ImuSample(t, np.zeros(3), np.zeros(3), (roll, -0.05, 0.0)))
    handlers["down"](Frame("down", 1.015, blank, 1))  # between the samples at 1.00 and 1.02 s: roll 0.075
    pipeline.step(1.05)
    handlers["down"](Frame("down", 1.2, blank, 2))  # waits for the IMU samples up to it ...
    pipeline.step(1.3)
    handlers["down"](Frame("down", 1.3, blank, 3))  # ... and is overtaken by this one (dropped)
    pipeline.step(1.9)  # the IMU stopped: released after HOLD_FOR_IMU_S, 0.26 s from the last sample (dropped)
    assert levelled == [(pytest.approx(0.075), pytest.approx(-0.05))]
    assert pipeline.stats.marker_frames == 1 and pipeline.stats.marker_frames_dropped == 2
