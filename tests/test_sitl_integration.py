"""The daemon against the real SITL vehicle process (python -m sitl.vehicle), MAVLink over loopback.

Two set-ups, both on free ports:

- in-process and deterministic: the real :class:`companion.daemon.Daemon` (with a TEST-ONLY
  truth+noise pipeline, tests/sitl_helpers.py) on a :class:`companion.clock.LockstepEventLoop`,
  against a ``--lockstep`` vehicle process; outcomes are scored from the vehicle's flight log
  against its ground truth;
- as deployed, in real time: ``companion run -c cfg`` and the vehicle as subprocesses, observed
  through the daemon's zenoh telemetry, a pymavlink ground station on a vehicle GCS link, and the
  flight log.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from companion.config import load_config
from pymavlink.dialects.v20 import ardupilotmega as mav
from sitl.report import capture_times, score_estimate
from tests.conftest import free_port
from tests.sitl_helpers import (
    GroundStation,
    PipelineDaemon,
    Processes,
    TelemetryRecorder,
    TruthPipeline,
    read_log,
    run_daemon_with_vehicle,
    vehicle_args,
    wait_for,
    write_config,
)

SIM_SECONDS = 25.0
PIPELINE_SEED = 7
VEHICLE_SEED = 3
LOITER = 5  # ArduCopter custom_mode


# -- in-process daemon + lockstep vehicle ----------------------------------------------------


class RecordingDaemon(PipelineDaemon):
    """Also keeps every STATUSTEXT the daemon sends (to the autopilot, which forwards it to the GCS)."""

    def __init__(self, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
        super().__init__(*args, **kwargs)
        self.texts: list[str] = []

    def statustext(self, text: str, severity: int = mav.MAV_SEVERITY_WARNING) -> None:
        self.texts.append(text)
        super().statustext(text, severity)


def fly_extnav(tmp_path: Path, procs: Processes, start: str | None = None,
               **pipeline_options: object) -> tuple[RecordingDaemon, dict]:
    """The hover mission on external navigation only (no GPS), in lockstep, with a truth pipeline.

    Returns the daemon after its run (exit 0 asserted) and the vehicle's flight log.
    """
    port = free_port()
    cfg = load_config(write_config(tmp_path / "companion.yaml", vehicle_port=port, sim_state_hz=50))
    log = tmp_path / "flight-log.json"
    vehicle = procs.start("vehicle", vehicle_args(
        port, log=log, lockstep=True, seconds=SIM_SECONDS, position_source="extnav", gps=False,
        seed=VEHICLE_SEED, start=start))
    daemon = RecordingDaemon(cfg, lambda truth: TruthPipeline(truth, PIPELINE_SEED, **pipeline_options))
    assert run_daemon_with_vehicle(daemon, vehicle) == 0
    assert vehicle.returncode == 0, procs.output("vehicle")
    return daemon, read_log(log)


def vision_rate_hz(log: dict, after: float = 0.0) -> float:
    t = [x for x in log["vision_position"]["t_rx"] if x >= after]
    return (len(t) - 1) / (t[-1] - t[0])


def vehicle_estimate_error_rms(log: dict) -> float:
    """RMS distance (m) of the vehicle's own position estimate from truth while it claims a position."""
    valid = np.asarray(log["vehicle_estimate"]["pos_valid"])
    est = np.asarray(log["vehicle_estimate"]["pos_ned"], dtype=float)[valid]
    truth = np.asarray(log["truth"]["pos_ned"], dtype=float)[valid]
    return float(np.sqrt(np.mean(np.sum((est - truth) ** 2, axis=1))))


def landed_after_flight(log: dict) -> bool:
    """Armed at some point, disarmed at the end (the mission's land step finished)."""
    return any(armed for _, _, armed in log["modes"]) and not log["modes"][-1][2]


def test_truth_estimates_reach_the_autopilot_in_its_frame_with_capture_stamps(tmp_path: Path, procs: Processes) -> None:
    daemon, log = fly_extnav(tmp_path, procs)

    assert log["external_nav"]["first_in_use_at"] is not None  # "EKF3 IMU0 is using external nav data"
    assert 28.0 <= vision_rate_hz(log) <= 31.0
    score = score_estimate(log)
    # truth + 1 cm noise: this scores the link, the stamps and the frame, not an estimator
    assert score["position_rms_m"] < 0.03
    assert score["yaw_rms_deg"] < 1.0
    # usec is the capture time on the daemon clock (here simulation time): never in the future,
    # and received within a couple of nav cycles of capture
    vp = log["vision_position"]
    latency = np.asarray(vp["t_rx"]) - capture_times(log, np.asarray(vp["usec"], dtype=float))
    assert latency.min() >= 0.0 and latency.max() <= 0.05
    assert log["rejected"] == {"nonfinite": 0, "stale_or_future": 0, "gated": 0}
    # the mission flew on these estimates alone (no GPS), and the autopilot's own estimate tracked truth
    assert daemon.mission.status == "completed"
    assert landed_after_flight(log)
    assert vehicle_estimate_error_rms(log) < 0.15


