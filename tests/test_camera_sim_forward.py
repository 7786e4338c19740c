"""The simulated camera as a fixed wing's forward camera over terrain (issue 15; sitl/camera_scene.py
with ``ground: terrain``): the horizon lies where the attitude puts it, and Lucas-Kanade flow between
two frames 0.1 s apart follows the true motion of the ground.

The camera is config/cameras/forward-90-640.yaml (640 x 480, fx = 320, fy = 240, no distortion) on
mount rpy [0, 0, 0] (along body x, image upright). Expected values come from the pinhole model
written out here: body FRD -> NED by ZYX Euler angles, optical = (body y, body z, body x).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.calibration import load_calibration
from companion.config import MountConfig
from companion.frames import euler_from_rotation, quat_from_euler, rotation_from_euler
from companion.nav.gnss_flow.flow import grid_flow
from companion.world import Bounds, World
from drivers.mount import Mount
from sitl.camera_sim import SimCameraSettings, SimulatedCamera

CALIBRATION = load_calibration(Path(__file__).parent.parent / "config" / "cameras" / "forward-90-640.yaml")
FX, FY, CX, CY = CALIBRATION.K[0, 0], CALIBRATION.K[1, 1], CALIBRATION.K[0, 2], CALIBRATION.K[1, 2]
FIELD = World(name="field", wall_angle_deg=90, bounds=Bounds((-1000.0, -1000.0), (1000.0, 1000.0)),
              start=(0.0, 0.0, 0.0), ground="terrain")
OPTICAL_IN_BODY = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # columns: optical x, y, z in FRD
SKY_OR_GROUND_GREY = 164.0  # between the ground at the horizon (its mean, 128) and the sky there (200)


@dataclass(frozen=True)
class Pose:
    """A truth sample: NED position (m), attitude [w, x, y, z] body FRD -> NED."""

    position_ned: np.ndarray
    quat: np.ndarray


def pose(position: tuple[float, float, float], rpy_deg: tuple[float, float, float]) -> Pose:
    return Pose(np.array(position, dtype=float), quat_from_euler(*np.radians(rpy_deg)))


def forward_camera(noise_sigma: float = 0.0) -> SimulatedCamera:
    settings = SimCameraSettings(fps=10.0, noise_sigma=noise_sigma)
    return SimulatedCamera("front", settings, CALIBRATION, Mount.from_config(MountConfig(rpy_deg=(0.0, 0.0, 0.0))),
                           FIELD, NoTruth())


class NoTruth:
    """TruthSource-like with no samples: the tests give :meth:`SimulatedCamera.render` its poses."""

    def at(self, t: float) -> Pose | None:
        return None


def horizon_rows(image: np.ndarray) -> np.ndarray:
    """Per column, the image row (px, to +-0.5) where the sky ends: the sky pixels of a column are
    the rows 0 .. floor(horizon), so the first ground row minus 0.5 estimates it (the ground just
    below the horizon is far away: its mean grey; further down its texture reaches the sky's greys)."""
    ground = image.astype(float) < SKY_OR_GROUND_GREY
    assert ground.any(axis=0).all() and not ground[0].any()
    return np.argmax(ground, axis=0) - 0.5


@pytest.mark.parametrize("pitch_deg", [-12.0, 0.0, 7.0, 20.0])
def test_the_horizon_row_moves_by_fy_tan_pitch(pitch_deg: float) -> None:
    image = forward_camera().render(0.0, pose((0.0, 0.0, -100.0), (0.0, pitch_deg, 40.0))).image
    expected = CY + FY * math.tan(math.radians(pitch_deg))  # nose up: the horizon drops in the image
    assert np.abs(horizon_rows(image) - expected).max() <= 0.5


def test_the_horizon_tilts_by_the_roll_and_the_sky_above_it_is_a_smooth_gradient() -> None:
    roll, pitch = math.radians(20.0), math.radians(5.0)
    image = forward_camera().render(0.0, pose((30.0, -20.0, -100.0), (20.0, 5.0, -60.0))).image
    rows = horizon_rows(image)
    # the horizon: y = tan(pitch) / cos(roll) - tan(roll) x in normalised image coordinates
    slope, at_cx = np.polyfit(np.arange(image.shape[1]) - CX, rows, 1)
    assert math.degrees(math.atan(-slope * FX / FY)) == pytest.approx(20.0, abs=0.1)  # 15.3 deg in pixels (fx != fy)
    assert at_cx == pytest.approx(CY + FY * math.tan(pitch) / math.cos(roll), abs=0.2)
    sky = np.arange(image.shape[0])[:, None] < rows[None, :] - 1
    assert image[sky].min() >= 200 and image[sky].max() <= 235
    steps = np.abs(np.diff(image.astype(float), axis=0))[sky[1:] & sky[:-1]]
    assert steps.max() <= 1.0  # no texture: one grey level between neighbours at most (rounding)


def test_grid_flow_between_frames_at_20_mps_from_100_m_matches_the_ground_motion() -> None:
    rpy_deg, rates_dps = (10.0, 3.0, 30.0), np.array([1.0, 0.5, 3.5])  # body p, q, r: a gentle banked turn
    dt, speed = 0.1, 20.0
    yaw = math.radians(rpy_deg[2])
    start = np.array([0.0, 0.0, -100.0])
    end = start + speed * dt * np.array([math.cos(yaw), math.sin(yaw), 0.0])
    body0 = rotation_from_euler(*np.radians(rpy_deg))
    body1 = body0 @ cv2.Rodrigues(np.radians(rates_dps) * dt)[0]
    cam = forward_camera(noise_sigma=2.0)
    frames = [cam.render(k * dt, Pose(p, quat_from_euler(*euler_from_rotation(body))), sequence=k).image
              for k, (p, body) in enumerate(((start, body0), (end, body1)))]
    flow = grid_flow(*frames)

    # the exact image motion of the ground point each grid point sees (the plane z = 0)
    points = flow.points_px
    rays = (body0 @ OPTICAL_IN_BODY @ np.column_stack(((points - [CX, CY]) / [FX, FY], np.ones(len(points)))).T).T
    depression = np.degrees(np.arcsin(rays[:, 2] / np.linalg.norm(rays, axis=1)))
    ground = start + (-start[2] / rays[:, 2])[:, None] * rays
    to_cam1 = (body1 @ OPTICAL_IN_BODY).T
    moved, _ = cv2.projectPoints(ground, cv2.Rodrigues(to_cam1)[0], -to_cam1 @ end, CALIBRATION.K, CALIBRATION.D)
    truth = moved.reshape(-1, 2) - points

    scored = depression >= 4.0  # ground whose 16 px window is clear of the horizon
    ok = scored & flow.valid
    errors = np.linalg.norm(flow.flows_px[ok] - truth[ok], axis=1)
    assert ok.sum() >= 0.9 * scored.sum() >= 700
    assert np.median(errors) < 0.25
    assert np.percentile(errors, 90) < 0.75
    assert np.abs(truth[ok]).max() > 3.0  # the ground does move (by up to 8 px at the bottom)
    high_sky = depression <= -6.0
    assert flow.valid[high_sky].mean() < 0.05  # the sky gives LK nothing to track

