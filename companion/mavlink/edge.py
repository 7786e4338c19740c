"""The values the companion takes from its autopilot, checked where they enter (the link).

Every field a consumer reads from these messages must be finite and within the bound below, or
the whole message is dropped (and counted per message type by the link) before the boot clock,
any subscriber or any pipeline sees it. The bounds are far outside anything a flying vehicle
reports and only catch garbage: a NaN, an infinity, a corrupted or forged value that would
otherwise reach the fusion. Fields not listed are not read by the companion (PX4 legitimately
sends NaN for some "unknown" values, e.g. HOME_POSITION's approach vector) and are left alone.

Units as MAVLink defines them: rad, rad/s, m, m/s, m/s^2, hPa, degE7, mm.
"""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import ardupilotmega as mavlink

ANGLE_RAD = 2 * math.pi + 0.1  # an Euler angle
RATE_RADS = 50.0  # an angular rate (about 2900 deg/s)
ACCEL_MPS2 = 2000.0  # a specific force (about 200 g)
POSITION_M = 1.0e6  # a local position from the EKF origin
SPEED_MPS = 500.0
LAT_E7 = 90 * 10**7
LON_E7 = 180 * 10**7

_EULER = {"roll": ANGLE_RAD, "pitch": ANGLE_RAD, "yaw": ANGLE_RAD}
_RATES = {"rollspeed": RATE_RADS, "pitchspeed": RATE_RADS, "yawspeed": RATE_RADS}
_IMU = {**{f"{axis}acc": ACCEL_MPS2 for axis in "xyz"}, **{f"{axis}gyro": RATE_RADS for axis in "xyz"}}
ALTITUDE_MM = 1.0e7  # AMSL, mm (10 km)
_LOCATION = {"latitude": LAT_E7, "longitude": LON_E7, "altitude": ALTITUDE_MM}

# message type -> {field: largest magnitude accepted}
BOUNDS: dict[str, dict[str, float]] = {
    "ATTITUDE": {**_EULER, **_RATES},
    "HIGHRES_IMU": _IMU,
    "LOCAL_POSITION_NED": {"x": POSITION_M, "y": POSITION_M, "z": POSITION_M,
                           "vx": SPEED_MPS, "vy": SPEED_MPS, "vz": SPEED_MPS},
    "GPS_GLOBAL_ORIGIN": _LOCATION,
    "HOME_POSITION": _LOCATION,
    "SIM_STATE": {"q1": 1.01, "q2": 1.01, "q3": 1.01, "q4": 1.01, "lat": 90.0, "lon": 180.0, "alt": 1.0e5,
                  "vn": SPEED_MPS, "ve": SPEED_MPS, "vd": SPEED_MPS, "lat_int": LAT_E7, "lon_int": LON_E7},
    "SIMSTATE": {**_EULER, "lat": LAT_E7, "lng": LON_E7},
    "ATT_POS_MOCAP": {"x": POSITION_M, "y": POSITION_M, "z": POSITION_M},  # the built-in SITL vehicle's truth
    "SCALED_PRESSURE": {"press_abs": 2000.0},
}


def rejection(msg: mavlink.MAVLink_message) -> str | None:
    """Why ``msg`` must not be used ("non-finite yaw", "xacc beyond 2000"), or None."""
    for name, bound in BOUNDS.get(msg.get_type(), {}).items():
        value = getattr(msg, name, 0)  # (an extension field an older sender leaves out reads 0)
        if not math.isfinite(value):
            return f"non-finite {name}"
        if abs(value) > bound:
            return f"{name} beyond {bound:g}"
    return None