@pytest.mark.parametrize("frame", ["enu_position", "enu"])
def test_estimates_in_enu_instead_of_ned_visibly_fail(tmp_path: Path, procs: Processes, frame: str) -> None:
    """x/y swapped and z negated (``enu``: the yaw from east too): the flight must not look fine.

    The vehicle starts at (1, 3): off the x = y diagonal, where swapping x and y changes nothing.
    """
    daemon, log = fly_extnav(tmp_path, procs, start="1.0,3.0,0", frame=frame)

    assert daemon.mission.status == "failed", daemon.mission.snapshot()
    assert not landed_after_flight(log)
    assert score_estimate(log)["position_rms_m"] > 1.0  # the report shows the estimates are off
    if frame == "enu":
        # a heading 90 degrees off: ArduPilot-like pre-arm checks refuse to arm
        assert daemon.mission.step_index == 2 and "arm" in daemon.mission.reason
        assert any("PreArm" in text for _, _, text in log["statustext"])
    else:
        # the autopilot believes the mirrored position: takeoff never reaches 1 m in its estimate
        assert daemon.mission.snapshot()["step_kind"] == "takeoff"
        assert "altitude" in daemon.mission.reason
        assert log["rejected"]["gated"] > 0 or vehicle_estimate_error_rms(log) > 1.0


def test_nan_estimates_are_dropped_before_the_autopilot_and_counted(tmp_path: Path, procs: Processes) -> None:
    daemon, log = fly_extnav(tmp_path, procs, nan_every=10)
    pipeline = daemon.pipeline

    assert pipeline.nan_emitted > 100
    assert daemon.estimate.stats.nonfinite_dropped == pipeline.nan_emitted  # every one counted
    assert log["rejected"]["nonfinite"] == 0  # none reached the autopilot
    assert all(None not in p for p in log["vision_position"]["pos_ned"])
    assert daemon.link.stats.nonfinite_dropped == 0  # dropped by the estimate API, before the link guard
    assert 28.0 <= vision_rate_hz(log) <= 31.0  # the other estimates still make 30 Hz
    health = daemon.health.get("estimate_output")
    assert health is not None and health.state.label == "degraded" and "non-finite" in health.reason
    # reported, once: the health change and one alert, not a STATUSTEXT per dropped estimate
    assert 1 <= sum("estimate_output" in t or "non-finite" in t for t in daemon.texts) <= 3
    assert daemon.mission.status == "completed"


def test_crashed_pipeline_is_restarted_and_reported(tmp_path: Path, procs: Processes) -> None:
    daemon, log = fly_extnav(tmp_path, procs, crash_on_call=3)
    pipeline = daemon.pipeline

    assert pipeline.crash_time is not None
    record = daemon.supervisor.tasks["nav"]
    assert record.restarts == 1 and "test pipeline exploded on call 3" in record.last_error
    health = daemon.health.get("task:nav")  # reported, then ok again once it kept running
    assert health is not None and health.state.label == "ok"
    assert "after 1 restarts" in health.reason
    assert "RuntimeError: test pipeline exploded on call 3" in health.reason
    # the nav loop came back: estimates flowed again within the backoff and for the rest of the run
    received = log["vision_position"]["t_rx"]
    assert received[0] - pipeline.crash_time < 1.0
    assert 28.0 <= vision_rate_hz(log, after=received[0]) <= 31.0
    assert pipeline.calls > 1000
    assert daemon.mission.status == "completed"


# -- as deployed: subprocesses in real time --------------------------------------------------


def start_daemon(procs: Processes, cfg: Path) -> subprocess.Popen:
    return procs.start("daemon", [sys.executable, "-m", "companion.cli", "run", "-c", str(cfg)])


def runs(values: list) -> list:
    """``values`` with repeats collapsed: [F, T, T, F, T] -> [F, T, F, T]."""
    return [v for i, v in enumerate(values) if i == 0 or v != values[i - 1]]


