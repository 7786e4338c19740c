"""Estimate output over a real loopback MAVLink link: rate, NaN guard, reset counter, covariance."""

from __future__ import annotations

import asyncio
import dataclasses
import os

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

from companion.config import MavlinkConfig, VehicleConfig  # noqa: E402
from companion.health import Health  # noqa: E402
from companion.mavlink.estimate import EstimateSender  # noqa: E402
from companion.messages import PoseEstimate  # noqa: E402
from companion.mavlink.link import MavlinkLink  # noqa: E402
from tests.conftest import free_port  # noqa: E402


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def estimate(t: float, x: float = 1.0, reset: bool = False) -> PoseEstimate:
    cov = np.diag([0.01, 0.01, 0.04, 0.001, 0.001, 0.002])
    return PoseEstimate(t, np.array([x, 2.0, -1.0]), (0.0, 0.0, 0.5), cov,
                        np.array([0.1, 0.0, 0.0]), np.eye(3) * 0.01, reset, "test")


def run_with_link(body) -> list:
    """Open a daemon-side link to a pymavlink 'autopilot' on loopback; run body; return what arrived."""
    port = free_port()
    autopilot = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=1, source_component=1)

    async def main() -> None:
        health = Health(FakeClock())
        link = MavlinkLink(MavlinkConfig(), VehicleConfig(), f"udpout:127.0.0.1:{port}", health)
        await link._open()
        try:
            await body(link, health)
        finally:
            link._close()

    asyncio.run(main())
    received = []
    while (msg := autopilot.recv_match(blocking=True, timeout=0.2)) is not None:
        received.append(msg)
    autopilot.close()
    return received


def test_fifty_hz_input_is_sent_at_the_configured_thirty_hz() -> None:
    clock = FakeClock()

    async def body(link: MavlinkLink, health: Health) -> None:
        sender = EstimateSender(link, 30.0, health, clock)
        for k in range(100):  # 2 s at 50 Hz
            clock.t = 100.0 + k * 0.02
            sender.submit(estimate(clock.t))

    msgs = run_with_link(body)
    vpe = [m for m in msgs if m.get_type() == "VISION_POSITION_ESTIMATE"]
    vse = [m for m in msgs if m.get_type() == "VISION_SPEED_ESTIMATE"]
    assert 59 <= len(vpe) <= 61
    assert len(vse) == len(vpe)
    assert all(b.usec > a.usec for a, b in zip(vpe, vpe[1:]))
    assert vpe[0].usec == 100_000_000  # capture time on the daemon clock, in microseconds


def test_non_finite_estimate_never_reaches_the_autopilot() -> None:
    clock = FakeClock()
    result = {}

    async def body(link: MavlinkLink, health: Health) -> None:
        sender = EstimateSender(link, 30.0, health, clock)
        sender.submit(estimate(clock.t, x=float("nan")))
        clock.t += 1.0
        sender.submit(estimate(clock.t, x=3.0))
        result["stats"] = sender.stats
        result["health"] = health.get("estimate_output")

    msgs = run_with_link(body)
    vpe = [m for m in msgs if m.get_type() == "VISION_POSITION_ESTIMATE"]
    assert [m.x for m in vpe] == [3.0]
    assert result["stats"].nonfinite_dropped == 1


def test_link_drops_any_message_with_a_nan_field() -> None:
    from companion.mavlink.link import mavlink

    result = {}

    async def body(link: MavlinkLink, health: Health) -> None:
        result["sent"] = link.send(mavlink.MAVLink_vision_speed_estimate_message(1, float("nan"), 0, 0, [0.0] * 9, 0))
        result["dropped"] = link.stats.nonfinite_dropped

    msgs = run_with_link(body)
    assert result == {"sent": False, "dropped": 1}
    assert not [m for m in msgs if m.get_type() == "VISION_SPEED_ESTIMATE"]


def test_nonfinite_fields_names_each_bad_field_and_passes_large_finite_values() -> None:
    from companion.mavlink.link import mavlink, nonfinite_fields

    cov = [0.0] * 21
    cov[4], cov[7] = float("inf"), float("-inf")  # opposite infinities: their sum is NaN, not inf
    vpe = mavlink.MAVLink_vision_position_estimate_message(1, float("nan"), 0.0, 0.0, 0.0, 0.0, 0.0, cov, 0)
    assert nonfinite_fields(vpe) == ["x", "covariance"]
    big = mavlink.MAVLink_vision_position_estimate_message(1, 3e38, 3e38, -3e38, 0.0, 0.0, 0.0, [3e38] * 21, 0)
    assert nonfinite_fields(big) == []
    odd = mavlink.MAVLink_vision_position_estimate_message(1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, ["a"] * 21, 0)
    assert nonfinite_fields(odd) == []  # no float in the array: nothing non-finite, and no crash


@pytest.mark.parametrize("field", ["position", "euler", "covariance", "t_capture", "velocity", "velocity_cov"])
def test_a_pose_estimate_with_any_non_finite_number_is_not_finite(field: str) -> None:
    good = estimate(1.0)
    assert good.is_finite()
    bad = {
        "position": dict(position_ned=np.array([1.0, np.inf, 0.0])),
        "euler": dict(euler_rad=(0.0, float("nan"), 0.0)),
        "covariance": dict(pose_covariance=np.diag([0.01, 0.01, np.inf, 0.001, 0.001, 0.002])),
        "t_capture": dict(t_capture=float("nan")),
        "velocity": dict(velocity_ned=np.array([0.0, -np.inf, 0.0])),
        "velocity_cov": dict(velocity_covariance=np.full((3, 3), np.nan)),
    }[field]
    assert not dataclasses.replace(good, **bad).is_finite()


def test_reset_counter_increments_only_on_a_reset_and_covariance_is_upper_triangle() -> None:
    clock = FakeClock()

    async def body(link: MavlinkLink, health: Health) -> None:
        sender = EstimateSender(link, 30.0, health, clock)
        for k, reset in enumerate([False, False, True, False, True]):
            clock.t = 100.0 + k * 0.1
            sender.submit(estimate(clock.t, reset=reset))

    msgs = run_with_link(body)
    vpe = [m for m in msgs if m.get_type() == "VISION_POSITION_ESTIMATE"]
    assert [m.reset_counter for m in vpe] == [0, 0, 1, 1, 2]
    cov = vpe[0].covariance
    assert len(cov) == 21
    assert cov[0:3] == pytest.approx([0.01, 0, 0]) and cov[6] == pytest.approx(0.01)
    assert cov[11] == pytest.approx(0.04)  # x, y, z variances (float32 on the wire)
    assert cov[15] == pytest.approx(0.001) and cov[20] == pytest.approx(0.002)  # roll, yaw



def test_stale_capture_time_is_not_sent_twice() -> None:
    clock = FakeClock()
    result = {}

    async def body(link: MavlinkLink, health: Health) -> None:
        sender = EstimateSender(link, 30.0, health, clock)
        sender.submit(estimate(100.0))
        clock.t = 101.0
        sender.submit(estimate(100.0))
        result["stats"] = sender.stats

    msgs = run_with_link(body)
    assert len([m for m in msgs if m.get_type() == "VISION_POSITION_ESTIMATE"]) == 1
    assert result["stats"].out_of_order_dropped == 1
