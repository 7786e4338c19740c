"""SET_POSITION_TARGET_LOCAL_NED type masks are the ones ArduPilot documents (REFERENCE.md)."""

import numpy as np
import pytest

from companion.mavlink.setpoints import Setpoint, setpoint_message

P = np.array([1.0, 2.0, -1.0])


@pytest.mark.parametrize("setpoint, mask", [
    (Setpoint(position_ned=P), 3576),
    (Setpoint(velocity_ned=P), 3527),
    (Setpoint(acceleration_ned=P), 3135),
    (Setpoint(position_ned=P, velocity_ned=P), 3520),
    (Setpoint(position_ned=P, velocity_ned=P, acceleration_ned=P), 3072),
])
def test_type_mask_matches_the_ardupilot_table(setpoint: Setpoint, mask: int) -> None:
    assert setpoint.type_mask == mask


def test_a_yaw_target_clears_the_yaw_ignore_bit() -> None:
    assert Setpoint(position_ned=P, yaw_rad=0.5).type_mask == 3576 & ~1024


def test_message_is_local_ned_with_ignored_fields_zero() -> None:
    msg = setpoint_message(Setpoint(velocity_ned=P), 1234, (1, 1))
    assert msg.coordinate_frame == 1
    assert (msg.vx, msg.vy, msg.vz) == (1.0, 2.0, -1.0)
    assert (msg.x, msg.y, msg.z) == (0.0, 0.0, 0.0)
