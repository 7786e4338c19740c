"""What the firmware changes in the companion's frames and setpoints (companion/mavlink/firmware.py):
ArduPilot before 4.1 reports LOCAL_POSITION_NED and reads setpoint z relative to home, and its
Copter flies no acceleration targets. Here with home 2 m above and 3 m north-east of the origin."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from companion import clock
from companion.config import MavlinkConfig, VehicleConfig
from companion.control.outer_loop import ControlOutput
from companion.frames import geodetic_from_ned
from companion.health import Health
from companion.mavlink.autopilot import AutopilotState
from companion.mavlink.firmware import Firmware
from companion.mavlink.link import MavlinkLink, mavlink
from companion.mavlink.setpoints import Setpoint, setpoint_message
from companion.mission.flight import output_mode

ORIGIN = (1.2966, 103.7764, 10.0)
HOME_NED = np.array([3.0, 3.0, -2.0])  # home in the origin frame: 2 m up


def version(major: int, minor: int, patch: int) -> int:
    return (major << 24) | (minor << 16) | (patch << 8) | mavlink.FIRMWARE_VERSION_TYPE_OFFICIAL


def from_autopilot(msg: mavlink.MAVLink_message) -> mavlink.MAVLink_message:
    codec = mavlink.MAVLink(None, 1, 1)
    return codec.parse_char(msg.pack(codec))


def autopilot_state(firmware_version: tuple[int, int, int]) -> AutopilotState:
    """An AutopilotState told (as by the autopilot) its firmware, origin and home."""
    async def main() -> AutopilotState:
        link = MavlinkLink(MavlinkConfig(), VehicleConfig(), "udpout:127.0.0.1:9", Health(clock.now))
        state = AutopilotState(link)
        link.autopilot = "ArduPilot"
        lat, lon, alt = geodetic_from_ned(HOME_NED, ORIGIN)
        for msg in (
            mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                              0, 4, mavlink.MAV_STATE_STANDBY, 3),
            mavlink.MAVLink_autopilot_version_message(0, version(*firmware_version), 0, 0, 0, [0] * 8, [0] * 8,
                                                      [0] * 8, 0, 0, 0, [0] * 18),
            mavlink.MAVLink_gps_global_origin_message(*(round(v * 1e7) for v in ORIGIN[:2]), round(ORIGIN[2] * 1e3), 0),
            mavlink.MAVLink_home_position_message(round(lat * 1e7), round(lon * 1e7), round(alt * 1e3), 0, 0, 0,
                                                  [1, 0, 0, 0], 0, 0, 0, 0),
            mavlink.MAVLink_local_position_ned_message(0, 1.0, 2.0, -0.5, 0.1, 0.2, 0.3),  # as the firmware reports it
        ):
            link._dispatch(from_autopilot(msg))
        return state
    return asyncio.run(main())


def test_arducopter_40_local_position_is_moved_from_home_to_the_origin() -> None:
    state = autopilot_state((4, 0, 5))
    assert state.firmware is not None and state.firmware.local_position_relative_to_home
    np.testing.assert_allclose(state.home_offset_ned(), HOME_NED, atol=0.02)
    np.testing.assert_allclose(state.local_position_ned, [4.0, 5.0, -2.5], atol=0.02)
    np.testing.assert_allclose(state.local_velocity_ned, [0.1, 0.2, 0.3])


def test_arducopter_40_setpoint_z_is_sent_relative_to_home() -> None:
    state = autopilot_state((4, 0, 5))
    offset = state.setpoint_z_offset_m()
    assert offset == pytest.approx(2.0, abs=0.01)
    # 1 m above the origin is 1 m *below* a home 2 m up: z = +1 in the home-relative frame
    msg = setpoint_message(Setpoint(position_ned=np.array([1.0, 2.0, -1.0])), 0, (1, 1), offset)
    assert (msg.x, msg.y) == (1.0, 2.0) and msg.z == pytest.approx(1.0, abs=0.01)


def test_arducopter_41_uses_the_origin_frame_unchanged() -> None:
    state = autopilot_state((4, 1, 0))
    assert state.setpoint_z_offset_m() == 0.0
    np.testing.assert_allclose(state.local_position_ned, [1.0, 2.0, -0.5])


def test_auto_output_needs_a_firmware_known_to_fly_acceleration_targets() -> None:
    copter = "ArduPilot", "copter"
    assert output_mode("auto", Firmware(*copter, (4, 0, 5))) == "pos_vel"
    assert output_mode("auto", Firmware(*copter, (4, 5, 7))) == "pos_vel_acc"
    assert output_mode("auto", Firmware(*copter)) == "pos_vel"  # version unknown: what every firmware takes
    assert output_mode("auto", None) == "pos_vel"
    assert output_mode("auto", Firmware("PX4", "copter", (1, 15, 0))) == "pos_vel_acc"
    assert output_mode("position_only", Firmware(*copter, (4, 5, 7))) == "position_only"


def test_pos_vel_folds_the_horizontal_acceleration_into_the_velocity_through_the_autopilot_gain() -> None:
    out = ControlOutput(acceleration_ned=(1.0, -0.5, 0.3), velocity_ned_z=-0.2, position_ned=(1.0, 2.0, -1.0),
                        velocity_ned=(0.4, 0.0, -0.2), measured_position_ned=(1.0, 2.0, -1.0),
                        measured_velocity_ned=(0.4, 0.0, -0.2), saturated=(False, False, False))
    fields = out.position_velocity_fields(vel_gain_xy=2.0)
    np.testing.assert_allclose(fields["position_ned"], [1.0, 2.0, -1.0])
    np.testing.assert_allclose(fields["velocity_ned"], [0.4 + 0.5, -0.25, -0.2])
    assert Setpoint(**fields, yaw_rad=0.0).type_mask == 2496
    held = out._replace(valid=False)
    np.testing.assert_allclose(held.position_velocity_fields(2.0)["velocity_ned"], [0.4, 0.0, -0.2])
