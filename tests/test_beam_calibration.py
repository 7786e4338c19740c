"""`companion laser-dots calibrate` (companion/beam_calibration.py) on frames rendered by the simulated
camera from a rig mounted 1 degree off its nominal 90 degrees: the calibration recovers the true beams
from the frames alone (poses from the floor markers), and the calibrated rig poses better than the
nominal one."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.calibration import load_calibration
from companion.cli import main
from companion.config import load_config
from companion.frames import rotation_from_euler
from companion.nav.laser_dots.beams import BeamRig, BeamRigConfig, nominal_rig
from companion.nav.laser_dots.frame_pose import FramePoser, FramePoseParams
from companion.schema import parse_document
from companion.world import load_world
from drivers.mount import OPTICAL_TO_SENSOR, Mount
from sitl.camera_sim import SimCameraSettings, SimulatedCamera
from tests.conftest import REPO
from tests.test_camera_sim import FakeTruth, pose

CONFIG = REPO / "config" / "sitl-laser-dots.yaml"
TRUE_RIG = nominal_rig(89.0, 2.0, (0.01, -0.01, -0.17))  # as built: 1 deg narrower, turned, 1-2 cm off


def camera(rig: BeamRig) -> SimulatedCamera:
    cfg = load_config(CONFIG)
    section = cfg.sensors["down"]
    settings = SimCameraSettings(fps=10, exposure_s=0.004, noise_sigma=2.0, laser_speckle_px=0.5, seed=3,
                                 laser_beams=BeamRigConfig(origins_m=[tuple(o) for o in rig.origins],
                                                           directions=[tuple(d) for d in rig.directions]))
    world = cfg.load_referenced("sitl.world", cfg.sitl.world, load_world)
    calibration = load_calibration(REPO / "config" / "cameras" / "down-wide-640.yaml")
    return SimulatedCamera("down", settings, calibration, Mount.from_config(section.mount), world,
                           FakeTruth(pose((0.0, 0.0, -1.0))))


def poses(n: int, seed: int) -> list[tuple[tuple[float, float, float], tuple[float, float, float]]]:
    """Vehicle poses over the first markers of the fig4 hall: heights 0.4-1.8 m, a few degrees of tilt, turned."""
    rng = np.random.default_rng(seed)
    return [((float(rng.uniform(1, 8)), float(rng.uniform(-0.3, 1.8)), -float(h)),
             (float(rng.normal(0, 3)), float(rng.normal(0, 3)), float(rng.uniform(-30, 30))))
            for h in np.linspace(0.4, 1.8, n)]


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("calibration-frames")
    cam = camera(TRUE_RIG)
    for k, (position, rpy) in enumerate(poses(60, seed=1)):
        cv2.imwrite(str(folder / f"{k:04d}.png"), cam.render(0.0, pose(position, rpy), None, k).image)
    return folder


@dataclass
class BeamsFile:
    """The file `companion laser-dots calibrate --out` writes: the config's beams section."""

    beams: BeamRigConfig


@pytest.fixture(scope="module")
def calibrated(recording: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[BeamRig, str]:
    out = tmp_path_factory.mktemp("beams") / "beams.yaml"
    assert main(["laser-dots", "calibrate", "-c", str(CONFIG), str(recording), "--out", str(out)]) == 0
    return parse_document(out.read_text(), str(out)).build(BeamsFile).beams.rig(), out.read_text()


def test_the_calibration_recovers_the_true_beam_directions_from_the_frames_alone(calibrated: tuple[BeamRig, str]) -> None:
    rig, text = calibrated
    assert text.startswith("beams:\n  origins_m:")
    errors = [math.degrees(math.acos(min(1.0, float(a @ b)))) for a, b in zip(rig.directions, TRUE_RIG.directions)]
    assert max(errors) < 0.15, errors
    assert [rig.angle_deg(0, 1), rig.angle_deg(1, 2), rig.angle_deg(0, 2)] == pytest.approx([89.0] * 3, abs=0.2)


def test_the_calibrated_rig_poses_to_a_centimetre_where_the_nominal_one_is_lost_or_wrong(
        calibrated: tuple[BeamRig, str]) -> None:
    rig, _ = calibrated
    cfg = load_config(CONFIG)
    mount = Mount.from_config(cfg.sensors["down"].mount)
    cam = camera(TRUE_RIG)
    markers = load_world(REPO / "config" / "worlds" / "fig4.yaml").floor_markers

    def errors(assumed: BeamRig) -> np.ndarray:
        """Position errors (m) of the frames posed; frames the calibration did not see."""
        poser = FramePoser(assumed, cam.calibration, mount.rotation @ OPTICAL_TO_SENSOR, mount.offset_m, markers,
                           FramePoseParams(max_tilt_deg=20.0))
        out = []
        for k, (position, rpy) in enumerate(poses(15, seed=2)):
            image = cam.render(0.0, pose(position, rpy), None, 100 + k).image
            result = poser.process(image, rotation_from_euler(*np.radians(rpy)))
            if result.kind == "pose":
                out.append(np.linalg.norm(result.solution.position_ned - np.array(position)))
        return np.array(out)

    good, nominal = errors(rig), errors(nominal_rig(90.0, 0.0, (0.0, 0.0, -0.18)))
    assert len(good) >= 13 and np.sqrt(np.mean(good ** 2)) < 0.015
    # uncalibrated, the dots leave their beams' image curves: lost (refused), or posed centimetres off
    assert len(nominal) <= 3 or np.sqrt(np.mean(nominal ** 2)) > 2 * np.sqrt(np.mean(good ** 2))


def test_a_recording_without_usable_frames_is_refused_with_the_reason(tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    cv2.imwrite(str(tmp_path / "0000.png"), np.zeros((480, 640, 3), np.uint8))
    assert main(["laser-dots", "calibrate", "-c", str(CONFIG), str(tmp_path)]) == 2
    assert "none of its 1 frames shows the three dots" in capsys.readouterr().err
