"""The laser-dot pipeline (companion/nav/laser_dots/): its failure cases on frames of the simulated
camera (a dot missing, a fourth spot, no marker in view, a dot on a table, a saturated camera:
degraded or lost with the reason, never a NaN or a confident wrong pose), its estimates to the
daemon, check-config's field-of-view warning, and the Fig. 4 scenario in lockstep SITL scored
against the simulator's truth (the issue's contract)."""

from __future__ import annotations

import dataclasses
import json
import math
import socket
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from companion.calibration import load_calibration
from companion.cli import main
from companion.config import load_config
from companion.frames import rotation_from_quat
from companion.health import Health
from companion.messages import AttitudeEstimate, Frame, ImuSample, PoseEstimate, RangeEstimate
from companion.nav.laser_dots.frame_pose import UNTRIANGULATED, FrameResult
from companion.nav.laser_dots.pipeline import LaserDotsConfig, LaserDotsPipeline, frame_poser
from companion.schema import SchemaError, parse_document
from companion.world import Obstacle, World, load_world
from drivers.mount import Mount
from sitl.calibration_sweep import NO_TRUTH, laser_dots_camera
from sitl.camera_sim import SimulatedCamera
from tests.conftest import REPO, free_port
from tests.test_camera_sim import Pose, pose

CONFIG = REPO / "config" / "sitl-laser-dots.yaml"
CFG = load_config(CONFIG)
SECTION = CFG.pipelines.enabled["laser_dots"]
MOUNT = Mount.from_config(CFG.sensors["down"].mount)
CALIBRATION = load_calibration(REPO / "config" / "cameras" / "down-wide-640.yaml")
FIG4 = load_world(REPO / "config" / "worlds" / "fig4.yaml")
OVER_MARKERS = pose((6.0, 0.8, -1.0), (2.0, -1.5, 10.0))


def camera(world: World = FIG4, **settings: object) -> SimulatedCamera:
    """The config's simulated camera and rig, over ``world``, with ``settings`` changed."""
    cfg = load_config(CONFIG)
    cfg.sensors["down"].settings.update(settings)
    cam = laser_dots_camera(cfg)
    return cam if world is FIG4 else SimulatedCamera("down", cam.settings, cam.calibration, cam.mount, world, NO_TRUTH)


def process(image: np.ndarray, truth: Pose = OVER_MARKERS, world: World = FIG4) -> FrameResult:
    poser = frame_poser(SECTION, CALIBRATION, MOUNT, world.floor_markers)
    return poser.process(image, rotation_from_quat(truth.quat))


def assert_no_nan_in_what_it_claims(result: FrameResult) -> None:
    if result.kind == "pose":
        assert np.all(np.isfinite(result.covariance)) and np.all(np.isfinite(result.solution.position_ned))
    if result.kind == "tilt":
        assert np.all(np.isfinite(result.tilt)) and np.all(np.isfinite(result.tilt_covariance))


def test_over_the_markers_a_frame_gives_the_pose_to_a_centimetre_with_a_covariance_that_covers_it() -> None:
    result = process(camera().render(0.0, OVER_MARKERS).image)
    assert result.kind == "pose", result.reason
    error = result.solution.position_ned - OVER_MARKERS.position_ned
    assert np.linalg.norm(error) < 0.02
    assert error @ np.linalg.solve(result.covariance[:3, :3], error) < 16.0  # within 4 sigma
    assert_no_nan_in_what_it_claims(result)


def test_a_missing_dot_gives_no_pose_and_says_so() -> None:
    cam = camera()
    image = cam.render(0.0, OVER_MARKERS).image
    rotation, origin = cam.camera_pose(OVER_MARKERS)
    hits, _ = cam.laser_hits(OVER_MARKERS)
    u, v = cam.calibration.project((hits[1:2] - origin) @ rotation)[0]
    cv2.circle(image, (round(u), round(v)), 12, (120, 120, 120), -1)  # dust on the floor over beam 1's dot
    result = process(image)
    assert result.kind == "none" and result.reason == "2 of 3 dots seen"
    assert result.dots.found.tolist() == [True, False, True]


def test_a_fourth_red_spot_near_a_dot_is_counted_and_the_pose_stays_right() -> None:
    cam = camera()
    image = cam.render(0.0, OVER_MARKERS).image
    rotation, origin = cam.camera_pose(OVER_MARKERS)
    hits, _ = cam.laser_hits(OVER_MARKERS)
    u, v = cam.calibration.project((hits[:1] - origin) @ rotation)[0]
    cv2.circle(image, (round(u) + 25, round(v)), 2, (0, 0, 255), -1)  # another laser pointer's spot
    result = process(image)
    assert result.kind == "pose" and result.dots.extra == 1
    assert np.linalg.norm(result.solution.position_ned - OVER_MARKERS.position_ned) < 0.02


