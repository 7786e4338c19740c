"""Missions against the real SITL vehicle (lockstep, in-process daemon): trajectories flown with
the outer-loop controller, and the failsafes of the control issue.

The daemon flies on a TEST-ONLY truth pipeline (tests/sitl_helpers.py ``TruthPipeline``: truth
plus 1 cm noise) so that faults can be injected exactly when wanted: an estimate blackout, or a
wrong jump of the estimate. The vehicle fuses GPS, so the autopilot keeps its own estimate
while the companion's is gone ("brake and hold using the autopilot's own estimate"); its GPS
error (decimetres) is why positions are checked to 0.35 m here: the autopilot's loop holds
the vehicle where its GPS says the target is. Every time below is simulation time (the daemon
clock in lockstep).
"""

from __future__ import annotations

import signal
import socket
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from pymavlink.dialects.v20 import ardupilotmega as mav

from companion.config import load_config
from companion.mavlink.setpoints import IGNORE_ACCELERATION, IGNORE_POSITION, IGNORE_VELOCITY
from sitl.truth import TruthSource
from tests.conftest import free_port
from tests.sitl_helpers import (PipelineDaemon, Processes, TelemetryRecorder, TruthPipeline, read_log,
                                run_daemon_with_vehicle, vehicle_args, wait_for, write_config)

TAKEOFF = [{"wait_ready": {"timeout_s": 30}}, {"mode": "GUIDED"}, {"arm": {}},
           {"takeoff": {"altitude_m": 1.0, "timeout_s": 20}}]
LONG_LEG = {"fly": {"speed_mps": 0.5, "waypoints": [{"position": [8.0, 0.0, -1.0]}]}}
LOST_HOLD_S = 2.0
GPS_TOLERANCE_M = 0.35


def fly(tmp_path: Path, procs: Processes, steps: list[dict], seconds: float, sections: dict | None = None,
        make: Callable[[TruthSource], Any] | None = None, gcs: tuple[str, ...] = (),
        **faults: object) -> tuple[PipelineDaemon, dict]:
    """Fly ``steps`` (after wait_ready / GUIDED / arm / takeoff) for ``seconds`` of simulation on a
    TruthPipeline with ``faults``, or on the pipeline ``make`` builds; ``gcs``: the vehicle's
    ground-station links (pymavlink URLs)."""
    mission = tmp_path / "mission.yaml"
    mission.write_text(yaml.safe_dump({"name": "test", "steps": TAKEOFF + steps}, sort_keys=False))
    port = free_port()
    merged = {"mission": {"failsafe": {"lost_hold_s": LOST_HOLD_S}}, **(sections or {})}
    cfg = load_config(write_config(tmp_path / "companion.yaml", vehicle_port=port, sim_state_hz=50, mission=mission,
                                   sections=merged))
    log = tmp_path / "flight-log.json"
    vehicle = procs.start("vehicle", vehicle_args(port, log=log, lockstep=True, seconds=seconds, seed=4, gcs=gcs))
    daemon = PipelineDaemon(cfg, make or (lambda truth: TruthPipeline(truth, 5, **faults)))
    assert run_daemon_with_vehicle(daemon, vehicle, timeout_s=120) == 0
    assert vehicle.returncode == 0, procs.output("vehicle")
    return daemon, read_log(log)


def mode_entries(log: dict, name: str) -> list[float]:
    return [t for t, mode, _ in log["modes"] if mode == name]


def truth_at(log: dict, t: float) -> np.ndarray:
    tt = np.asarray(log["truth"]["t"])
    pos = np.asarray(log["truth"]["pos_ned"])
    return np.array([np.interp(t, tt, pos[:, k]) for k in range(3)])


def truth_speed_xy(log: dict, t0: float, t1: float) -> float:
    """Largest horizontal ground speed (m/s) of the true vehicle between t0 and t1."""
    tt = np.asarray(log["truth"]["t"])
    v = np.asarray(log["truth"]["vel_ned"])[(tt >= t0) & (tt <= t1)]
    return float(np.max(np.hypot(v[:, 0], v[:, 1])))


