"""What the copter's and the fixed wing's flight controllers share: the MAVLink-facing command
handling (mode change, arming checks, arm, disarm, take-off checks), the public state the
simulated vehicle reads, and how a SET_POSITION_TARGET_LOCAL_NED target is read.

Plain floats, no I/O. Frames: NED (m) in the EKF frame of the autopilot's own estimate
(:class:`sitl.estimator.Estimator`), never the truth; headings in rad.
"""

from __future__ import annotations

import math

from sitl.estimator import SEVERITY_CRITICAL, SEVERITY_INFO, Estimator, StatusQueue

# MAV_FRAME values accepted by SET_POSITION_TARGET_LOCAL_NED
MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_LOCAL_OFFSET_NED = 7
MAV_FRAME_BODY_NED = 8
MAV_FRAME_BODY_OFFSET_NED = 9
SUPPORTED_FRAMES = frozenset({MAV_FRAME_LOCAL_NED, MAV_FRAME_LOCAL_OFFSET_NED, MAV_FRAME_BODY_NED,
                              MAV_FRAME_BODY_OFFSET_NED})
BODY_FRAMES = frozenset({MAV_FRAME_BODY_NED, MAV_FRAME_BODY_OFFSET_NED})
# POSITION_TARGET_TYPEMASK
IGNORE_YAW = 1024
IGNORE_YAW_RATE = 2048
# type_mask without the yaw bits -> which setpoint fields are used (ArduPilot's accepted sets)
TARGET_KINDS = {
    0b111111000: "pos",  # 3576 with yaw bits
    0b111000111: "vel",  # 3527
    0b000111111: "acc",  # 3135
    0b111000000: "posvel",  # 3520
    0b000000000: "posvelacc",  # 3072
}


def target_kind(frame: int, type_mask: int) -> str | None:
    """Which setpoint fields a SET_POSITION_TARGET_LOCAL_NED uses (a value of :data:`TARGET_KINDS`),
    or None when its MAV_FRAME or its type_mask is not accepted."""
    return TARGET_KINDS.get(type_mask & 0x3FF) if frame in SUPPORTED_FRAMES else None


def rotate_xy(v: tuple[float, float, float], heading: float) -> tuple[float, float, float]:
    """Rotate a body-heading (forward, right, down) vector into NED by ``heading`` rad."""
    c, s = math.cos(heading), math.sin(heading)
    return c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]


