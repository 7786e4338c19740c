"""Which autopilot firmware is on the other end, and what that means for the messages it takes.

Built from the autopilot's HEARTBEAT (autopilot family, vehicle type) and AUTOPILOT_VERSION
(flight software version, capability bits). The differences the companion must respect, checked
against ArduPilot's source (libraries/GCS_MAVLink/GCS_Common.cpp, ArduCopter/GCS_Mavlink.cpp at
Copter-4.0 and Copter-4.1 tags):

- ArduPilot before 4.1 reports LOCAL_POSITION_NED relative to *home* (4.1 on: to the EKF
  origin), and Copter before 4.1 reads the z of SET_POSITION_TARGET_LOCAL_NED in MAV_FRAME_LOCAL_NED
  as relative to home too (x and y are always relative to the EKF origin);
- ArduPilot Copter before 4.1 silently ignores SET_POSITION_TARGET_LOCAL_NED with an acceleration
  (no GUIDED pos+vel+acc until 4.1); PX4 takes it;
- PX4 encodes integer parameters bytewise in PARAM_VALUE / PARAM_SET, ArduPilot casts them to
  float (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE / _C_CAST).
"""

from __future__ import annotations

from dataclasses import dataclass

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

VEHICLE_TYPES = {
    mavlink.MAV_TYPE_QUADROTOR: "copter", mavlink.MAV_TYPE_HEXAROTOR: "copter", mavlink.MAV_TYPE_OCTOROTOR: "copter",
    mavlink.MAV_TYPE_TRICOPTER: "copter", mavlink.MAV_TYPE_COAXIAL: "copter", mavlink.MAV_TYPE_HELICOPTER: "copter",
    mavlink.MAV_TYPE_DODECAROTOR: "copter", mavlink.MAV_TYPE_DECAROTOR: "copter",
    mavlink.MAV_TYPE_GENERIC_MULTIROTOR: "copter", mavlink.MAV_TYPE_FIXED_WING: "plane",
    mavlink.MAV_TYPE_VTOL_DUOROTOR: "plane", mavlink.MAV_TYPE_VTOL_QUADROTOR: "plane",
    mavlink.MAV_TYPE_VTOL_TILTROTOR: "plane", mavlink.MAV_TYPE_GROUND_ROVER: "rover",
    mavlink.MAV_TYPE_SURFACE_BOAT: "rover", mavlink.MAV_TYPE_SUBMARINE: "sub",
}
FIRMWARE_TYPES = {mavlink.FIRMWARE_VERSION_TYPE_DEV: "dev", mavlink.FIRMWARE_VERSION_TYPE_ALPHA: "alpha",
                  mavlink.FIRMWARE_VERSION_TYPE_BETA: "beta", mavlink.FIRMWARE_VERSION_TYPE_RC: "rc",
                  mavlink.FIRMWARE_VERSION_TYPE_OFFICIAL: ""}
# ArduPilot custom_mode numbers by vehicle (ArduCopter's for anything else, as before)
ARDUPILOT_MODES: dict[str, dict[int, str]] = {
    "copter": mavutil.mode_mapping_acm, "plane": mavutil.mode_mapping_apm, "rover": mavutil.mode_mapping_rover,
    "sub": mavutil.mode_mapping_sub}
ORIGIN_FRAME_SINCE = (4, 1, 0)  # ArduPilot: LOCAL_POSITION_NED and setpoint z relative to the EKF origin
COPTER_ACCELERATION_SINCE = (4, 1, 0)  # ArduPilot Copter: GUIDED takes pos + vel + acc targets


def decode_version(flight_sw_version: int) -> tuple[tuple[int, int, int], str]:
    """((major, minor, patch), release type) from AUTOPILOT_VERSION.flight_sw_version."""
    major, minor, patch = (flight_sw_version >> 24) & 0xFF, (flight_sw_version >> 16) & 0xFF, (flight_sw_version >> 8) & 0xFF
    return (major, minor, patch), FIRMWARE_TYPES.get(flight_sw_version & 0xFF, "")


@dataclass(frozen=True)
class Firmware:
    """The autopilot's family, vehicle type and (once AUTOPILOT_VERSION arrived) version."""

    autopilot: str  # "ArduPilot", "PX4" or "autopilot type N"
    vehicle: str  # "copter", "plane", "rover", "sub" or "other"
    version: tuple[int, int, int] | None = None
    release: str = ""  # "", "rc", "beta", ...
    capabilities: int = 0  # MAV_PROTOCOL_CAPABILITY bits

    @property
    def label(self) -> str:
        """e.g. "ArduPilot copter 4.0.5-rc"."""
        version = "" if self.version is None else " " + ".".join(str(v) for v in self.version)
        return f"{self.autopilot} {self.vehicle}{version}{'-' + self.release if self.release else ''}"

    def _ardupilot_before(self, version: tuple[int, int, int]) -> bool:
        return self.autopilot == "ArduPilot" and self.version is not None and self.version < version

    @property
    def local_position_relative_to_home(self) -> bool:
        """LOCAL_POSITION_NED is home-relative (ArduPilot < 4.1), not EKF-origin-relative."""
        return self._ardupilot_before(ORIGIN_FRAME_SINCE)

    @property
    def setpoint_z_relative_to_home(self) -> bool:
        """SET_POSITION_TARGET_LOCAL_NED z (MAV_FRAME_LOCAL_NED) is read relative to home (ArduPilot Copter < 4.1)."""
        return self.vehicle == "copter" and self._ardupilot_before(ORIGIN_FRAME_SINCE)

    @property
    def accepts_setpoint_acceleration(self) -> bool | None:
        """Whether position + velocity + acceleration targets are flown; None while the version is unknown."""
        if self.autopilot == "PX4":
            return True
        if self.autopilot != "ArduPilot" or self.version is None:
            return None
        return self.version >= COPTER_ACCELERATION_SINCE

    def ardupilot_mode_number(self, name: str) -> int:
        """ArduPilot custom_mode of mode ``name`` on this vehicle (ArduPlane's GUIDED is 15, ArduCopter's 4);
        ValueError if it has none."""
        by_name = {v: k for k, v in ARDUPILOT_MODES.get(self.vehicle, mavutil.mode_mapping_acm).items()}
        if name not in by_name:
            raise ValueError(f"ArduPilot {self.vehicle} has no mode {name!r}")
        return by_name[name]

    @property
    def params_bytewise(self) -> bool:
        """Integer parameters travel bytewise in PARAM_* float fields (PX4), not cast (ArduPilot)."""
        if self.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE:
            return True
        if self.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST:
            return False
        return self.autopilot == "PX4"


def firmware_from_heartbeat(autopilot: str, mav_type: int) -> Firmware:
    """What a HEARTBEAT tells (no version yet)."""
    return Firmware(autopilot, VEHICLE_TYPES.get(mav_type, "other"))


def with_version(firmware: Firmware, msg: mavlink.MAVLink_message) -> Firmware:
    """``firmware`` completed from an AUTOPILOT_VERSION message."""
    version, release = decode_version(msg.flight_sw_version)
    return Firmware(firmware.autopilot, firmware.vehicle, version, release, msg.capabilities)
