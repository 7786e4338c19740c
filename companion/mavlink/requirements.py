"""The autopilot parameters the companion needs for its configured pipelines (pure, no I/O).

``companion setup-autopilot`` prints the difference between these and what the autopilot has
(and writes them with ``--apply``); ``companion sitl --ardupilot`` applies them to ArduPilot SITL
through it; the daemon points to it when it first finds the autopilot. Which parameters exist decides the firmware generation,
never a version number alone: ArduPilot 4.1 replaced EKF2's external-navigation switches by
EKF3 source sets (EK3_SRC1_*), 4.5 renamed GPS_TYPE to GPS1_TYPE.

Sources: ArduPilot wiki "Non-GPS navigation" and "EKF source selection", REFERENCE.md, and the
Copter 4.0 source (AP_Arming_Copter::gps_checks, NavEKF2 external navigation), checked against
the 4.0 SITL in ../shared/ardupilot.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from companion import plugins
from companion.config import Config
from companion.mavlink.firmware import Firmware

EXTNAV = 6  # EK3_SRCn_*: ExternalNAV
COMPASS = 1  # EK3_SRCn_YAW: Compass
ARMING_CHECK_ALL = 1
ARMING_CHECK_GPS = 1 << 3
ARMING_CHECK_ALL_BITS = (1 << 16) - 2  # bits 1..15: every individual check of Copter 4.0


@dataclass(frozen=True)
class Requirement:
    """One parameter the companion needs: a fixed value, or one derived from the current value."""

    name: str
    want: float | Callable[[float], float]
    why: str
    reboot: bool = False  # the autopilot reads it at boot only

    def wanted(self, current: float) -> float:
        return self.want(current) if callable(self.want) else float(self.want)


@dataclass(frozen=True)
class Difference:
    """A parameter whose value differs from what the companion needs."""

    name: str
    current: float
    wanted: float
    why: str
    reboot: bool


def without_gps_arming_check(current: float) -> float:
    """ARMING_CHECK with the GPS check off and every other check kept (1 = all becomes the explicit bits)."""
    bits = ARMING_CHECK_ALL_BITS if int(current) & ARMING_CHECK_ALL else int(current)
    return float(bits & ~ARMING_CHECK_GPS)


def uses_external_navigation(cfg: Config) -> bool:
    """The configured pipelines give the autopilot its position (indoors, no GPS)."""
    return bool(cfg.source_priority())


def heading_from_companion(cfg: Config) -> bool:
    """Every pose source measures the heading itself (walls, floor markers), so the autopilot takes
    its yaw from the companion and its compass (unreliable indoors) is turned off. A source that
    carries the autopilot's own heading forward (ekf_slam) needs the compass kept: with both off,
    each would follow the other and the true heading would be known to neither (seen on ArduCopter
    4.0 SITL: 135 degrees off from the take-off on, every landmark rotated with it)."""
    return all(plugins.pipeline(name).heading for name in cfg.source_priority())


def requirements(firmware: Firmware, cfg: Config, params: Mapping[str, float]) -> list[Requirement]:
    """What this config needs from this autopilot; parameters the firmware lacks are left out."""
    if not uses_external_navigation(cfg):
        return []
    if firmware.autopilot == "PX4":
        wanted = _px4_external_navigation(params)
    elif firmware.autopilot == "ArduPilot":
        wanted = (_ardupilot_companion_port(cfg.mavlink.autopilot_serial_port)
                  + _ardupilot_external_navigation(params, heading_from_companion(cfg), position_sigma_m(cfg))
                  + _ardupilot_indoor_failsafes(firmware))
    else:
        return []
    return [r for r in wanted if r.name in params]


def _ardupilot_companion_port(serial: int | None) -> list[Requirement]:
    """MAVLink 2 at 921600 baud on the port wired to the companion: the bandwidth for 30 Hz
    estimates and 50 Hz setpoints, and (4.0) a receive-time bound on the estimates' stamps that
    the baud rate tightens (GCS_MAVLINK::correct_offboard_timestamp_usec_to_ms)."""
    if serial is None:
        return []
    return [Requirement(f"SERIAL{serial}_PROTOCOL", 2, "MAVLink 2 on the port the companion is wired to", reboot=True),
            Requirement(f"SERIAL{serial}_BAUD", 921, "921600 baud on the companion's port", reboot=True)]


def position_sigma_m(cfg: Config) -> float:
    """The largest typical position 1-sigma of the pose sources (m): what EKF2 4.0 must assume of
    every estimate, since it ignores the covariance each one carries."""
    return max(plugins.pipeline(name).position_sigma_m for name in cfg.source_priority())


def _ardupilot_external_navigation(params: Mapping[str, float], heading: bool, sigma_m: float) -> list[Requirement]:
    """External navigation for position (and, with ``heading``, yaw instead of the compass);
    ``sigma_m``: the estimates' position noise for EKF2 (4.0)."""
    gps_type = "GPS1_TYPE" if "GPS1_TYPE" in params else "GPS_TYPE"
    common = [
        Requirement("VISO_TYPE", 1, "external navigation over MAVLink (VISION_POSITION_ESTIMATE)", reboot=True),
        Requirement(gps_type, 0, "indoors: no GPS, an enabled one can pull the position away", reboot=True),
    ]
    if "EK3_SRC1_POSXY" in params:  # 4.1 and later: EKF3 source sets
        return common + [
            Requirement("AHRS_EKF_TYPE", 3, "EKF3: the one with external-navigation source sets"),
            Requirement("EK3_ENABLE", 1, "EKF3 running", reboot=True),
            Requirement("EK3_SRC1_POSXY", EXTNAV, "horizontal position from the companion"),
            Requirement("EK3_SRC1_VELXY", EXTNAV, "horizontal velocity from the companion (VISION_SPEED_ESTIMATE)"),
            Requirement("EK3_SRC1_POSZ", EXTNAV, "height from the companion (lidar height over the floor)"),
            Requirement("EK3_SRC1_VELZ", EXTNAV, "vertical velocity from the companion"),
        ] + ([Requirement("EK3_SRC1_YAW", EXTNAV, "heading from the companion (magnetometers are unreliable indoors)")]
             if heading else [Requirement("EK3_SRC1_YAW", COMPASS, "heading from the compass: the companion's pose "
                                          "sources carry the autopilot's heading forward")])
    return common + [  # 4.0: EKF2, external navigation when GPS is inhibited; height follows the position
        Requirement("EK2_GPS_TYPE", 3, "EKF2: no GPS, use external navigation"),
        Requirement("EK2_POSNE_M_NSE", sigma_m, "4.0 ignores the estimate's covariance and takes this as its noise: "
                    "the pose sources' (the default 1 m lets the EKF wander centimetres off a lidar estimate; "
                    "0.1 m on a GNSS-grade one lets its noise turn the EKF's heading away from the gyro)"),
    ] + ([
        Requirement("COMPASS_USE", 0, "EKF2 takes the heading from external navigation only without a compass"),
        Requirement("COMPASS_USE2", 0, "as COMPASS_USE"),
        Requirement("COMPASS_USE3", 0, "as COMPASS_USE"),
    ] if heading else [
        Requirement("COMPASS_USE", 1, "heading from the compass: the companion's pose sources carry the autopilot's "
                    "heading forward"),
    ]) + [
        Requirement("ARMING_CHECK", without_gps_arming_check,
                    "Copter 4.0 refuses to arm in GUIDED without GPS (\"High GPS HDOP\"): every check but GPS"),
    ]