def setpoints_between(log: dict, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
    """(type masks, positions) of the setpoints the autopilot received in [t0, t1]."""
    sp = log["setpoints"]
    t = np.asarray(sp["t_rx"])
    keep = (t >= t0) & (t <= t1)
    return np.asarray(sp["type_mask"])[keep], np.asarray(sp["pos"])[keep]


def position_only(masks: np.ndarray) -> bool:
    return bool(np.all(masks & (IGNORE_VELOCITY | IGNORE_ACCELERATION) == IGNORE_VELOCITY | IGNORE_ACCELERATION)
                and np.all(masks & IGNORE_POSITION == 0))


def test_a_trajectory_is_flown_with_feed_forward_setpoints_and_the_payload_released(
        tmp_path: Path, procs: Processes) -> None:
    steps = [{"fly": {"speed_mps": 0.5, "waypoints": [{"position": [2.0, 0.0, -1.0]},
                                                       {"position": [2.0, 2.0, -1.2], "hold_s": 2.0}]}},
             {"payload_drop": {"hold_s": 1.0}}, {"land": {"timeout_s": 30}}]
    daemon, log = fly(tmp_path, procs, steps, 50)
    assert daemon.mission.status == "completed", daemon.mission.snapshot()
    assert not daemon.mission.ctx.failsafes
    masks = np.asarray(log["setpoints"]["type_mask"])
    assert np.any(masks & 0b111_111_111 == 0)  # position + velocity + acceleration (RPT feed-forward)
    np.testing.assert_allclose(truth_at(log, mode_entries(log, "LAND")[0]), [2.0, 2.0, -1.2], atol=GPS_TOLERANCE_M)
    servo = [c for c in log["commands"] if c[1] == mav.MAV_CMD_DO_SET_SERVO]
    assert [c[2] for c in servo] == [mav.MAV_RESULT_ACCEPTED]
    assert not log["modes"][-1][2]  # landed and disarmed


def test_estimate_lost_mid_flight_brakes_holds_on_the_autopilot_then_lands(tmp_path: Path, procs: Processes) -> None:
    blackout_at = 18.0
    daemon, log = fly(tmp_path, procs, [LONG_LEG, {"land": {"timeout_s": 30}}], 40, blackout=(blackout_at, 1e9))
    mission = daemon.mission
    assert mission.status == "failed" and "estimate lost" in mission.reason, mission.snapshot()
    assert mission.mission.steps[mission.step_index].kind == "fly"  # it happened while flying the leg
    lost = mission.ctx.failsafes[0]
    assert lost["kind"] == "estimate_lost"
    assert blackout_at < lost["t"] <= blackout_at + 0.5 + 0.05  # estimate_timeout_s 0.5
    assert truth_speed_xy(log, lost["t"] - 1.0, lost["t"]) > 0.3  # it was flying when it happened
    land_at = mode_entries(log, "LAND")[0]
    assert land_at == pytest.approx(lost["t"] + LOST_HOLD_S, abs=0.2)
    masks, positions = setpoints_between(log, lost["t"] + 0.05, land_at)
    assert len(masks) >= 10 * LOST_HOLD_S - 2 and position_only(masks)  # a hold target, kept alive
    assert truth_speed_xy(log, land_at - 0.5, land_at) < 0.15  # braked and held
    assert np.hypot(*(truth_at(log, land_at)[:2] - positions[-1][:2])) < GPS_TOLERANCE_M
    assert not log["modes"][-1][2]  # landed and disarmed


def test_a_short_estimate_loss_is_ridden_out_and_the_rest_of_the_trajectory_replanned(
        tmp_path: Path, procs: Processes) -> None:
    daemon, log = fly(tmp_path, procs, [LONG_LEG, {"land": {"timeout_s": 30}}], 60, blackout=(18.0, 19.0))
    mission = daemon.mission
    assert mission.status == "completed", mission.snapshot()
    assert [f["kind"] for f in mission.ctx.failsafes] == ["estimate_lost"]
    assert not mode_entries(log, "LAND") or mode_entries(log, "LAND")[0] > 24.0  # not the failsafe landing
    np.testing.assert_allclose(truth_at(log, mode_entries(log, "LAND")[0])[:2], [8.0, 0.0], atol=GPS_TOLERANCE_M)


def test_a_loss_during_a_hold_resumes_the_rest_of_the_hold_then_the_remaining_waypoints(
        tmp_path: Path, procs: Processes) -> None:
    steps = [{"fly": {"speed_mps": 0.5, "waypoints": [{"position": [2.0, 0.0, -1.0], "hold_s": 6.0},
                                                       {"position": [2.0, 2.0, -1.0]}]}},
             {"land": {"timeout_s": 30}}]
    daemon, log = fly(tmp_path, procs, steps, 60, blackout=(14.0, 15.0))  # arrives at the first about 12 s
    mission = daemon.mission
    assert mission.status == "completed", mission.snapshot()
    lost = mission.ctx.failsafes[0]
    assert [f["kind"] for f in mission.ctx.failsafes] == ["estimate_lost"]
    # the loss came during the hold at the first waypoint, and the vehicle stayed there afterwards
    # for the rest of the hold before flying to the second one
    at_first = [t for t in np.arange(10.0, 60.0, 0.25) if np.hypot(*(truth_at(log, t)[:2] - [2.0, 0.0])) < 0.3]
    assert at_first[0] < lost["t"] < at_first[-1]
    assert at_first[-1] - at_first[0] >= 6.0 + 1.0  # the whole hold, plus the ride-out
    np.testing.assert_allclose(truth_at(log, mode_entries(log, "LAND")[0])[:2], [2.0, 2.0], atol=GPS_TOLERANCE_M)


def test_tracking_off_through_an_opening_stops_and_holds_before_it(tmp_path: Path, procs: Processes) -> None:
    jump_at = 18.0  # the estimate moves 0.3 m sideways: the vehicle is off the line through the opening
    steps = [{"fly": {"speed_mps": 0.5, "waypoints": [
        {"position": [4.0, 0.0, -1.0], "pass_tolerance_m": 0.15, "name": "door"}, {"position": [6.0, 0.0, -1.0]}]}},
        {"land": {"timeout_s": 30}}]
    daemon, log = fly(tmp_path, procs, steps, 30, offset=(jump_at, (0.0, 0.3, 0.0)))
    mission = daemon.mission
    assert mission.status == "failed" and "pass door" in mission.reason, mission.snapshot()
    assert [f["kind"] for f in mission.ctx.failsafes] == ["pass_tolerance"]
    stopped = mission.ctx.failsafes[0]["t"]
    assert stopped >= jump_at and 2.5 < truth_at(log, stopped)[0] < 4.0  # on entering the 1 m zone before it
    assert not mode_entries(log, "LAND") and log["modes"][-1][2]  # holding, still flying
    assert truth_at(log, log["sim_seconds"])[0] < 4.0  # it did not go through


def test_a_geofence_breach_stops_the_flight_and_holds_without_landing(tmp_path: Path, procs: Processes) -> None:
    fence = {"box_ned_m": [[-1.0, -1.0], [9.0, 1.0]], "inset_m": 0.3}
    jump_at = 18.0  # the estimate jumps 10 m north (a wrong relocalization): outside the fence
    daemon, log = fly(tmp_path, procs, [LONG_LEG, {"land": {"timeout_s": 30}}], 30,
                      sections={"mission": {"failsafe": {"lost_hold_s": LOST_HOLD_S}, "geofence": fence}},
                      offset=(jump_at, (10.0, 0.0, 0.0)))
    mission = daemon.mission
    assert mission.status == "failed" and "geofence breach" in mission.reason, mission.snapshot()
    assert [f["kind"] for f in mission.ctx.failsafes] == ["geofence"]
    assert jump_at <= mission.ctx.failsafes[0]["t"] <= jump_at + 0.1
    assert not mode_entries(log, "LAND") and log["modes"][-1][2]  # still flying: the pilot decides
    masks, positions = setpoints_between(log, jump_at + 0.1, 30.0)
    assert position_only(masks)
    assert len(np.unique(positions, axis=0)) == 1  # one hold target, kept alive
    for t in np.arange(mission.ctx.failsafes[0]["t"] + 2.0, log["sim_seconds"], 0.5):  # holding there
        assert np.hypot(*(truth_at(log, t)[:2] - positions[-1][:2])) < GPS_TOLERANCE_M


def test_a_trajectory_leaving_the_geofence_is_refused_before_the_vehicle_moves(tmp_path: Path, procs: Processes) -> None:
    fence = {"box_ned_m": [[-1.0, -1.0], [5.0, 1.0]], "inset_m": 0.3}
    daemon, log = fly(tmp_path, procs, [LONG_LEG, {"land": {"timeout_s": 30}}], 20,
                      sections={"mission": {"geofence": fence}})
    mission = daemon.mission
    assert mission.status == "failed" and "leaves the geofence" in mission.reason, mission.snapshot()
    assert "x -0.7..4.7" in mission.reason
    assert log["modes"][-1][2] and not mode_entries(log, "LAND")  # holding where it took off
    assert np.hypot(*truth_at(log, log["sim_seconds"])[:2]) < GPS_TOLERANCE_M


def test_position_only_output_flies_the_trajectory_with_position_targets(tmp_path: Path, procs: Processes) -> None:
    steps = [{"fly": {"speed_mps": 0.5, "waypoints": [{"position": [3.0, 0.0, -1.0]}]}}, {"land": {"timeout_s": 30}}]
    daemon, log = fly(tmp_path, procs, steps, 40, sections={"control": {"output": "position_only"}})
    assert daemon.mission.status == "completed", daemon.mission.snapshot()
    land_at = mode_entries(log, "LAND")[0]
    masks, _ = setpoints_between(log, 8.0, land_at)
    assert len(masks) > 100 and position_only(masks)
    np.testing.assert_allclose(truth_at(log, land_at)[:2], [3.0, 0.0], atol=GPS_TOLERANCE_M)


def test_the_daemon_stopping_in_flight_leaves_a_hold_target_and_lands(tmp_path: Path, procs: Processes) -> None:
    """Real time, separate processes: SIGTERM to `companion run` while it flies a trajectory."""
    mission = tmp_path / "mission.yaml"
    mission.write_text(yaml.safe_dump({"name": "test", "steps": TAKEOFF + [LONG_LEG]}, sort_keys=False))
    port, zenoh_port = free_port(), free_port(socket.SOCK_STREAM)
    cfg = write_config(tmp_path / "companion.yaml", vehicle_port=port, zenoh_port=zenoh_port, mission=mission,
                       telemetry={"status_hz": 5})
    log = tmp_path / "flight-log.json"
    vehicle = procs.start("vehicle", vehicle_args(port, log=log))
    daemon = procs.start("daemon", [sys.executable, "-m", "companion.cli", "run", "-c", str(cfg)])
    telemetry = TelemetryRecorder(zenoh_port)
    try:
        wait_for(lambda: telemetry.get("mission").get("step_kind") == "fly", 40, "the fly step")
        # The 8 m leg at 0.5 m/s is a ~35 s minimum-snap segment whose speed peaks mid-way: 16 s in it
        # flies at ~0.45 m/s (12 s in, only ~0.3 m/s: too close to the check below).
        time.sleep(16.0)
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(5) == 0
        time.sleep(4.0)  # the vehicle, on its own
        assert Processes.stop(vehicle) == 0
    finally:
        telemetry.close()
    flight = read_log(log)
    land_at = mode_entries(flight, "LAND")[0]
    masks, _ = setpoints_between(flight, land_at - 1.0, land_at)
    assert truth_speed_xy(flight, land_at - 1.5, land_at - 1.0) > 0.3  # it was flying
    assert position_only(masks[-1:]) and not position_only(masks[:1])  # the last target was a hold
    assert "switching to LAND" in procs.output("daemon")
    assert truth_speed_xy(flight, land_at + 2.0, flight["sim_seconds"]) < 0.15  # braked, descending in place