def test_without_a_marker_in_view_the_dots_still_give_height_roll_and_pitch() -> None:
    bare = dataclasses.replace(FIG4, floor_markers=())
    truth = pose((6.0, 0.8, -1.2), (3.0, -2.0, 40.0))
    result = process(camera(bare).render(0.0, truth).image, truth, bare)
    assert result.kind == "tilt" and "no floor marker" in result.reason
    height, roll, pitch = result.tilt
    assert height == pytest.approx(1.2, abs=0.05)
    assert math.degrees(roll) == pytest.approx(3.0, abs=1.0) and math.degrees(pitch) == pytest.approx(-2.0, abs=1.0)
    assert_no_nan_in_what_it_claims(result)


def test_a_dot_on_a_table_is_found_off_the_floor_and_no_pose_is_given() -> None:
    hits, _ = camera().laser_hits(OVER_MARKERS)
    x, y = hits[2, :2]  # a 0.75 m table under beam 2's dot
    table = Obstacle("table", (x - 0.4, y - 0.4), (x + 0.4, y + 0.4), 0.75)
    world = dataclasses.replace(FIG4, obstacles=(table,))
    result = process(camera(world).render(0.0, OVER_MARKERS).image, OVER_MARKERS, world)
    assert result.kind == "none" and "beam 2's dot is off the floor" in result.reason


def test_a_saturated_camera_gives_no_dots_and_says_why() -> None:
    result = process(camera(gain=10.0).render(0.0, OVER_MARKERS).image)
    assert result.kind == "none" and "saturated" in result.reason


def test_dots_whose_lengths_cannot_be_triangulated_give_no_fix_rather_than_an_unchecked_one_or_a_crash() -> None:
    at_the_beams = Mount(MOUNT.rotation, np.array(SECTION.beams.origin_m))  # no baseline: each ray runs along its beam
    cam = camera()
    cam = SimulatedCamera("down", cam.settings, cam.calibration, at_the_beams, FIG4, NO_TRUTH)
    image = cam.render(0.0, OVER_MARKERS).image
    over_markers, bare = (frame_poser(SECTION, CALIBRATION, at_the_beams, world.floor_markers).process(
        image, rotation_from_quat(OVER_MARKERS.quat)) for world in (FIG4, dataclasses.replace(FIG4, floor_markers=())))
    assert over_markers.kind == "none" and over_markers.reason == UNTRIANGULATED
    assert bare.kind == "none" and bare.reason == "the three floor points are collinear: no plane"  # not a raise


def test_the_closed_form_on_a_rig_far_from_90_degrees_is_a_config_error() -> None:
    raw = yaml.safe_load(CONFIG.read_text())["pipelines"]["laser_dots"]
    raw.update(method="closed_form", beams={"angle_deg": 60})
    with pytest.raises(SchemaError, match="beams.angle_deg: closed_form solves beams at 90 degrees"):
        parse_document(yaml.safe_dump(raw), "c.yaml").build(LaserDotsConfig)


def imu_sample(t: float) -> ImuSample:
    return ImuSample(t, np.array([0.0, 0.0, -9.81]), np.zeros(3), euler_rad=(0.0, 0.0, 0.0))


def pipeline() -> LaserDotsPipeline:
    return LaserDotsPipeline(SECTION, CALIBRATION, FIG4, MOUNT, Health(lambda: 0.0))


def test_the_pipeline_sends_a_finite_pose_after_a_frame_over_the_markers() -> None:
    p, level = pipeline(), pose((6.0, 0.8, -1.0))
    image = camera().render(0.0, level).image
    for k in range(20):
        p.imu.add(imu_sample(0.02 * k))
    p.on_frame(Frame("down", 0.2, image))
    out = p.step(0.4)
    poses = [e for e in out if isinstance(e, PoseEstimate)]
    assert len(poses) == 1 and poses[0].is_finite() and poses[0].source == "laser_dots"
    assert np.linalg.norm(poses[0].position_ned - level.position_ned) < 0.03
    assert p.telemetry(False)["laser_dots"]["kind"] == "pose"


def test_without_markers_the_pipeline_gives_a_range_and_an_attitude_without_yaw_but_no_pose() -> None:
    bare = dataclasses.replace(FIG4, floor_markers=())
    p = LaserDotsPipeline(SECTION, CALIBRATION, bare, MOUNT, Health(lambda: 0.0))
    image = camera(bare).render(0.0, pose((6.0, 0.8, -1.0))).image
    p.imu.add(imu_sample(0.0))
    p.on_frame(Frame("down", 0.0, image))
    out = p.step(0.05)
    assert not any(isinstance(e, PoseEstimate) for e in out)  # no x, y, yaw: the fusion is not initialised
    (distance,) = [e for e in out if isinstance(e, RangeEstimate)]
    (attitude,) = [e for e in out if isinstance(e, AttitudeEstimate)]
    assert distance.distance_m == pytest.approx(1.0, abs=0.05) and distance.orientation == "down"
    assert math.isnan(attitude.euler_rad[2]) and all(math.isfinite(a) for a in attitude.euler_rad[:2])


