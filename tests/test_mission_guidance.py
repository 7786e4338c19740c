"""A pipeline that flies the vehicle itself (companion.pipeline.GuidanceSource) and the mission:
the ``return_to_base`` step and the takeover on GNSS loss (``failsafe.gnss_loss``), flown
against the real SITL vehicle in lockstep (tests/test_mission_failsafes.py's harness).

The guidance source here is a TEST-ONLY truth pipeline that "loses GNSS" at a set daemon time
and then guides the vehicle to a base 2 m away and lands it there; the EKF-SLAM pipeline is the
real one (tests/test_ekf_slam_sitl.py)."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
from pymavlink import mavutil

from companion.messages import Guidance
from tests.conftest import free_port
from tests.mavlink_peer import COMPANION_COMPID
from tests.sitl_helpers import Processes, TruthPipeline
from tests.test_mission_failsafes import GPS_TOLERANCE_M, fly, mode_entries, truth_at

BASE = np.array([2.0, 1.0, -1.0])
RTL = mavutil.mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH
SPEED_MPS = 0.5


class GuidingTruthPipeline(TruthPipeline):
    """Truth plus noise as the pose; from ``lost_at`` (daemon s) on, or when asked, guidance:
    fly at ``speed_mps`` straight to BASE, then land once within ``land_within_m`` of it."""

    def __init__(self, truth: object, lost_at: float, speed_mps: float = SPEED_MPS, land_within_m: float = 0.1) -> None:
        super().__init__(truth, 5)
        self.lost_at = lost_at
        self.speed_mps = speed_mps
        self.land_within_m = land_within_m
        self.requested: str | None = None

    def request_guidance(self, now: float, reason: str) -> str | None:
        self.requested = reason
        return None

    def guidance(self, now: float) -> Guidance | None:
        sample = self.truth.latest
        if sample is None or (now < self.lost_at and self.requested is None):
            return None
        trigger = "commanded" if self.requested is not None else "gnss_lost"
        offset = BASE - sample.position_ned
        if np.linalg.norm(offset[:2]) < self.land_within_m:
            return Guidance(now, "land", BASE, np.zeros(3), None, trigger, "at the base")
        along = offset / np.linalg.norm(offset)
        target = sample.position_ned + along * min(1.0, float(np.linalg.norm(offset)))
        return Guidance(now, "fly", target, along * self.speed_mps, None, trigger, "flying to the base")


HOLD_LONG = [{"hold": {"seconds": 120}}]


def fly_guided(tmp_path: Path, procs: Processes, steps: list[dict], lost_at: float, gnss_loss: str = "return_to_base",
               seconds: float = 50, gcs: tuple[str, ...] = (), **guide: float) -> tuple[object, dict]:
    daemon, log = fly(tmp_path, procs, steps, seconds, sections={"mission": {"failsafe": {
        "lost_hold_s": 2.0, "gnss_loss": gnss_loss}}}, make=lambda truth: GuidingTruthPipeline(truth, lost_at, **guide),
        gcs=gcs)
    return daemon, log


class GroundStation(threading.Thread):
    """A ground station (sysid 255) on the vehicle's GCS link: after ``after_heartbeats`` of the
    autopilot's HEARTBEATs (1 Hz of simulated time) it sends MAV_CMD_NAV_RETURN_TO_LAUNCH to the
    companion's component, once per HEARTBEAT until the companion acknowledges it."""

    def __init__(self, after_heartbeats: int) -> None:
        super().__init__(daemon=True)
        self.port = free_port()
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{self.port}", source_system=255, source_component=190)
        self.after = after_heartbeats
        self.acks: list[tuple[int, int]] = []  # (command, result) from the companion
        self.done = threading.Event()

    @property
    def vehicle_url(self) -> str:
        return f"udpout:127.0.0.1:{self.port}"

    def run(self) -> None:
        beats = 0
        while not self.done.is_set():
            msg = self.conn.recv_match(blocking=True, timeout=0.2)
            if msg is None:
                continue
            if msg.get_type() == "COMMAND_ACK" and msg.get_srcComponent() == COMPANION_COMPID:
                self.acks.append((msg.command, msg.result))
            elif msg.get_type() == "HEARTBEAT" and msg.get_srcComponent() == 1:
                beats += 1
                if beats >= self.after and not self.acks:
                    self.conn.mav.command_long_send(1, COMPANION_COMPID, RTL, 0, 0, 0, 0, 0, 0, 0, 0)


