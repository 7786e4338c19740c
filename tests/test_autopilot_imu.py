"""The autopilot's IMU samples on the daemon clock (AutopilotState, companion/jitter.py): scaled
units converted, and a rebooted autopilot's restarted boot clock learnt as soon as the reboot is
confirmed."""

from __future__ import annotations

import asyncio

import numpy as np

from companion import clock
from companion.config import MavlinkConfig, VehicleConfig
from companion.frames import GRAVITY_MPS2
from companion.health import Health
from companion.mavlink.autopilot import PRESSURE_MAX_AGE_S, VELOCITY_MAX_AGE_S, AutopilotState
from companion.mavlink.link import MavlinkLink, mavlink
from companion.mavlink.trust import OLD_CLOCK_SILENT_S

SAMPLE_S = 0.02  # 50 Hz


def from_autopilot(msg: mavlink.MAVLink_message) -> mavlink.MAVLink_message:
    codec = mavlink.MAVLink(None, 1, 1)
    return codec.parse_char(msg.pack(codec))


async def stream_imu(link: MavlinkLink, boot_ms: int, count: int) -> None:
    """ATTITUDE (the link's boot-time watch) and ``count`` SCALED_IMU at rest from ``boot_ms``, at 50 Hz."""
    link._dispatch(from_autopilot(mavlink.MAVLink_attitude_message(boot_ms, 0, 0, 0, 0, 0, 0)))
    for i in range(count):
        t_ms = boot_ms + round(i * SAMPLE_S * 1000)
        link._dispatch(from_autopilot(mavlink.MAVLink_scaled_imu_message(t_ms, 0, 0, -1000, 1, 2, 3, 0, 0, 0)))
        await asyncio.sleep(SAMPLE_S)


def test_scaled_imu_becomes_specific_force_and_rates_in_si_units() -> None:
    async def main() -> AutopilotState:
        link = MavlinkLink(MavlinkConfig(), VehicleConfig(), "udpout:127.0.0.1:9", Health(clock.now))
        state = AutopilotState(link)
        state.imu_source = "SCALED_IMU"
        await stream_imu(link, 100_000, 5)
        return state

    state = asyncio.run(main())
    assert len(state.imu) == 5 and state.imu_rejected == 0
    np.testing.assert_allclose(state.imu[-1].accel_body, [0.0, 0.0, -GRAVITY_MPS2])  # -1000 mG
    np.testing.assert_allclose(state.imu[-1].gyro_body, [0.001, 0.002, 0.003])  # mrad/s


def test_after_an_autopilot_reboot_its_imu_is_used_once_the_reboot_is_confirmed() -> None:
    """The boot clock restarts near 0: the offset learnt before the reboot would place every new
    sample 100 s in the past (stale) until it slid out of the window; a new connection starts over.
    After the silence of a boot, the link confirms the reboot on the third stamp of the new clock
    (ATTITUDE, then two IMU samples): the two before it are dropped as off the clock, every one
    after is used."""
    async def main() -> tuple[AutopilotState, MavlinkLink, int]:
        link = MavlinkLink(MavlinkConfig(), VehicleConfig(), "udpout:127.0.0.1:9", Health(clock.now))
        state = AutopilotState(link)
        state.imu_source = "SCALED_IMU"
        link._dispatch(from_autopilot(mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, mavlink.MAV_STATE_STANDBY, 3)))
        await stream_imu(link, 100_000, 10)
        before = len(state.imu)
        await asyncio.sleep(OLD_CLOCK_SILENT_S)  # booting: silent
        await stream_imu(link, 500, 10)  # its ATTITUDE's boot time goes back: the link confirms a reboot
        return state, link, before

    state, link, before = asyncio.run(main())
    assert link.stats.autopilot_reboots == 1 and link.stats.time_anomalies == 2
    assert before == 10
    assert len(state.imu) == 19 and state.imu_rejected == 0


def test_a_failsafe_announcement_is_found_but_not_one_that_says_the_failsafe_ended() -> None:
    async def main() -> AutopilotState:
        return AutopilotState(MavlinkLink(MavlinkConfig(), VehicleConfig(), "udpout:127.0.0.1:9", Health(clock.now)))

    state = asyncio.run(main())
    state.statustext = [(1.0, 2, "EKF Failsafe: changed to LAND mode"), (2.0, 6, "EKF Failsafe Cleared")]
    assert state.failsafe_text(0.5) == "EKF Failsafe: changed to LAND mode"
    assert state.failsafe_text(1.5) is None  # only the "cleared" one since
    state.statustext.append((3.0, 2, "GCS Failsafe Off"))
    assert state.failsafe_text(1.5) is None


def test_imu_samples_carry_the_autopilots_velocity_only_while_it_is_fresh() -> None:
    async def main() -> AutopilotState:
        link = MavlinkLink(MavlinkConfig(), VehicleConfig(), "udpout:127.0.0.1:9", Health(clock.now))
        state = AutopilotState(link)
        state.imu_source = "SCALED_IMU"
        link._dispatch(from_autopilot(mavlink.MAVLink_local_position_ned_message(99_000, 1.0, 2.0, -3.0, 4.0, -5.0, 0.5)))
        await stream_imu(link, 100_000, 3)
        await asyncio.sleep(VELOCITY_MAX_AGE_S)
        await stream_imu(link, 101_100, 1)
        return state

    state = asyncio.run(main())
    np.testing.assert_allclose(state.imu[0].velocity_ned, [4.0, -5.0, 0.5])
    assert state.imu[-1].velocity_ned is None  # the velocity is older than VELOCITY_MAX_AGE_S by then


def test_scaled_imu_samples_carry_the_barometer_only_while_scaled_pressure_is_fresh() -> None:
    """ArduPilot 4.0 streams no HIGHRES_IMU: the SCALED_PRESSURE beside the scaled IMU gives its
    samples their barometric altitude (ISA: 1013.25 hPa is 0 m, 898.75 hPa about 1000 m)."""
    async def main() -> AutopilotState:
        link = MavlinkLink(MavlinkConfig(), VehicleConfig(), "udpout:127.0.0.1:9", Health(clock.now))
        state = AutopilotState(link)
        state.imu_source = "SCALED_IMU"
        link._dispatch(from_autopilot(mavlink.MAVLink_scaled_pressure_message(99_000, 898.75, 0.0, 2500)))
        await stream_imu(link, 100_000, 3)
        await asyncio.sleep(PRESSURE_MAX_AGE_S)
        await stream_imu(link, 100_600, 1)
        return state

    state = asyncio.run(main())
    assert state.imu[0].pressure_alt_m is not None and abs(state.imu[0].pressure_alt_m - 1000.0) < 1.0
    assert state.imu[-1].pressure_alt_m is None  # the pressure is older than PRESSURE_MAX_AGE_S by then