def test_check_config_warns_when_the_camera_cannot_see_all_three_dots(tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check-config", str(CONFIG)]) == 0
    assert "warning" not in capsys.readouterr().err
    narrow = tmp_path / "narrow.yaml"
    cal = yaml.safe_load((REPO / "config" / "cameras" / "down-wide-640.yaml").read_text())
    cal["camera_matrix"]["data"][0] = cal["camera_matrix"]["data"][4] = 320.0  # 90 x 74 degrees
    narrow.write_text(yaml.safe_dump(cal))
    raw = yaml.safe_load(CONFIG.read_text())
    raw["pipelines"]["laser_dots"]["calibration"] = str(narrow)
    for key in ("world",):
        raw["pipelines"]["laser_dots"][key] = str(REPO / "config" / raw["pipelines"]["laser_dots"][key])
    raw["sensors"]["down"]["settings"]["calibration"] = str(narrow)
    raw["sitl"]["world"] = str(REPO / "config" / raw["sitl"]["world"])
    raw["mission"]["file"] = None
    cfg = tmp_path / "c.yaml"
    cfg.write_text(yaml.safe_dump(raw))
    assert main(["check-config", str(cfg)]) == 0
    err = capsys.readouterr().err
    assert "warning" in err and "loses a laser dot" in err and "outside the image" in err
    assert "eq. 41 asks a sensor size over focal length of at least 2.83" in err and "this camera has 1.50" in err


def fly_fig4(tmp_path: Path, seconds: float, **pipeline_changes: object) -> dict:
    """The flight report of the fig4 mission in lockstep (seed 1) on config/sitl-laser-dots.yaml."""
    raw = yaml.safe_load(CONFIG.read_text())
    raw["mavlink"]["url"] = f"udpout:127.0.0.1:{(port := free_port())}"
    raw["sitl"]["vehicle_url"] = f"udpin:127.0.0.1:{port}"
    raw["sitl"]["gcs_urls"] = [f"udpout:127.0.0.1:{free_port()}"]
    raw["telemetry"]["listen"] = [f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"]
    raw["pipelines"]["laser_dots"].update(pipeline_changes)
    for folder in ("worlds", "cameras", "missions"):
        (tmp_path / folder).symlink_to(REPO / "config" / folder)
    cfg, report = tmp_path / "laser-dots.yaml", tmp_path / "report.json"
    cfg.write_text(yaml.safe_dump(raw, sort_keys=False))
    proc = subprocess.run([sys.executable, "-m", "companion.cli", "sitl", "-c", str(cfg), "--mission", "fig4",
                           "--lockstep", "--seed", "1", "--seconds", str(seconds), "--report", str(report)],
                          cwd=REPO, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(report.read_text())


def test_fig4_first_150_s_flown_on_the_dots_alone_meet_a_centimetre_and_half_a_degree(tmp_path: Path) -> None:
    r = fly_fig4(tmp_path, 150)
    est, ap = r["estimate"], r["autopilot"]
    assert ap["external_nav_in_use"] and ap["nonfinite_dropped"] == 0
    assert 28.0 <= ap["vision_position_estimate_hz"] <= 31.0
    assert est["position_rms_m"] <= 0.01 and est["attitude_rms_deg"] <= 0.5
    assert est["lost_seconds"] == 0.0 and est["wrong_resets"] == 0
    # Honest covariance (3 is ideal): never more than 20 % over the 95 % band, and cautious by at most a
    # factor 1.5 below it. These 150 s gave 2.80-2.93 (band 2.81-3.19; OpenCV's version moves them by a
    # few percent) while the simulated camera rendered from SIM_STATE's 1.1 cm position steps, about 3 mm
    # of error the covariance happened to cover; from the exact position (2026-12-04, sitl/truth.py)
    # 2.13, the error 3.6 / 3.8 / 1.7 mm per axis against sigmas of 4.2 / 4.2 / 2.0 mm.
    low, high = est["nees_band"]
    assert low / 1.5 <= est["nees_mean"] <= high * 1.2
    assert r["control"]["failsafes_triggered"] == []


def test_one_frame_without_a_pose_is_ridden_out_three_in_a_row_degrade_with_the_reason() -> None:
    health = Health(lambda: 0.0)
    p = LaserDotsPipeline(SECTION, CALIBRATION, FIG4, MOUNT, health)
    good = camera().render(0.0, OVER_MARKERS).image
    blinded = camera(gain=10.0).render(0.0, OVER_MARKERS).image

    def state_after(image: np.ndarray, t: float) -> str:
        p.imu.add(imu_sample(t))
        p.on_frame(Frame("down", t, image))
        p.step(t + 0.01)
        return health.snapshot()["components"]["nav:laser_dots"]["state"]

    assert state_after(good, 0.0) == "ok"
    assert state_after(blinded, 0.1) == "ok" and state_after(good, 0.2) == "ok"
    assert [state_after(blinded, t) for t in (0.3, 0.4, 0.5)] == ["ok", "ok", "degraded"]
    assert "saturated" in health.snapshot()["components"]["nav:laser_dots"]["reason"]
