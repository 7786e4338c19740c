"""The simulated GNSS receiver (sitl/gnss_sim.py): errors as configured, latency, denial, registration."""

from __future__ import annotations

import asyncio
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml

from companion.config import load_config
from companion.frames import ned_from_geodetic
from companion.health import Health
from companion.messages import GNSS_3D, GNSS_NO_FIX, GnssFix
from companion.schema import SchemaError, load_text
from companion.sensors import SensorContext, build_driver
from sitl.gnss_sim import SimGnssSettings, SimulatedGnss

ORIGIN = (1.2966, 103.7764, 10.0)  # lat deg, lon deg, alt m AMSL


@dataclass(frozen=True)
class Sample:
    """A truth sample: NED position (m) and velocity (m/s)."""

    position_ned: np.ndarray
    velocity_ned: np.ndarray


class FlyingNorth:
    """Truth of a vehicle passing the origin at daemon time ``t0`` (s), 2 m up, flying north at
    ``speed`` m/s, known from ``available_from`` on."""

    def __init__(self, t0: float = 0.0, speed: float = 1.5, available_from: float = -math.inf) -> None:
        self.t0, self.speed, self.available_from = t0, speed, available_from

    def at(self, t: float) -> Sample | None:
        if t < self.available_from:
            return None
        return Sample(np.array([self.speed * (t - self.t0), 3.0, -2.0]), np.array([self.speed, 0.0, 0.0]))


def opened(settings: SimGnssSettings, truth: FlyingNorth | None = None) -> SimulatedGnss:
    gnss = SimulatedGnss("gps", settings, ORIGIN, truth or FlyingNorth())
    asyncio.run(gnss.open())
    return gnss


def errors(gnss: SimulatedGnss, epochs: int) -> tuple[np.ndarray, np.ndarray, list[GnssFix]]:
    """(position errors (N, 3) NED m, velocity errors (N, 3) m/s, fixes) over ``epochs`` epochs."""
    fixes, position, velocity = [], [], []
    for k in range(epochs):
        epoch = k * gnss.grid.period_s
        truth = gnss.truth.at(epoch)
        fix = gnss.fix(epoch, truth, k)
        fixes.append(fix)
        position.append(ned_from_geodetic(fix.lat_deg, fix.lon_deg, fix.alt_m, ORIGIN) - truth.position_ned)
        velocity.append(fix.velocity_ned_mps - truth.velocity_ned)
    return np.array(position), np.array(velocity), fixes


def test_white_errors_have_the_configured_sigmas_and_the_fix_reports_them() -> None:
    settings = SimGnssSettings(horizontal_sigma_m=0.8, vertical_sigma_m=1.2, bias_share=0.0, velocity_sigma_mps=0.1,
                               seed=3)
    position, velocity, fixes = errors(opened(settings), 4000)
    assert position.std(axis=0) == pytest.approx([0.8, 0.8, 1.2], rel=0.05)
    assert np.all(np.abs(position.mean(axis=0)) < 4 * np.array([0.8, 0.8, 1.2]) / math.sqrt(4000))
    assert velocity.std(axis=0) == pytest.approx([0.1, 0.1, 0.1], rel=0.05)
    fix = fixes[0]
    assert (fix.fix_type, fix.h_acc_m, fix.v_acc_m, fix.speed_acc_mps, fix.satellites, fix.jamming) == \
        (GNSS_3D, 0.8, 1.2, 0.1, 12, False)


def test_the_bias_drifts_slowly_with_its_time_constant_and_keeps_the_total_sigma() -> None:
    settings = SimGnssSettings(horizontal_sigma_m=1.0, vertical_sigma_m=2.0, bias_share=1.0, bias_tau_s=4.0, seed=5)
    position, _, _ = errors(opened(settings), 20000)  # 4000 s: a thousand time constants
    assert position.std(axis=0) == pytest.approx([1.0, 1.0, 2.0], rel=0.1)
    lag = 0.2  # one epoch at 5 Hz
    correlation = [np.corrcoef(position[:-1, i], position[1:, i])[0, 1] for i in range(3)]
    assert correlation == pytest.approx([math.exp(-lag / 4.0)] * 3, abs=0.01)
    steps = np.diff(position, axis=0).std(axis=0)  # a random walk step: sigma sqrt(1 - exp(-2 lag / tau))
    assert steps == pytest.approx(np.array([1.0, 1.0, 2.0]) * math.sqrt(1 - math.exp(-2 * lag / 4.0)), rel=0.05)


