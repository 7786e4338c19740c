"""Timings and accuracy of the laser-dot pipeline on simulated frames (for ``companion bench``).

Frames: the simulated downward camera of config/sitl-laser-dots.yaml (640 x 480, 135-degree
pinhole, 2 grey levels of pixel noise, 0.5 px laser speckle) over the Fig. 4 hall
(config/worlds/fig4.yaml): a 10 Hz sequence along the hall climbing from the scenario's 0.82 m
to its 1.63 m, turning 1 degree and moving 2 cm per frame with a few degrees of tilt. Each stage
is timed on the same frames, in order; the whole-frame stage tracks the markers from the previous
frame's pose as in flight (one search of the whole image per pass through the sequence, at its
start). The accuracy of the dots' pose is set beside the camera pose from the floor markers alone
(OpenCV solvePnP: IPPE_SQUARE on one marker, iterative on several) against the simulator's
truth, so a user sees what the lasers buy. Imports the simulator (a bench tool, allowed to).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from companion.config import load_config
from companion.frames import quat_from_euler, rotation_from_euler
from companion.nav.laser_dots import geometry
from companion.nav.laser_dots.frame_pose import FramePoser, FrameResult
from companion.nav.laser_dots.pipeline import frame_poser
from companion.timing import time_stage
from companion.world import load_world

CONFIG = Path(__file__).resolve().parents[3] / "config" / "sitl-laser-dots.yaml"
HEIGHTS_M = (0.82, 1.63)  # the sequence climbs from the first to the second
FRAMES = 24  # rendered frames the stages cycle through and the accuracy is measured on
START_NORTH_M, STEP_M, START_YAW_DEG = 20.0, 0.02, -10.0
TILT_DEG = 3.0  # roll and pitch swing this much (sines of 2-3 s periods)


@dataclass(frozen=True)
class BenchFrame:
    image: np.ndarray
    rotation: np.ndarray  # true body FRD -> NED
    position_ned: np.ndarray  # true, m


def bench_frames(n: int = FRAMES) -> tuple[FramePoser, list[BenchFrame]]:
    """The config's pipeline (as a FramePoser) and ``n`` frames its simulated camera renders."""
    from sitl.calibration_sweep import laser_dots_camera
    from sitl.truth import TruthSample

    cfg = load_config(CONFIG)
    section = cfg.pipelines.enabled["laser_dots"]
    camera = laser_dots_camera(cfg)
    world = cfg.load_referenced("pipelines.laser_dots.world", section.world, load_world)
    poser = frame_poser(section, camera.calibration, camera.mount, world.floor_markers)
    frames = []
    for k in range(n):
        rpy = np.radians([TILT_DEG * np.sin(0.3 * k), TILT_DEG * np.cos(0.2 * k), START_YAW_DEG + k])
        height = HEIGHTS_M[0] + (HEIGHTS_M[1] - HEIGHTS_M[0]) * k / (n - 1)
        position = np.array([START_NORTH_M + STEP_M * k, 0.7, -height])
        image = camera.render(0.0, TruthSample(0.0, position, np.zeros(3), quat_from_euler(*rpy)), None, k).image
        frames.append(BenchFrame(image, rotation_from_euler(*rpy), position))
    return poser, frames


def run_dots_bench(repeat: int) -> tuple[dict[str, tuple[float, float]], dict[str, str]]:
    """({stage: (median ms, p99 ms)}, {figure: text}) on the bench frames."""
    poser, frames = bench_frames()
    cycle: Iterator[BenchFrame] = itertools.cycle(frames)
    tracked = Tracked(poser)
    stages = {
        "laser_dots.detect (3 dots, 640x480)": lambda: poser.detector.detect(next(cycle).image),
        "laser_dots.markers (whole image: ArUco + homography)": lambda: poser.mapper.find(next(cycle).image),
        "laser_dots.frame (detect, markers tracked, solve, covariance)": lambda: tracked.process(next(cycle)),
        "markers alone: solvePnP camera pose (whole image)": lambda: _marker_pose(poser, next(cycle).image),
    }
    timings = {name: time_stage(fn, repeat) for name, fn in stages.items()}
    return timings, _accuracy(poser, frames)


class Tracked:
    """Frames processed in order, each with the previous one's pose and dots (as the pipeline does)."""

    def __init__(self, poser: FramePoser) -> None:
        self.poser = poser
        self.previous: tuple[np.ndarray, np.ndarray] | None = None
        self.pixels: np.ndarray | None = None

    def process(self, frame: BenchFrame) -> FrameResult:
        result = self.poser.process(frame.image, frame.rotation, self.previous, self.pixels)
        self.previous = None if result.solution is None else (result.solution.rotation, result.solution.position_ned)
        self.pixels = result.dots.pixels
        return result


def _marker_pose(poser: FramePoser, image: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(rotation body -> NED, body origin NED m) from the floor markers alone, or None."""
    view = poser.mapper.find(image)
    camera = None if view is None else poser.mapper.camera_pose(view)
    if camera is None:
        return None
    optical_to_ned, centre = camera
    body_to_ned = optical_to_ned @ poser.detector.optical_to_body.T
    return body_to_ned, centre - body_to_ned @ poser.detector.camera_origin_body


def _accuracy(poser: FramePoser, frames: list[BenchFrame]) -> dict[str, str]:
    """Position and attitude RMS of the dots' pose and of the markers-alone pose against the truth."""
    dots, markers = [], []
    tracked = Tracked(poser)
    for f in frames:
        result = tracked.process(f)
        if result.kind == "pose" and result.solution is not None:
            dots.append(_errors(result.solution.rotation, result.solution.position_ned, f))
        alone = _marker_pose(poser, f.image)
        if alone is not None:
            markers.append(_errors(*alone, f))
    return {"laser dots": _summary(dots, len(frames)), "markers alone (solvePnP)": _summary(markers, len(frames))}


def _errors(rotation: np.ndarray, position_ned: np.ndarray, f: BenchFrame) -> tuple[float, float]:
    return float(np.linalg.norm(position_ned - f.position_ned)), float(np.degrees(geometry.rotation_angle(rotation, f.rotation)))


def _summary(errors: list[tuple[float, float]], total: int) -> str:
    if not errors:
        return f"no pose on any of {total} frames"
    e = np.array(errors)
    rms = np.sqrt(np.mean(e ** 2, axis=0))
    return f"position RMS {rms[0] * 1e3:.1f} mm, attitude RMS {rms[1]:.2f} deg ({len(e)} of {total} frames posed)"