def test_gnss_lost_in_a_hold_jumps_to_the_return_to_base_step_which_flies_the_guidance_and_lands_at_base(
        tmp_path: Path, procs: Processes) -> None:
    daemon, log = fly_guided(tmp_path, procs, HOLD_LONG + [{"return_to_base": {}}], lost_at=15.0)
    mission = daemon.mission
    assert mission.status == "completed", mission.snapshot()
    assert mission.ctx.failsafes[0]["kind"] == "guidance" and "gnss_lost" in mission.ctx.failsafes[0]["reason"]
    assert 15.0 <= mission.ctx.failsafes[0]["t"] < 15.5
    land_at = mode_entries(log, "LAND")[0]
    np.testing.assert_allclose(truth_at(log, land_at)[:2], BASE[:2], atol=GPS_TOLERANCE_M)
    assert not log["modes"][-1][2]  # landed and disarmed


def test_without_a_return_to_base_step_the_guidance_is_flown_and_the_mission_ends_failed_naming_it(
        tmp_path: Path, procs: Processes) -> None:
    daemon, log = fly_guided(tmp_path, procs, HOLD_LONG, lost_at=15.0)
    mission = daemon.mission
    assert mission.status == "failed" and "gnss_lost" in mission.reason, mission.snapshot()
    np.testing.assert_allclose(truth_at(log, mode_entries(log, "LAND")[0])[:2], BASE[:2], atol=GPS_TOLERANCE_M)


def test_gnss_loss_continue_ignores_the_takeover_and_the_return_to_base_step_flies_the_active_guidance(
        tmp_path: Path, procs: Processes) -> None:
    daemon, log = fly_guided(tmp_path, procs, [{"hold": {"seconds": 12}}, {"return_to_base": {}}], lost_at=15.0,
                             gnss_loss="continue")
    mission = daemon.mission
    assert mission.status == "completed" and not mission.ctx.failsafes, mission.snapshot()
    # the hold ran its 12 s although the guidance was active from 15 s on: no takeover
    hold_end = mode_entries(log, "GUIDED")[0] + 12.0
    landed_at = truth_at(log, mode_entries(log, "LAND")[0])
    np.testing.assert_allclose(landed_at[:2], BASE[:2], atol=GPS_TOLERANCE_M)
    assert mode_entries(log, "LAND")[0] > hold_end


def test_a_return_to_base_step_asks_a_pipeline_that_is_not_guiding_to_start(tmp_path: Path, procs: Processes) -> None:
    daemon, log = fly_guided(tmp_path, procs, [{"hold": {"seconds": 3}}, {"return_to_base": {}}], lost_at=1e9)
    assert daemon.mission.status == "completed", daemon.mission.snapshot()
    assert daemon.pipeline.requested == "mission step return_to_base" and not daemon.mission.ctx.failsafes
    np.testing.assert_allclose(truth_at(log, mode_entries(log, "LAND")[0])[:2], BASE[:2], atol=GPS_TOLERANCE_M)


def test_a_ground_stations_return_command_to_the_companion_takes_over_and_lands_at_base(
        tmp_path: Path, procs: Processes) -> None:
    gcs = GroundStation(after_heartbeats=15)
    gcs.start()
    try:
        daemon, log = fly_guided(tmp_path, procs, HOLD_LONG + [{"return_to_base": {}}], lost_at=1e9,
                                 gnss_loss="continue", gcs=(gcs.vehicle_url,))
    finally:
        gcs.done.set()
        gcs.join(timeout=2.0)
    assert gcs.acks[:1] == [(RTL, mavutil.mavlink.MAV_RESULT_ACCEPTED)]
    mission = daemon.mission
    assert mission.status == "completed", mission.snapshot()
    assert daemon.pipeline.requested == "MAVLink command"
    takeover = mission.ctx.failsafes[0]
    assert takeover["kind"] == "guidance" and "commanded" in takeover["reason"] and 8.0 < takeover["t"] < 25.0
    np.testing.assert_allclose(truth_at(log, mode_entries(log, "LAND")[0])[:2], BASE[:2], atol=GPS_TOLERANCE_M)


def test_a_landing_asked_at_speed_first_settles_over_its_point(tmp_path: Path, procs: Processes) -> None:
    """The guidance says land 1.5 m short of the base while flying at 2 m/s: LAND then would hold
    where the vehicle comes to rest, past the point; the step holds the point until settled."""
    daemon, log = fly_guided(tmp_path, procs, [{"return_to_base": {}}], lost_at=1e9, seconds=60,
                             speed_mps=2.0, land_within_m=1.5)
    assert daemon.mission.status == "completed", daemon.mission.snapshot()
    land_at = mode_entries(log, "LAND")[0]
    np.testing.assert_allclose(truth_at(log, land_at)[:2], BASE[:2], atol=GPS_TOLERANCE_M)
    np.testing.assert_allclose(log["truth"]["pos_ned"][-1][:2], BASE[:2], atol=GPS_TOLERANCE_M)