def _ardupilot_indoor_failsafes(firmware: Firmware) -> list[Requirement]:
    if firmware.vehicle != "copter":
        return []
    return [
        Requirement("FS_EKF_ACTION", 1, "EKF failsafe (e.g. the companion's estimate stops): land"),
        Requirement("FS_THR_ENABLE", 3, "radio failsafe indoors: land (RTL would climb to RTL_ALT)"),
    ]


def _px4_external_navigation(params: Mapping[str, float]) -> list[Requirement]:
    """From PX4's documentation; not tested against PX4 (no PX4 SITL here)."""
    if "EKF2_EV_CTRL" in params:  # PX4 1.14 and later
        return [Requirement("EKF2_EV_CTRL", 15, "fuse vision position (horizontal, vertical), velocity and yaw"),
                Requirement("EKF2_HGT_REF", 3, "height reference: vision"),
                Requirement("EKF2_GPS_CTRL", 0, "indoors: no GPS")]
    return [Requirement("EKF2_AID_MASK", 24, "fuse vision position and yaw (bits 3 and 4)"),
            Requirement("EKF2_HGT_MODE", 3, "height reference: vision")]


def differences(required: list[Requirement], params: Mapping[str, float]) -> list[Difference]:
    """The required parameters whose current value is not the wanted one (float32 tolerance)."""
    out = []
    for r in required:
        current = params[r.name]
        wanted = r.wanted(current)
        if not math.isclose(current, wanted, rel_tol=1e-6, abs_tol=1e-6):
            out.append(Difference(r.name, current, wanted, r.why, r.reboot))
    return out
