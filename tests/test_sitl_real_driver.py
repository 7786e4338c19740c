"""The real Hokuyo driver end to end in SITL, through the SCIP bridge (sitl/scip_bridge.py).

- In-process: a :class:`sitl.scip_bridge.BridgedScanner` fed with a known moving truth serves
  SCIP 2.0 on a free port and the real driver (drivers/hokuyo.py) reads it. Every beam's range
  must be what the world looks like from the pose at the time the *driver* assigns to that beam
  (its capture time from the sensor's 24-bit clock plus the beam's step time): the emulated
  clock, the truth clock and the per-beam rendering agree.
- As deployed, in real time: ``companion sitl -c <copy of config/sitl-real-driver.yaml on free
  ports> --mission hover --seconds 30 --report``: the vehicle, the bridge and the daemon (whose
  scanners are ``backend: real``) as processes; the report is scored against the vehicle's truth.
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from companion.config import MountConfig
from companion.frames import quat_from_euler
from drivers.hokuyo import HokuyoScip, HokuyoSettings
from sitl.lidar_sim import SimLidarSettings
from drivers.mount import Mount
from sitl.harness import TelemetryListener
from sitl.scip_bridge import BridgedScanner, SensorSpec, SweptLidar, TruthHistory
from companion.world import load_world
from tests.conftest import REPO
from tests.sitl_helpers import real_driver_config

ARENA = REPO / "config" / "worlds" / "arena.yaml"
SITL_SECONDS = 30


# -- in-process: timestamps and rendering agree ------------------------------------------------

VELOCITY_NED = np.array([1.0, 0.0, 0.0])  # m/s: a 1 ms timing error moves the walls by ~1 mm
START_NED = np.array([1.5, 2.5, -1.0])  # the south-west room of the arena, 1 m up
YAW_RATE = 0.5  # rad/s


def moving_pose(t: float) -> tuple[np.ndarray, np.ndarray]:
    return START_NED + VELOCITY_NED * t, np.array(quat_from_euler(0.02, -0.03, YAW_RATE * t))


async def driver_vs_truth(model: str, mount: MountConfig, seconds: float) -> tuple[np.ndarray, int]:
    """Ranges the real driver read from the bridge minus the noise-free ranges at the driver's
    beam times (m, beams valid in both), and the number of scans read."""
    loop = asyncio.get_running_loop()
    world = load_world(ARENA)
    truth = TruthHistory()
    t0 = loop.time()

    async def feed() -> None:  # SIM_STATE at 100 Hz, stamped on arrival like the bridge's receiver
        while True:
            now = loop.time()
            position, quat = moving_pose(now - t0)
            truth.add(now, position, VELOCITY_NED, quat)
            await asyncio.sleep(0.01)

    feeder = asyncio.create_task(feed())
    scanner = BridgedScanner(SensorSpec("lidar", model, mount, 0), world, truth, 0, loop.time, noise_scale=0.0)
    await scanner.start()
    driver = HokuyoScip(HokuyoSettings(host="127.0.0.1", tcp_port=scanner.port, model=model), "lidar")
    reference = SweptLidar("reference", SimLidarSettings(model=model, noise_scale=0.0),  # type: ignore[arg-type]
                           Mount.from_config(mount), world, truth)
    errors = []
    scans = 0
    try:
        await driver.open()
        while loop.time() - t0 < seconds:
            scan = await driver.read()
            scans += 1
            if scan.valid_count == 0:  # before the first truth: the scanner sees nothing
                continue
            times = scan.t_capture + np.linspace(0.0, scan.sweep_s, len(scan.angles_rad))
            poses = [moving_pose(t - t0) for t in times]
            expected = reference.render_sweep(times, np.array([p for p, _ in poses]), np.array([q for _, q in poses]))
            both = expected.valid & scan.valid
            errors.append(scan.ranges_m[both] - expected.ranges_m[both])
    finally:
        await driver.close()
        await scanner.close()
        feeder.cancel()
    return np.concatenate(errors), scans


@pytest.mark.parametrize(("model", "mount"), [
    ("UTM-30LX", MountConfig((0.0, 0.0, -0.10), (0.0, 0.0, 0.0))),
    ("URG-04LX", MountConfig((0.05, 0.0, -0.05), (90.0, 0.0, 0.0))),
])
def test_the_driver_sees_each_beam_from_the_pose_at_its_own_time(model: str, mount: MountConfig) -> None:
    errors, scans = asyncio.run(driver_vs_truth(model, mount, seconds=1.5))
    assert scans >= 10
    error = np.abs(errors)
    # mm ranges on the wire, ms timestamps; a 5 ms error would give a median of ~3 mm (UTM-30LX).
    # A few beams grazing an edge jump to another surface for any tiny pose difference.
    assert np.median(error) < 0.001
    assert np.mean(error < 0.005) > 0.99


# -- configuration -------------------------------------------------------------------------------


def test_scip_sensors_must_be_real_loopback_scanners_of_an_emulated_model(tmp_path: Path) -> None:
    path, raw = real_driver_config(tmp_path)
    cases = [
        (("sitl", "scip_sensors"), ["lidar_h", "camera"], "sitl.scip_sensors[1]: 'camera' is not a lidar with backend: real"),
        (("sensors", "lidar_h", "settings", "host"), "192.168.0.10", "set settings.host: 127.0.0.1"),
        (("sensors", "lidar_h", "settings", "model"), None, "settings.model must name the emulated model"),
        (("sensors", "lidar_v", "settings", "tcp_port"), raw["sensors"]["lidar_h"]["settings"]["tcp_port"],
         "sitl.scip_sensors[1]: sensor 'lidar_v': settings.tcp_port"),
        (("sitl", "scip_sensors"), ["lidar_h", "lidar_h"], "sitl.scip_sensors[1]: 'lidar_h' is named twice"),
    ]
    for keys, value, message in cases:
        broken = yaml.safe_load(path.read_text())
        node = broken
        for key in keys[:-1]:
            node = node[key]
        node[keys[-1]] = value
        bad = tmp_path / "bad.yaml"
        bad.write_text(yaml.safe_dump(broken, sort_keys=False))
        proc = subprocess.run([sys.executable, "-m", "companion.cli", "check-config", str(bad)],
                              cwd=REPO, capture_output=True, text=True, timeout=30)
        assert proc.returncode == 2 and message in proc.stderr, (keys, proc.stderr)
    assert subprocess.run([sys.executable, "-m", "companion.cli", "check-config", str(REPO / "config" / "sitl-real-driver.yaml")],
                          cwd=REPO, capture_output=True, timeout=30).returncode == 0


def test_lockstep_refuses_the_wall_clock_bridge(tmp_path: Path) -> None:
    path, _ = real_driver_config(tmp_path)
    proc = subprocess.run([sys.executable, "-m", "companion.cli", "sitl", "-c", str(path), "--lockstep",
                           "--seconds", "1"], cwd=REPO, capture_output=True, text=True, timeout=30)
    assert proc.returncode == 2
    assert "sitl.scip_sensors needs the built-in vehicle in real time" in proc.stderr


# -- as deployed: companion sitl with the bridge -------------------------------------------------


def test_hover_mission_flies_on_the_real_driver_through_the_scip_bridge(tmp_path: Path) -> None:
    path, raw = real_driver_config(tmp_path)
    report_path = tmp_path / "report.json"
    listener = TelemetryListener(raw["telemetry"]["listen"], raw["vehicle"]["sysid"])
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "companion.cli", "sitl", "-c", str(path), "--mission", "hover",
             "--seconds", str(SITL_SECONDS), "--report", str(report_path)],
            cwd=REPO, capture_output=True, text=True, timeout=SITL_SECONDS + 40)
        telemetry = listener.snapshot()
    finally:
        listener.close()
    output = proc.stdout + proc.stderr
    assert proc.returncode == 0, output[-4000:]
    report = json.loads(report_path.read_text())

    assert report["lockstep"] is False and report["seconds"] == SITL_SECONDS
    assert report["control"]["mission_completed"] is True
    assert report["autopilot"]["origin_confirmed"] is True
    assert report["autopilot"]["external_nav_in_use"] is True  # flown on the estimate from the real driver's scans
    assert report["estimate"]["position_rms_m"] < 0.05
    assert report["estimate"]["height_rms_m"] < 0.05
    assert report["estimate"]["lost_seconds"] == 0.0

    # The daemon read both scanners with the real driver over TCP, without a loss or a bad frame.
    for name in ("lidar_h", "lidar_v"):
        port = raw["sensors"][name]["settings"]["tcp_port"]
        health = telemetry["health"]["components"][f"sensor:{name}"]
        assert health["state"] == "ok" and f"Hokuyo scanner on 127.0.0.1:{port}" in health["reason"], health
    drivers = telemetry["system"]["drivers"]
    assert drivers["lidar_h"]["messages"] > 0.8 * 40 * (SITL_SECONDS - 5)  # 40 Hz
    assert drivers["lidar_v"]["messages"] > 0.8 * 10 * (SITL_SECONDS - 5)  # 10 Hz
    for name, stats in drivers.items():
        assert stats["reconnects"] == 0 and stats["corrupt_frames"] == 0, (name, stats)
    assert "sitl.scip_bridge: stopped" in output
