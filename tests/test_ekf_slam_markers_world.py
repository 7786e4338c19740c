"""The camera path of the EKF-SLAM return to base, as configured for SITL: the markers world
(config/worlds/outdoor-markers.yaml, written by ``python -m sitl.outdoor_world --markers``), its
config (config/sitl-outdoor-markers.yaml) and one rendered frame over the base. The flight itself
(``companion sitl -c config/sitl-outdoor-markers.yaml --mission gnss-loss-return-60m --lockstep``)
takes minutes and is not run here.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from companion.calibration import load_calibration
from companion.config import load_config
from companion.frames import quat_from_euler
from companion.nav.ekf_slam.markers import MarkerSighter
from companion.world import load_world
from drivers.mount import OPTICAL_TO_SENSOR, Mount
from sitl.camera_scene import Scene
from sitl.camera_sim import SimCameraSettings, SimulatedCamera
from sitl.outdoor_world import outdoor_markers_world, outdoor_world
from sitl.truth import TruthSample

REPO = Path(__file__).resolve().parent.parent
WORLD = REPO / "config" / "worlds" / "outdoor-markers.yaml"
CONFIG = REPO / "config" / "sitl-outdoor-markers.yaml"


def test_the_markers_world_is_the_generators_and_has_a_marker_on_the_ground_at_every_landmark() -> None:
    assert yaml.safe_load(WORLD.read_text()) == outdoor_markers_world()
    assert yaml.safe_load((REPO / "config" / "worlds" / "outdoor.yaml").read_text()) == outdoor_world()
    world, plain = load_world(WORLD), load_world(REPO / "config" / "worlds" / "outdoor.yaml")
    assert world.marker_dictionary == "DICT_4X4_1000" and world.base == plain.base
    assert [m.id for m in world.landmarks] == [m.id for m in plain.landmarks] == list(range(641))
    markers = {m.id: m for m in world.floor_markers}
    for landmark, original in zip(world.landmarks, plain.landmarks):
        assert landmark.position == original.position and landmark.height_m == 0.0  # the marker's centre
        assert markers[landmark.id].position == landmark.position and markers[landmark.id].size_m == 4.0
    assert markers[640].position == world.base  # the landing pad


def test_the_config_passes_check_config_and_matches_its_camera() -> None:
    from companion.cli import main

    assert main(["check-config", str(CONFIG)]) == 0
    cfg = load_config(CONFIG)
    section = cfg.pipelines.enabled["ekf_slam"]
    camera = cfg.sensors[section.marker_camera]
    assert camera.kind == "camera" and camera.backend == "sim" and section.landmarks is None
    assert not any(s.kind == "landmarks" for s in cfg.sensors.values())
    assert camera.settings["calibration"] == section.marker_calibration and camera.settings["fps"] == 5
    assert section.marker_dictionary == load_world(WORLD).marker_dictionary and section.marker_size_m == 4.0
    calibration = load_calibration(CONFIG.parent / section.marker_calibration)
    half_short_side_deg = np.degrees(np.arctan(calibration.height / 2 / calibration.K[1, 1]))
    for part in (section.slam, section.planner):
        assert part.half_fov_deg <= half_short_side_deg  # the planner's footprint lies in the image
        assert part.altitude_m == 60.0


def test_a_frame_from_60_m_over_the_base_shows_the_pads_marker_and_only_near_textures_are_made() -> None:
    cfg = load_config(CONFIG)
    section = cfg.pipelines.enabled["ekf_slam"]
    world = load_world(WORLD)
    scene = Scene(world)
    assert scene._textures == {}  # none made up front (641 markers: 2 GB)
    near = {t.marker.id for t in scene.markers_near((353.5, 353.5, -60.0))}
    assert 640 in near and len(near) < 60
    calibration = load_calibration(CONFIG.parent / section.marker_calibration)
    mount = Mount.from_config(cfg.sensors[section.marker_camera].mount)
    settings = SimCameraSettings(calibration="x", fps=5, exposure_s=0.004)
    camera = SimulatedCamera("down", settings, calibration, mount, world, None)
    pose = TruthSample(0.0, np.array([353.5, 353.5, -60.0]), np.zeros(3), quat_from_euler(0.0, 0.0, 3.9))
    sighter = MarkerSighter(calibration, mount.rotation @ OPTICAL_TO_SENSOR, mount.offset_m, section.marker_params(),
                            "down")
    seen = sighter.sightings(camera.render(0.0, pose), 0.0, 0.0).sightings
    assert 640 in seen.ids
    k = list(seen.ids).index(640)
    assert abs(seen.range_m[k] - 60.0) < 1.0 and seen.elevation_rad[k] < np.radians(-85)