def test_link_loss_and_a_new_vehicle_are_handled_without_restarting_the_daemon(
        tmp_path: Path, procs: Processes) -> None:
    port, zenoh_port = free_port(), free_port(socket.SOCK_STREAM)
    cfg = write_config(tmp_path / "companion.yaml", vehicle_port=port, zenoh_port=zenoh_port, mission=False,
                       mavlink={"link_timeout_s": 1.0}, telemetry={"status_hz": 5})
    first = procs.start("vehicle1", vehicle_args(port))
    daemon = start_daemon(procs, cfg)
    telemetry = TelemetryRecorder(zenoh_port)
    log = tmp_path / "vehicle2-log.json"
    try:
        wait_for(lambda: telemetry.get("autopilot").get("origin_confirmed"), 20, "the origin confirmed")
        confirmed_since = telemetry.get("health")["components"]["origin"]["since"]
        first.kill()
        first.wait()
        wait_for(lambda: telemetry.get("link").get("connected") is False, 10, "the link reported lost")
        lost = telemetry.mark()
        second = procs.start("vehicle2", vehicle_args(port, log=log))
        wait_for(lambda: any(p["connected"] for p in telemetry.stream("link", lost)), 20, "the link back")
        # the origin starts over (unconfirmed from the reconnect: too short for telemetry to see it
        # every time), then the new vehicle confirms it: health has been ok again since later
        wait_for(lambda: (o := telemetry.get("health")["components"]["origin"])["state"] == "ok"
                 and o["since"] > confirmed_since, 10, "the origin confirmed again, by the new vehicle")
        assert telemetry.stream("autopilot", lost)[-1]["origin_confirmed"]
        assert Processes.stop(second) == 0
        assert daemon.poll() is None, "the daemon kept running"
    finally:
        telemetry.close()
    link_states = runs([p["connected"] for p in telemetry.stream("link")])
    assert link_states[-3:] == [True, False, True]  # connected, lost, connected again
    vehicle_log = read_log(log)
    assert vehicle_log["origin"]["set_at"] is not None  # SET_GPS_GLOBAL_ORIGIN re-sent to the new vehicle
    stream_requests = [c for c in vehicle_log["commands"] if c[1] == mav.MAV_CMD_SET_MESSAGE_INTERVAL]
    assert stream_requests and all(result == mav.MAV_RESULT_ACCEPTED for _, _, result in stream_requests)


def test_pilot_takeover_stops_setpoints_at_once_and_aborts_the_mission(tmp_path: Path, procs: Processes) -> None:
    port, zenoh_port = free_port(), free_port(socket.SOCK_STREAM)
    cfg = write_config(tmp_path / "companion.yaml", vehicle_port=port, zenoh_port=zenoh_port,
                       telemetry={"status_hz": 5})
    gcs = GroundStation()
    log = tmp_path / "flight-log.json"
    vehicle = procs.start("vehicle", vehicle_args(port, log=log, gcs=(gcs.url_for_vehicle,)))
    start_daemon(procs, cfg)
    telemetry = TelemetryRecorder(zenoh_port)
    try:
        wait_for(lambda: telemetry.get("mission").get("step_kind") == "hold", 30, "the hover hold")
        time.sleep(1.0)  # hovering on the companion's setpoints
        gcs.command_long(mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, LOITER)
        ack = gcs.wait_for(lambda m: m.get_type() == "COMMAND_ACK" and m.command == mav.MAV_CMD_DO_SET_MODE,
                           5, "the mode change ACK")
        assert ack.result == mav.MAV_RESULT_ACCEPTED
        mission = wait_for(lambda: (m := telemetry.get("mission")).get("state") == "aborted" and m, 5,
                           "the mission aborted")
        assert mission["reason"] == "pilot or ground station changed the mode to LOITER"
        assert mission["failsafe_counts"] == {}  # a pilot's decision is no failsafe
        time.sleep(1.5)  # would the daemon take the vehicle back?
        assert Processes.stop(vehicle) == 0
    finally:
        telemetry.close()
        gcs.close()
    flight = read_log(log)
    loiter_at = next(t for t, mode, _ in flight["modes"] if mode == "LOITER")
    setpoints = flight["setpoints"]["t_rx"]
    assert sum(loiter_at - 1.0 <= t < loiter_at for t in setpoints) >= 9  # streaming at >= 10 Hz before
    assert [t for t in setpoints if t > loiter_at + 0.2] == []  # and stopped at once
    assert [mode for t, mode, _ in flight["modes"] if t >= loiter_at] == ["LOITER"]  # never taken back
    assert not [c for c in flight["commands"] if c[0] > loiter_at and c[1] == mav.MAV_CMD_DO_SET_MODE]
    assert "mission hover aborted: pilot or ground station changed the mode to LOITER" in procs.output("daemon")


def test_origin_statustext_reaches_the_ground_station(tmp_path: Path, procs: Processes) -> None:
    port = free_port()
    cfg = write_config(tmp_path / "companion.yaml", vehicle_port=port, mission=False)
    gcs = GroundStation()
    try:
        procs.start("vehicle", vehicle_args(port, gcs=(gcs.url_for_vehicle,)))
        start_daemon(procs, cfg)
        msg = gcs.wait_for(lambda m: m.get_type() == "STATUSTEXT" and m.text.startswith("companion: origin ok"),
                           20, "the companion's origin STATUSTEXT")
    finally:
        gcs.close()
    assert msg.get_srcSystem() == 1 and msg.get_srcComponent() == 197  # from the companion, routed by the autopilot
    assert msg.severity == mav.MAV_SEVERITY_INFO
