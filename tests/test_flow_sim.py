"""The simulated optic-flow sensor (sitl/flow_sim.py, ``kind: flow, backend: sim``): its noiseless
field against the plane-induced homography of a known translation and rotation over flat ground,
the sky invalid, the seed's angle noise, timing, and the plugin registration.

Frames: NED world (ground at D = 0 unless stated), body FRD, OpenCV's optical frame; a forward
camera (mount rpy 0) as the seed's.
"""

from __future__ import annotations

import asyncio
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from companion.config import load_config
from companion.frames import quat_from_euler, rotation_from_euler
from companion.health import Health
from companion.messages import FlowField
from companion.sensors import SensorContext, build_driver
from drivers.checks import flow_problem
from drivers.mount import Mount
from sitl.flow_sim import SimFlowSettings, SimulatedFlowSensor

# v_sensor = M v_optical, written out here rather than taken from the module under test
OPTICAL_TO_FRD = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
FORWARD = Mount(np.eye(3), np.zeros(3))
GROUND_D = 0.0


@dataclass(frozen=True)
class Pose:
    """A truth sample: NED position (m), velocity (m/s), attitude [w, x, y, z] body FRD -> NED."""

    position_ned: np.ndarray
    velocity_ned: np.ndarray
    quat: np.ndarray


def pose(position: tuple[float, float, float], euler_deg: tuple[float, float, float]) -> Pose:
    return Pose(np.array(position, float), np.zeros(3), quat_from_euler(*np.radians(euler_deg)))


# 40 m above the ground, banked 15 deg, nose 5 deg down; 0.1 s later 2.5 m on and 0.3 m lower,
# turned 0.6 deg in yaw, 0.4 deg in roll and -0.3 deg in pitch
EARLIER = ((0.0, 0.0, -40.0), (15.0, -5.0, 30.0))
LATER = ((2.5 * math.cos(math.radians(30)), 2.5 * math.sin(math.radians(30)), -39.7), (15.4, -5.3, 30.6))


def sensor(truth: object = None, **settings: object) -> SimulatedFlowSensor:
    return SimulatedFlowSensor("flow", SimFlowSettings(**settings), FORWARD, truth)


def homography_flow(points_n: np.ndarray, earlier: tuple, later: tuple,
                    ground_d: float = GROUND_D) -> tuple[np.ndarray, np.ndarray]:
    """The motion field of the ground plane by its homography H = R + t n^T / d between the two
    camera frames (earlier camera: X; later: R X + t; the plane n . X = d in the earlier frame),
    and where it is defined (the ray meets the plane ahead; the point lies ahead of the later camera)."""
    (p0, e0), (p1, e1) = earlier, later
    r0 = rotation_from_euler(*np.radians(e0)) @ OPTICAL_TO_FRD  # optical -> NED
    r1 = rotation_from_euler(*np.radians(e1)) @ OPTICAL_TO_FRD
    rotation = r1.T @ r0
    t = r1.T @ (np.array(p0) - np.array(p1))
    normal = r0.T @ np.array([0.0, 0.0, 1.0])  # NED down in the earlier optical frame
    d = ground_d - p0[2]
    rays = np.column_stack((points_n, np.ones(len(points_n))))
    mapped = rays @ (rotation + np.outer(t, normal) / d).T
    valid = (rays @ normal > 0) & (mapped[:, 2] > 0)
    return mapped[:, :2] / mapped[:, 2:] - points_n, valid


