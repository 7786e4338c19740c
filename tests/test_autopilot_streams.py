"""Stream negotiation against the SITL vehicle process: per-message intervals where the firmware
takes them, ArduPilot's legacy stream groups where it does not, and the IMU from whichever
message came (in the units the fusion expects)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from companion.config import load_config
from pymavlink.dialects.v20 import ardupilotmega as mav
from tests.conftest import free_port
from tests.sitl_helpers import (PipelineDaemon, Processes, TruthPipeline, read_log, run_daemon_with_vehicle,
                                vehicle_args, write_config)

SIM_SECONDS = 8.0


def run_on_ground(tmp_path: Path, procs: Processes, legacy_streams: bool = False,
                  refuse_intervals: tuple[int, ...] = ()) -> tuple[PipelineDaemon, dict]:
    """The daemon (truth test pipeline, no mission) against a lockstep vehicle for SIM_SECONDS."""
    port = free_port()
    cfg = load_config(write_config(tmp_path / "companion.yaml", vehicle_port=port, mission=False, sim_state_hz=50))
    log = tmp_path / "flight-log.json"
    vehicle = procs.start("vehicle", vehicle_args(port, log=log, lockstep=True, seconds=SIM_SECONDS,
                                                  position_source="extnav", gps=False,
                                                  legacy_streams=legacy_streams, refuse_intervals=refuse_intervals))
    daemon = PipelineDaemon(cfg, lambda truth: TruthPipeline(truth, 1))
    assert run_daemon_with_vehicle(daemon, vehicle) == 0
    assert vehicle.returncode == 0, procs.output("vehicle")
    return daemon, read_log(log)


def assert_imu_is_specific_force_at_rest(daemon: PipelineDaemon) -> None:
    samples = list(daemon.state.imu)
    assert len(samples) > 20
    accel = np.array([s.accel_body for s in samples])
    gyro = np.array([s.gyro_body for s in samples])
    np.testing.assert_allclose(accel.mean(axis=0), [0.0, 0.0, -9.81], atol=0.15)  # m/s^2, standing level
    assert np.abs(gyro.mean(axis=0)).max() < 0.02  # rad/s
    assert all(b.t > a.t for a, b in zip(samples, samples[1:]))


def test_current_firmware_gets_message_intervals_and_highres_imu(tmp_path: Path, procs: Processes) -> None:
    daemon, log = run_on_ground(tmp_path, procs, legacy_streams=False)

    chosen = daemon.streams.chosen
    assert chosen["imu"] == "HIGHRES_IMU @ 50 Hz" and chosen["sim_state"] == "SIM_STATE @ 50 Hz"
    assert chosen["attitude"] == "ATTITUDE @ 50 Hz" and None not in chosen.values()
    assert daemon.state.imu_source == "HIGHRES_IMU"
    assert daemon.state.firmware is not None and daemon.state.firmware.label == "ArduPilot copter 4.5.7"
    assert_imu_is_specific_force_at_rest(daemon)
    assert log["external_nav"]["first_in_use_at"] is not None


def test_firmware_without_message_intervals_gets_the_legacy_stream_groups(tmp_path: Path, procs: Processes) -> None:
    daemon, log = run_on_ground(tmp_path, procs, legacy_streams=True)

    chosen = daemon.streams.chosen
    assert chosen["imu"] == "RAW_IMU via REQUEST_DATA_STREAM"  # mG / mrad/s, converted
    assert chosen["sim_state"] == "SIM_STATE via REQUEST_DATA_STREAM"
    assert daemon.state.imu_source == "RAW_IMU"
    assert_imu_is_specific_force_at_rest(daemon)
    # the estimates flowed on the legacy streams (truth from SIM_STATE), and the autopilot used them
    assert log["external_nav"]["first_in_use_at"] is not None
    assert len(log["vision_position"]["t_rx"]) > 20 * 4


def test_a_refused_imu_stream_falls_back_to_scaled_imu_and_a_need_without_options_is_reported(
        tmp_path: Path, procs: Processes) -> None:
    # as ArduPilot 4.0: no HIGHRES_IMU; and no SIM_STATE, with no SIMSTATE either on this vehicle
    daemon, _ = run_on_ground(tmp_path, procs, refuse_intervals=(mav.MAVLINK_MSG_ID_HIGHRES_IMU,
                                                                 mav.MAVLINK_MSG_ID_SIM_STATE))

    chosen = daemon.streams.chosen
    assert chosen["imu"] == "SCALED_IMU @ 50 Hz" and daemon.state.imu_source == "SCALED_IMU"
    assert_imu_is_specific_force_at_rest(daemon)
    assert chosen["sim_state"] is None  # SIMSTATE + SCALED_PRESSURE: this vehicle has no SIMSTATE
    streams = daemon.health.snapshot()["components"]["streams"]
    assert streams["state"] == "degraded" and "sim_state" in streams["reason"]
