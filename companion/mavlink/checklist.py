"""Autopilot parameters the companion relies on (REFERENCE.md; ArduPilot and PX4 docs).

`companion run` logs the list for the detected autopilot; the README carries the same
checklist with explanations.
"""

from __future__ import annotations

ARDUPILOT = (
    ("VISO_TYPE", "1 (MAVLink; reboot after setting)"),
    ("EK3_SRC1_POSXY", "6 (ExternalNAV)"),
    ("EK3_SRC1_VELXY", "6 (ExternalNAV) or 0"),
    ("EK3_SRC1_POSZ", "1 (Baro) or 6 (ExternalNAV)"),
    ("EK3_SRC1_YAW", "6 (ExternalNAV) or 1 (Compass)"),
    ("VISO_DELAY_MS", "the pipeline latency, e.g. 20"),
    ("VISO_POS_X/Y/Z", "0 (the companion already reports the body origin)"),
    ("GPS1_TYPE", "0 indoors (an enabled GPS can pull the position away)"),
)

PX4 = (
    ("EKF2_EV_CTRL", "position + yaw (+ velocity) bits, e.g. 11 or 15"),
    ("EKF2_HGT_REF", "Vision (3) or Baro"),
    ("EKF2_EV_DELAY", "the pipeline latency in ms"),
    ("EKF2_EV_POS_X/Y/Z", "0 (the companion already reports the body origin)"),
    ("COM_OF_LOSS_T / COM_OBL_RC_ACT", "offboard-loss timeout and action"),
)


def expected_parameters(autopilot: str | None) -> tuple[tuple[str, str], ...]:
    """(parameter, expected value) pairs for ``autopilot`` ("ArduPilot" or "PX4")."""
    return PX4 if autopilot == "PX4" else ARDUPILOT
