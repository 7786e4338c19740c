"""The three estimate kinds at the edges: a pose goes through the source selection, a range estimate
becomes DISTANCE_SENSOR, an attitude estimate is only a cross-check of the autopilot's ATTITUDE
(companion/navloop.py, companion/mavlink/distance.py, companion/crosscheck.py)."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from companion import clock
from companion.config import MavlinkConfig, VehicleConfig
from companion.crosscheck import AttitudeCrossCheck
from companion.health import Health
from companion.mavlink.autopilot import AutopilotState
from companion.mavlink.distance import DistanceSender
from companion.mavlink.link import MavlinkLink
from companion.messages import AttitudeEstimate, Estimate, PoseEstimate, RangeEstimate
from companion.navloop import NavLoop, NavOutputs
from companion.sdnotify import WatchdogGate
from companion.selection import SourceSelector
from companion.timing import Timings


class SentMessages:
    """A link stand-in that keeps what would go on the wire, packed and parsed back as MAVLink 2."""

    def __init__(self) -> None:
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=197)
        self.messages: list[mavlink.MAVLink_message] = []

    def send(self, msg: mavlink.MAVLink_message) -> bool:
        self.messages.append(self.mav.decode(bytearray(msg.pack(self.mav))))
        return True


def test_a_height_estimate_goes_out_as_a_downward_distance_sensor_in_centimetres() -> None:
    link = SentMessages()
    sender = DistanceSender(link)  # type: ignore[arg-type]
    sender.submit(RangeEstimate(12.3456, 1.234, 0.0004, min_m=0.2, max_m=8.0, source="dots"))
    (msg,) = link.messages
    assert msg.get_type() == "DISTANCE_SENSOR"
    assert (msg.current_distance, msg.min_distance, msg.max_distance) == (123, 20, 800)
    assert msg.orientation == mavlink.MAV_SENSOR_ROTATION_PITCH_270 and msg.covariance == 4  # 0.0004 m^2 = 4 cm^2
    assert msg.time_boot_ms == 12345


def test_a_non_finite_or_out_of_span_distance_is_never_sent() -> None:
    link = SentMessages()
    sender = DistanceSender(link)  # type: ignore[arg-type]
    for d, var in ((math.nan, 0.01), (1.0, math.inf), (0.05, 0.01), (50.0, 0.01)):
        sender.submit(RangeEstimate(1.0, d, var, min_m=0.1, max_m=40.0))
    assert link.messages == [] and sender.dropped == 4


def test_each_range_source_gets_its_own_sensor_id() -> None:
    link = SentMessages()
    sender = DistanceSender(link)  # type: ignore[arg-type]
    for source in ("a", "b", "a"):
        sender.submit(RangeEstimate(1.0, 2.0, 0.01, source=source))
    assert [m.id for m in link.messages] == [0, 1, 0]


def test_the_attitude_check_raises_only_after_a_lasting_divergence_and_clears() -> None:
    health = Health(lambda: 0.0)
    published: list[dict] = []
    check = AttitudeCrossCheck(lambda t: (0.0, 0.0, 0.0), health, lambda stream, p: published.append(p),
                               threshold_deg=5.0, hold_s=1.0)

    def state_after(t: float, roll_deg: float) -> str:
        check.submit(AttitudeEstimate(t, (math.radians(roll_deg), 0.0, 0.0), np.eye(3) * 1e-4, source="flow"))
        return health.snapshot()["components"]["crosscheck:flow"]["state"]

    assert state_after(0.0, 1.0) == "ok"
    assert {state_after(0.1 * k, 9.0) for k in range(1, 10)} == {"ok"}  # diverged, not yet for hold_s
    assert state_after(1.2, 9.0) == "degraded"
    assert state_after(1.3, 2.0) == "ok"
    assert published[-1]["difference_deg"] == pytest.approx(2.0)


def test_two_diverging_attitudes_with_nothing_between_them_raise_no_alarm() -> None:
    """Estimates can be seconds apart (a fixed wing's turns give none): two that diverge 2 s apart
    do not show a divergence lasting the 2 s hold; a run of them closer than half the hold does."""
    health = Health(lambda: 0.0)
    published: list[dict] = []
    check = AttitudeCrossCheck(lambda t: (0.0, 0.0, 0.0), health, lambda stream, p: published.append(p),
                               threshold_deg=5.0, hold_s=2.0)
    for t in (10.0, 12.1, 14.3):
        check.submit(AttitudeEstimate(t, (math.radians(9.0), 0.0, 0.0), np.eye(3) * 1e-4, source="flow"))
    assert not any(p["alarm"] for p in published)
    assert health.snapshot()["components"].get("crosscheck:flow", {"state": "ok"})["state"] == "ok"
    for k in range(1, 4):  # 15.0 .. 16.8 s: 0.9 s apart, diverging throughout from 14.3 s
        check.submit(AttitudeEstimate(14.3 + 0.9 * k, (math.radians(9.0), 0.0, 0.0), np.eye(3) * 1e-4, source="flow"))
    assert [p["alarm"] for p in published[3:]] == [False, False, True]


def test_the_attitude_check_compares_only_the_angles_an_estimate_measures() -> None:
    health = Health(lambda: 0.0)
    check = AttitudeCrossCheck(lambda t: (0.0, 0.0, 2.0), health, lambda stream, p: None, threshold_deg=5.0, hold_s=0.0)
    check.submit(AttitudeEstimate(0.0, (math.radians(1.0), 0.0, math.nan), np.diag([1e-4, 1e-4, math.inf]), source="dots"))
    assert health.snapshot()["components"]["crosscheck:dots"]["state"] == "ok"  # yaw unmeasured, not 115 deg off
    check.submit(AttitudeEstimate(0.1, (math.radians(8.0), 0.0, math.nan), np.diag([1e-4, 1e-4, math.inf]), source="dots"))
    check.submit(AttitudeEstimate(0.2, (math.radians(8.0), 0.0, math.nan), np.diag([1e-4, 1e-4, math.inf]), source="dots"))
    assert health.snapshot()["components"]["crosscheck:dots"]["state"] == "degraded"


class Emits:
    """A pipeline that emits a fixed list each step."""

    name = "p"
    telemetry_streams: tuple[str, ...] = ()

    def __init__(self, estimates: list[Estimate]) -> None:
        self.estimates = estimates
        self.timings = {"p": Timings()}

    def step(self, now: float) -> list[Estimate]:
        return self.estimates


def test_the_loop_routes_each_kind_to_its_edge_and_only_poses_to_the_autopilot() -> None:
    pose = PoseEstimate(1.0, np.zeros(3), (0.0, 0.0, 0.0), np.eye(6), source="p")
    rng = RangeEstimate(1.0, 1.5, 0.01, source="p")
    att = AttitudeEstimate(1.0, (0.0, 0.0, 0.1), np.eye(3), source="p")
    got: dict[str, list] = {"pose": [], "range": [], "attitude": [], "publish": []}
    outputs = NavOutputs(pose=got["pose"].append, range=got["range"].append, attitude=got["attitude"].append,
                         publish=lambda stream, payload: got["publish"].append(stream))
    loop = NavLoop([Emits([pose, rng, att])], SourceSelector(["p"], 0.3, 2.0), outputs,  # type: ignore[list-item]
                   WatchdogGate(1.0, clock=lambda: 0.0), 50.0, lambda: 0.0)
    loop.cycle(1.0)
    assert got["pose"] == [pose] and got["range"] == [rng] and got["attitude"] == [att]
    assert got["publish"] == ["pose"] and loop.last_estimate is pose


def test_the_attitude_check_compares_with_the_autopilot_attitude_at_the_estimate_time() -> None:
    """An estimate is published after its GNSS fixes came, 0.2-0.3 s late: in a roll-in the newest
    ATTITUDE would be degrees away from it while the autopilot was right at the estimate's time."""
    async def main() -> AutopilotState:
        link = MavlinkLink(MavlinkConfig(), VehicleConfig(), "udpout:127.0.0.1:9", Health(clock.now))
        state = AutopilotState(link)
        for k in range(20):  # rolling in at 30 deg/s, ATTITUDE at 50 Hz
            codec = mavlink.MAVLink(None, 1, 1)  # as the autopilot (sysid 1, compid 1) sends it
            attitude = mavlink.MAVLink_attitude_message(1000 + 20 * k, math.radians(0.6 * k), 0.0, 0.0, 0, 0, 0)
            link._dispatch(codec.parse_char(attitude.pack(codec)))
            await asyncio.sleep(0.02)
        return state

    state = asyncio.run(main())
    first_time = state.attitude_history[0][0]
    assert state.attitude_at(first_time + 0.005) == pytest.approx((0.0, 0.0, 0.0))
    assert state.attitude_at(first_time - 1.0) is None  # nothing received near that time
    health = Health(lambda: 0.0)
    check = AttitudeCrossCheck(state.attitude_at, health, lambda stream, p: None, threshold_deg=5.0, hold_s=0.0)
    for _ in range(2):
        check.submit(AttitudeEstimate(first_time, (0.0, 0.0, 0.0), np.eye(3) * 1e-4, source="flow"))
    assert health.snapshot()["components"]["crosscheck:flow"]["state"] == "ok"  # the newest is 11.4 deg off
    for _ in range(2):
        check.submit(AttitudeEstimate(first_time, (math.radians(8.0), 0.0, 0.0), np.eye(3) * 1e-4, source="flow"))
    assert health.snapshot()["components"]["crosscheck:flow"]["state"] == "degraded"