def angles_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Signed angles from b to a, rad (N,)."""
    return np.arctan2(b[:, 0] * a[:, 1] - b[:, 1] * a[:, 0], np.einsum("ij,ij->i", a, b))


def test_the_noiseless_field_is_the_motion_field_of_the_ground_and_the_sky_is_invalid() -> None:
    s = sensor(angle_noise_deg=0.0)
    field = s.field(0.0, 0.1, pose(*EARLIER), pose(*LATER), sequence=7)
    assert isinstance(field, FlowField) and field.sequence == 7 and (field.t_earlier, field.t_capture) == (0.0, 0.1)
    assert field.points_n.shape == (45 * 45, 2)
    assert field.points_n.min(axis=0) == pytest.approx([-1.0, -1.0]) and field.points_n.max(axis=0) == pytest.approx(
        [1.0, 1.0])  # 90 x 90 deg: tan(45 deg) either side
    expected, defined = homography_flow(field.points_n, EARLIER, LATER)
    assert np.array_equal(field.valid, defined)
    assert 0.3 < field.valid.mean() < 0.8  # ground and sky both in view
    assert np.abs(field.flows_n[field.valid] - expected[field.valid]).max() < 1e-6
    assert np.all(np.isnan(field.flows_n[~field.valid]))  # the sky: no flow
    assert flow_problem(field, None) is None


def test_the_ground_height_setting_moves_the_plane() -> None:
    s = sensor(angle_noise_deg=0.0, ground_down_m=-10.0, grid=(9, 7), fov_deg=(60.0, 40.0))
    field = s.field(0.0, 0.1, pose(*EARLIER), pose(*LATER))
    assert field.points_n.shape == (63, 2) and field.points_n[:, 1].max() == pytest.approx(math.tan(math.radians(20)))
    expected, defined = homography_flow(field.points_n, EARLIER, LATER, ground_d=-10.0)
    assert np.array_equal(field.valid, defined) and defined.any()
    assert np.abs(field.flows_n[field.valid] - expected[field.valid]).max() < 1e-6


def test_a_camera_below_the_ground_sees_no_ground() -> None:
    field = sensor().field(0.0, 0.1, pose((0.0, 0.0, 1.0), (0.0, 0.0, 0.0)), pose((2.0, 0.0, 1.0), (0.0, 0.0, 0.0)))
    assert not field.valid.any() and flow_problem(field, None) is None


def test_the_noise_turns_each_flow_within_its_bound_keeps_its_length_and_is_seeded() -> None:
    clean = sensor(angle_noise_deg=0.0).field(0.0, 0.1, pose(*EARLIER), pose(*LATER), sequence=3)
    noisy = sensor(angle_noise_deg=2.5, seed=5).field(0.0, 0.1, pose(*EARLIER), pose(*LATER), sequence=3)
    v = clean.valid
    assert np.array_equal(noisy.valid, v)
    assert np.allclose(np.linalg.norm(noisy.flows_n[v], axis=1), np.linalg.norm(clean.flows_n[v], axis=1),
                       rtol=1e-12, atol=0)
    turned = np.degrees(angles_between(noisy.flows_n[v], clean.flows_n[v]))
    assert np.abs(turned).max() <= 2.5 + 1e-9
    assert np.abs(turned).max() > 2.4 and turned.min() < -2.4  # both ways, to the bound
    assert abs(turned.mean()) < 0.15 and np.std(turned) == pytest.approx(2.5 / math.sqrt(3), rel=0.1)  # uniform
    again = sensor(angle_noise_deg=2.5, seed=5).field(0.0, 0.1, pose(*EARLIER), pose(*LATER), sequence=3)
    other = sensor(angle_noise_deg=2.5, seed=5).field(0.0, 0.1, pose(*EARLIER), pose(*LATER), sequence=4)
    assert np.array_equal(again.flows_n[v], noisy.flows_n[v])
    assert not np.allclose(other.flows_n[v], noisy.flows_n[v])


class FakeTruth:
    """Truth from ``available_from`` (daemon s) on: flying north at 25 m/s, 40 m up."""

    def __init__(self, available_from: float) -> None:
        self.available_from = available_from

    def at(self, t: float) -> Pose | None:
        if t < self.available_from:
            return None
        return Pose(np.array([25.0 * t, 0.0, -40.0]), np.array([25.0, 0.0, 0.0]), quat_from_euler(0.0, 0.0, 0.0))


def test_fields_span_one_period_follow_the_grid_and_wait_for_truth_at_both_instants() -> None:
    async def run() -> tuple[list[FlowField], list[float], float]:
        loop = asyncio.get_running_loop()
        truth = FakeTruth(math.inf)
        s = sensor(truth, rate_hz=20.0, latency_s=0.01, angle_noise_deg=0.0)
        await s.open()
        truth.available_from = loop.time() + 0.06  # slot 1's later instant has truth, its earlier not
        fields, arrived = [], []
        for _ in range(3):
            fields.append(await s.read())
            arrived.append(loop.time())
        await s.close()
        return fields, arrived, truth.available_from

    fields, arrived, available_from = asyncio.run(run())
    assert fields[0].t_earlier >= available_from
    assert [f.sequence for f in fields] == list(range(fields[0].sequence, fields[0].sequence + 3))
    assert all(f.t_capture - f.t_earlier == pytest.approx(0.05) for f in fields)
    assert np.diff([f.t_capture for f in fields]) == pytest.approx(0.05)
    assert all(a >= f.t_capture + 0.01 - 1e-6 for f, a in zip(fields, arrived))
    # level flight north: the ground's flow expands from the horizon's centre (the FOE at (0, 0))
    f = fields[0]
    p, d = f.points_n[f.valid], f.flows_n[f.valid]
    assert np.all(p[:, 1] > 0) and np.allclose(p[:, 0] * d[:, 1] - p[:, 1] * d[:, 0], 0.0, atol=1e-3)


class _Link:
    """Stands in for the autopilot link: the truth source subscribes to it; nothing is sent."""

    def subscribe(self, name: str, handler: object) -> None:
        pass


def test_the_plugin_builds_a_flow_sensor(tmp_path: Path) -> None:
    (tmp_path / "c.yaml").write_text(
        "origin: {lat: 1.2966, lon: 103.7764, alt: 10.0}\nplugins: [sitl.sim_backends]\n"
        "mavlink: {streams: {sim_state: 50}}\n"
        "sensors:\n  of:\n    kind: flow\n    backend: sim\n    mount: {rpy_deg: [0, -10, 0]}\n"
        "    settings: {grid: [21, 15], angle_noise_deg: 1.0}\n")
    cfg = load_config(tmp_path / "c.yaml")
    driver = build_driver("of", cfg.sensors["of"], SensorContext(cfg, Health(lambda: 0.0), _Link()))
    backend = driver.backend
    assert isinstance(backend, SimulatedFlowSensor) and backend.settings.rate_hz == 10.0
    assert backend.points_n.shape == (21 * 15, 2) and backend.settings.fov_deg == (90.0, 90.0)
    assert np.allclose(backend.mount.rotation, rotation_from_euler(0.0, math.radians(-10.0), 0.0))