class FlightControllerBase:
    """Mode table, arming, disarming and take-off checks of an ArduPilot-like flight controller.

    Public state: ``mode`` (custom_mode), ``armed``, ``landed`` (the land detector), ``home_ned``
    (home in the EKF frame, m, or None), ``home_locked`` (set explicitly, not moved at arming),
    ``nonfinite_rejected`` (commands refused for a NaN or infinite field) and ``t`` (s, of the
    last update).

    A subclass tells its modes (``MODE_NAMES`` custom_mode -> name, ``POSITION_MODES`` that need a
    position to fly, ``ARMABLE_MODES``, ``ARMING_NEEDS_POSITION``, ``TAKEOFF_MODES`` that take
    MAV_CMD_NAV_TAKEOFF, ``GUIDED_MODE`` that flies position targets, ``RTL_MODE``) and implements :meth:`_enter_mode`, :meth:`_start_takeoff`
    and :meth:`_end_flight`.
    """

    MODE_NAMES: dict[int, str]
    POSITION_MODES: frozenset[int]
    ARMABLE_MODES: frozenset[int]
    ARMING_NEEDS_POSITION: frozenset[int]
    TAKEOFF_MODES: frozenset[int]
    GUIDED_MODE: int
    RTL_MODE: int

    def __init__(self, *, status: StatusQueue, estimator: Estimator, mode: int) -> None:
        self.status = status
        self.est = estimator
        self.mode = mode
        self.armed = False
        self.landed = True
        self.home_ned: tuple[float, float, float] | None = None
        self.home_locked = False
        self.nonfinite_rejected = 0
        self.t = 0.0
        self._arming_z = 0.0  # estimated NED z (m, down) where the vehicle armed

    @property
    def mode_name(self) -> str:
        """ArduPilot name of the current mode."""
        return self.MODE_NAMES[self.mode]

    @property
    def guided(self) -> bool:
        """In GUIDED (position targets are flown)."""
        return self.mode == self.GUIDED_MODE

    # ------------------------------------------------------------------ commands
    def set_mode(self, mode: int) -> tuple[bool, str]:
        """Change flight mode; refused for unknown modes and where :meth:`_mode_change_failure` says."""
        if mode not in self.MODE_NAMES:
            return False, f"Unsupported mode {mode}"
        reason = self._mode_change_failure(mode)
        if reason:
            return False, reason
        self._enter_mode(mode)
        return True, ""

    def arm(self, force: bool = False) -> tuple[bool, str]:
        """Arm after ArduPilot-like checks (``force`` skips them), then enter the current mode again."""
        if self.armed:
            return True, "Already armed"
        if not force:
            reason = self._arming_failure()
            if reason:
                self.status.push(SEVERITY_CRITICAL, reason)
                return False, reason
        self.armed = True
        self.landed = True
        self._arming_z = self.est.axes[2].p
        self._on_arm()
        if not self.home_locked and self.est.pos_valid:
            self.home_ned = self._position()
        self.status.push(SEVERITY_INFO, "Arming motors")
        self._enter_mode(self.mode)
        return True, ""

    def disarm(self, force: bool = False) -> tuple[bool, str]:
        """Disarm; refused in flight unless ``force``."""
        if not self.armed:
            return True, "Already disarmed"
        if not self.landed and not force:
            return False, "Disarm: vehicle not landed"
        self._disarm()
        return True, ""

    def takeoff(self, altitude_m: float) -> tuple[bool, str]:
        """Take off to ``altitude_m`` above home (or the arming point) with :meth:`_start_takeoff`:
        in a ``TAKEOFF_MODES`` mode, armed, on the ground, with a position."""
        if not math.isfinite(altitude_m):
            self.nonfinite_rejected += 1
            return False, "Takeoff: altitude not finite"
        if self.mode not in self.TAKEOFF_MODES:
            return False, "Takeoff: mode is not GUIDED"
        if not self.armed:
            return False, "Takeoff: not armed"
        if not self.landed:
            return False, "Takeoff: already flying"
        if altitude_m <= 0.0:
            return False, "Takeoff: altitude must be positive"
        if not self.est.pos_valid:
            return False, "Takeoff: requires position"
        self._start_takeoff(altitude_m)
        return True, ""

    # ------------------------------------------------------------------ checks
    def _mode_change_failure(self, mode: int) -> str:
        """Why a change to a known ``mode`` is refused, or '': a position mode needs a position, RTL a home."""
        if mode in self.POSITION_MODES and not self.est.pos_valid:
            return f"Mode change to {self.MODE_NAMES[mode]} failed: requires position"
        if mode == self.RTL_MODE and self.home_ned is None:
            return "Mode change to RTL failed: no home"
        return ""

    def _arming_failure(self) -> str:
        """Reason arming is refused, or '' if the checks pass."""
        if not self.landed:
            return "Arm: vehicle not landed"
        if self.mode not in self.ARMABLE_MODES:
            return f"Arm: Mode {self.MODE_NAMES[self.mode]} not armable"
        if self.mode in self.ARMING_NEEDS_POSITION and not self.est.pos_valid:
            return "PreArm: Need Position Estimate"
        return ""

    # ------------------------------------------------------------------ what a subclass flies
    def _enter_mode(self, mode: int) -> None:
        """Switch to ``mode`` and set what it flies from here."""
        raise NotImplementedError

    def _start_takeoff(self, altitude_m: float) -> None:
        """Begin the climb to ``altitude_m`` (m) above :meth:`_ground_z`; the checks have passed."""
        raise NotImplementedError

    def _end_flight(self) -> None:
        """Drop the flight state (take-off, phases, pending targets) on disarming."""
        raise NotImplementedError

    def _on_arm(self) -> None:
        """What else a subclass resets when it arms (before the mode is entered again); nothing here."""

    # ------------------------------------------------------------------ helpers
    def _disarm(self) -> None:
        self.armed = False
        self.landed = True
        self._end_flight()
        self.status.push(SEVERITY_INFO, "Disarming motors")

    def _ground_z(self) -> float:
        """NED z (m, down) of the ground heights count from: home's, else the arming point's."""
        return self.home_ned[2] if self.home_ned is not None else self._arming_z

    def _target_position(self, frame: int, pos: tuple[float, float, float]) -> tuple[float, float, float]:
        """A target position in ``frame`` as NED m in the EKF frame: body frames turned by the estimated
        heading, offset frames added to the estimated position."""
        p = rotate_xy(pos, self.est.ahrs.yaw) if frame in BODY_FRAMES else tuple(pos)
        if frame != MAV_FRAME_LOCAL_NED:
            here = self._position()
            p = (p[0] + here[0], p[1] + here[1], p[2] + here[2])
        return p

    def _position(self) -> tuple[float, float, float]:
        """Estimated NED position, m."""
        n, e, d = self.est.axes
        return n.p, e.p, d.p