def test_a_fix_describes_the_truth_latency_before_it_arrives() -> None:
    async def run() -> tuple[list[GnssFix], list[float], FlyingNorth]:
        loop = asyncio.get_running_loop()
        truth = FlyingNorth(t0=loop.time(), speed=2.0)
        gnss = SimulatedGnss("gps", SimGnssSettings(rate_hz=10, latency_s=0.15, horizontal_sigma_m=0.0,
                                                    vertical_sigma_m=0.0, velocity_sigma_mps=0.0), ORIGIN, truth)
        await gnss.open()
        fixes, arrived = [], []
        for _ in range(4):
            fixes.append(await gnss.read())
            arrived.append(loop.time())
        return fixes, arrived, truth

    fixes, arrived, truth = asyncio.run(run())
    assert np.diff([f.t_capture for f in fixes]) == pytest.approx(0.1)
    for fix, at in zip(fixes, arrived):
        fixed = ned_from_geodetic(fix.lat_deg, fix.lon_deg, fix.alt_m, ORIGIN)
        assert fixed == pytest.approx(truth.at(fix.t_capture).position_ned, abs=1e-4)  # the truth at its epoch
        assert at >= fix.t_capture + 0.15 - 1e-6  # ... which lies the latency before it arrived
        assert fixed[0] < truth.at(at).position_ned[0] - 2.0 * 0.15 + 1e-3  # 30 cm behind the vehicle by then
        assert fix.alt_m == pytest.approx(12.0, abs=1e-6)  # 2 m above the origin's 10 m AMSL


def test_denied_windows_and_commanded_denial_report_no_fix_with_jamming() -> None:
    async def run() -> list[GnssFix]:
        gnss = SimulatedGnss("gps", SimGnssSettings(rate_hz=20, latency_s=0.0, denied=((0.09, 0.19),)), ORIGIN,
                             FlyingNorth())
        await gnss.open()
        return [await gnss.read() for _ in range(6)]

    fixes = asyncio.run(run())  # epochs 0, 0.05, ... 0.25 s after open: 0.1 and 0.15 are denied
    assert [f.fix_type for f in fixes] == [GNSS_3D, GNSS_3D, GNSS_NO_FIX, GNSS_NO_FIX, GNSS_3D, GNSS_3D]
    denied = fixes[2]
    assert denied.jamming and not denied.has_position and denied.satellites == 0
    assert denied.velocity_ned_mps is None and denied.h_acc_m is None
    assert not any(f.jamming for f in fixes[:2] + fixes[4:])

    gnss = opened(SimGnssSettings())
    truth = gnss.truth.at(0.0)
    gnss.deny(True)
    assert [gnss.fix(0.2 * k, truth, k).fix_type for k in range(3)] == [GNSS_NO_FIX] * 3
    gnss.deny(False)
    assert gnss.fix(0.6, truth, 3).fix_type == GNSS_3D


def test_settings_are_checked_by_the_schema() -> None:
    s = load_text("{rate_hz: 10, denied: [[10, 20], [30.5, 40]], fix_type: 6}", SimGnssSettings)
    assert s.denied == ((10.0, 20.0), (30.5, 40.0)) and s.fix_type == 6
    for bad in ({"denied": [[20, 10]]}, {"denied": [[-1, 2]]}, {"denied": [[1, 2, 3]]}, {"rate_hz": 0},
                {"bias_share": 1.5}, {"fix_type": 1}, {"latency_s": -0.1}):
        with pytest.raises(SchemaError):
            load_text(yaml.safe_dump(bad), SimGnssSettings)


class _Link:
    """Stands in for the autopilot link: the truth source subscribes to it; nothing is sent."""

    def subscribe(self, name: str, handler: object) -> None:
        pass


def test_the_plugin_builds_a_receiver_around_the_configured_origin(tmp_path: Path) -> None:
    (tmp_path / "c.yaml").write_text(
        "origin: {lat: 47.0, lon: 8.0, alt: 400.0}\nplugins: [sitl.sim_backends]\n"
        "mavlink: {streams: {sim_state: 50}}\n"
        "sensors:\n  gps:\n    kind: gnss\n    backend: sim\n    settings: {rate_hz: 10, denied: [[5, 6]]}\n")
    cfg = load_config(tmp_path / "c.yaml")
    gnss = build_driver("gps", cfg.sensors["gps"], SensorContext(cfg, Health(lambda: 0.0), _Link())).backend
    assert isinstance(gnss, SimulatedGnss) and gnss.origin == (47.0, 8.0, 400.0)
    assert gnss.settings.denied == ((5.0, 6.0),) and gnss.grid.period_s == pytest.approx(0.1)
