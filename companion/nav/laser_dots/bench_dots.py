"""Timings and accuracy of the laser-dot pipeline on simulated frames (for ``companion bench``).

Frames: the simulated downward camera of config/sitl-laser-dots.yaml (640 x 480, 135-degree
pinhole, 2 grey levels of pixel noise, 0.5 px laser speckle) over the Fig. 4 hall
(config/worlds/fig4.yaml), at the scenario's two heights (0.82 and 1.63 m) with a few degrees of
tilt and any heading. Each stage is timed on the same frames; the accuracy of the dots' pose is
set beside the camera pose from the floor markers alone (OpenCV solvePnP: IPPE_SQUARE on one
marker, iterative on several) against the simulator's truth, so a user sees what the lasers buy.
Imports the simulator (a bench tool, allowed to).
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
from companion.nav.laser_dots.frame_pose import FramePoser
from companion.nav.laser_dots.pipeline import frame_poser
from companion.timing import time_stage
from companion.world import load_world

CONFIG = Path(__file__).resolve().parents[3] / "config" / "sitl-laser-dots.yaml"
HEIGHTS_M = (0.82, 1.63)
FRAMES = 24  # rendered frames the stages cycle through and the accuracy is measured on


@dataclass(frozen=True)
class BenchFrame:
    image: np.ndarray
    rotation: np.ndarray  # true body FRD -> NED
    position_ned: np.ndarray  # true, m


def bench_frames(n: int = FRAMES, seed: int = 0) -> tuple[FramePoser, list[BenchFrame]]:
    """The config's pipeline (as a FramePoser) and ``n`` frames its simulated camera renders."""
    from sitl.calibration_sweep import laser_dots_camera
    from sitl.truth import TruthSample

    cfg = load_config(CONFIG)
    section = cfg.pipelines.enabled["laser_dots"]
    camera = laser_dots_camera(cfg)
    world = cfg.load_referenced("pipelines.laser_dots.world", section.world, load_world)
    poser = frame_poser(section, camera.calibration, camera.mount, world.floor_markers)
    rng = np.random.default_rng(seed)
    frames = []
    for k in range(n):
        rpy = np.radians([rng.normal(0, 2), rng.normal(0, 2), rng.uniform(-180, 180)])
        position = np.array([rng.uniform(1, 58), rng.uniform(-0.3, 1.8), -HEIGHTS_M[k % len(HEIGHTS_M)]])
        image = camera.render(0.0, TruthSample(0.0, position, np.zeros(3), quat_from_euler(*rpy)), None, k).image
        frames.append(BenchFrame(image, rotation_from_euler(*rpy), position))
    return poser, frames


def run_dots_bench(repeat: int) -> tuple[dict[str, tuple[float, float]], dict[str, str]]:
    """({stage: (median ms, p99 ms)}, {figure: text}) on the bench frames."""
    poser, frames = bench_frames()
    cycle: Iterator[BenchFrame] = itertools.cycle(frames)
    stages = {
        "laser_dots.detect (3 dots, 640x480)": lambda: poser.detector.detect(next(cycle).image),
        "laser_dots.markers (ArUco + homography)": lambda: poser.mapper.find(next(cycle).image),
        "laser_dots.frame (detect, map, solve, covariance)":
            lambda: (f := next(cycle), poser.process(f.image, f.rotation)),
        "markers alone: solvePnP camera pose": lambda: _marker_pose(poser, next(cycle).image),
    }
    timings = {name: time_stage(fn, repeat) for name, fn in stages.items()}
    return timings, _accuracy(poser, frames)


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
    for f in frames:
        result = poser.process(f.image, f.rotation)
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
