"""What every mission step works with: the autopilot, the setpoint stream, the companion's
estimate, and the failsafes shared by all airborne steps (estimate lost, pilot takeover).

Frames: LOCAL_NED metres at the EKF origin; times are the daemon clock (``companion.clock``).
"""

from __future__ import annotations

import asyncio
import logging
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field

import numpy as np

from companion import clock
from companion.config import ControlConfig, FailsafeConfig, PayloadConfig
from companion.control.outer_loop import MeasuredState
from companion.health import State
from companion.mavlink.autopilot import AutopilotState
from companion.mavlink.commands import Commander
from companion.messages import Guidance, PoseEstimate
from companion.mavlink.origin import OriginSetter
from companion.mavlink.setpoints import Setpoint, SetpointStream
from companion.mission.failsafe import EstimateStatus, Geofence, classify_estimate, stopping_point

log = logging.getLogger("companion.mission")

FAILSAFE_ANNOUNCED_WITHIN_S = 2.0  # an autopilot failsafe text this recent explains a mode change
RECENT_FAILSAFES = 20  # the mission stream carries the last ones (and counts of all)
RECOVERED_AFTER_S = 1.0  # an estimate back from lost must stay healthy this long before flying on
AUTOPILOT_POSITION_MAX_AGE_S = 1.0
AGREEMENT_M = 0.2  # before take-off, the autopilot's position within this of the companion's estimate
EKF_HORIZONTAL_POSITION = 0x08 | 0x10  # EKF_STATUS_REPORT / ESTIMATOR_STATUS: POS_HORIZ_REL | POS_HORIZ_ABS


class MissionFailed(Exception):
    """The mission cannot go on; the message is the reason published on telemetry."""


class FailsafeLanding(MissionFailed):
    """A failsafe decided to land (the runner switches to LAND and waits for the disarm)."""


class GuidanceTakeover(MissionFailed):
    """A pipeline took over the flight on its own (GNSS lost): the runner follows its guidance."""


def _no_guidance() -> Guidance | None:
    return None


def _cannot_guide(reason: str) -> str | None:
    return "no pipeline can fly the vehicle (none is a guidance source)"


@dataclass
class MissionContext:
    """The mission's view of the daemon (one per runner)."""

    state: AutopilotState
    commander: Commander
    setpoints: SetpointStream
    origin: OriginSetter
    estimate: Callable[[], PoseEstimate | None]  # the companion's newest fused estimate
    nav_health: Callable[[], tuple[State, str]]  # worst nav:* component and its reason
    publish: Callable[[str, dict], None]  # telemetry stream, payload
    control: ControlConfig
    failsafe: FailsafeConfig
    payload: PayloadConfig
    geofence: Geofence | None
    select_source: Callable[[str | None], None]  # pin a pose source (None: the priority order again)
    guidance: Callable[[], Guidance | None] = _no_guidance  # the guidance source's wish now (None: not active)
    request_guidance: Callable[[str], str | None] = _cannot_guide  # ask it to start: None, or why not
    # Wait for the control step due at a daemon time (s): the daemon runs it right after the nav
    # cycle of that tick (NavLoop.after_cycle), on the estimate just made.
    control_tick: Callable[[float], Awaitable[None]] = clock.sleep_until
    following_guidance: bool = False  # a return_to_base is flying the guidance (no takeover into itself)
    takeover: asyncio.Event = field(default_factory=asyncio.Event)
    takeover_reason: str = ""  # who changed the mode and to what (on_mode_taken)
    autopilot_failsafe: bool = False  # the autopilot's own failsafe took the mode (not a pilot)
    airborne: bool = False  # from the take-off command to the land command: the estimate is watched
    failsafes: deque[dict] = field(default_factory=lambda: deque(maxlen=RECENT_FAILSAFES))  # kind, t, reason
    failsafe_counts: dict[str, int] = field(default_factory=dict)  # kind -> how often it fired

    def on_mode_taken(self, mode: str) -> None:
        """Someone else changed the mode (the setpoint stream stopped): the autopilot's own
        failsafe if it announced one just before (recorded as failsafe ``autopilot``), else the
        pilot or a ground station."""
        self.takeover.set()
        announced = self.state.failsafe_text(clock.now() - FAILSAFE_ANNOUNCED_WITHIN_S)
        self.autopilot_failsafe = announced is not None
        if announced is not None:
            self.takeover_reason = f"autopilot failsafe to {mode}: {announced}"
            self.record_failsafe("autopilot", self.takeover_reason)
        else:
            self.takeover_reason = f"pilot or ground station changed the mode to {mode}"

    def check_takeover(self) -> None:
        """Raise if someone else took the flight: the pilot or the autopilot (MissionFailed), or,
        while airborne, a pipeline that started guiding on command (a MAVLink command) or on its
        own with ``failsafe.gnss_loss: return_to_base`` (GuidanceTakeover)."""
        if self.takeover.is_set():
            raise MissionFailed(self.takeover_reason)
        if self.airborne and not self.following_guidance:
            wish = self.guidance()
            if wish is not None and (wish.trigger == "commanded" or self.failsafe.gnss_loss == "return_to_base"):
                raise GuidanceTakeover(f"{wish.trigger}: {wish.reason}")

    def estimate_status(self) -> EstimateStatus:
        return classify_estimate(clock.now(), self.estimate(), self.nav_health(), self.failsafe.estimate_timeout_s)

    def measured(self) -> MeasuredState | None:
        """The companion's estimate as the controller's input; the velocity is the estimate's or,
        for a pipeline without one, the autopilot's. None without a (finite) estimate."""
        est = self.estimate()
        if est is None or not np.all(np.isfinite(est.position_ned)):
            return None
        velocity = est.velocity_ned
        if velocity is None:
            velocity = self.state.local_velocity_ned if self.autopilot_position_fresh() else None
        if velocity is None:
            return None
        return MeasuredState(tuple(float(c) for c in est.position_ned), tuple(float(c) for c in velocity))

    def yaw(self) -> float | None:
        est = self.estimate()
        return float(est.euler_rad[2]) if est is not None else None

    def autopilot_agrees(self) -> bool:
        """The autopilot's own position is within ``AGREEMENT_M`` of the companion's estimate when it
        fuses that estimate: its EKF has converged onto it (else it flies somewhere else)."""
        if not self.state.external_nav_in_use:
            return True
        est, p = self.estimate(), self.state.local_position_ned
        return est is not None and p is not None and float(np.linalg.norm(p - est.position_ned)) <= AGREEMENT_M

    def autopilot_position_fresh(self) -> bool:
        t = self.state.local_position_time
        return t is not None and clock.now() - t < AUTOPILOT_POSITION_MAX_AGE_S

    def record_failsafe(self, kind: str, reason: str) -> None:
        self.failsafes.append({"kind": kind, "t": clock.now(), "reason": reason})
        self.failsafe_counts[kind] = self.failsafe_counts.get(kind, 0) + 1
        log.warning("failsafe %s: %s", kind, reason)

    def hold_on_autopilot(self, yaw_rad: float | None = None, height_m: float | None = None) -> np.ndarray:
        """Brake and hold: a position target at the autopilot's own stopping point (its estimate),
        at ``height_m`` above the origin if given (e.g. the take-off height), else where it is.

        Raises :class:`FailsafeLanding` if the autopilot has no fresh position either, or its EKF
        flags (once reported) say it has no horizontal position.
        """
        p, v = self.state.local_position_ned, self.state.local_velocity_ned
        if p is None or v is None or not self.autopilot_position_fresh():
            raise FailsafeLanding("no position from the autopilot either: landing")
        flags = self.state.ekf_flags
        if flags and not flags & EKF_HORIZONTAL_POSITION:
            raise FailsafeLanding(f"the autopilot's EKF has no horizontal position either (flags {flags:#x}): landing")
        target = stopping_point(p, v, self.control.limits.accel_xy_mps2 / 2)
        if height_m is not None:
            target[2] = -height_m
        self.setpoints.command(Setpoint(position_ned=target, yaw_rad=yaw_rad))
        return target

    async def wait_for(self, condition: Callable[[], bool], timeout_s: float, what: str,
                       after_ride_out: Callable[[], None] | None = None) -> None:
        """Poll ``condition`` every 50 ms until true; :class:`MissionFailed` after ``timeout_s``.

        While ``airborne``, a lost estimate is ridden out on the way (the timeout pauses meanwhile)
        and ``after_ride_out`` then restores what the step was commanding.
        """
        deadline = clock.now() + timeout_s
        while not condition():
            self.check_takeover()
            if self.airborne:
                status = self.estimate_status()
                if status.state == State.LOST:
                    started = clock.now()
                    await self.ride_out_estimate_loss(status, self.yaw())
                    deadline += clock.now() - started
                    if after_ride_out is not None:
                        after_ride_out()
            if clock.now() > deadline:
                raise MissionFailed(f"timed out after {timeout_s:g} s waiting for {what}")
            await asyncio.sleep(0.05)

    async def ride_out_estimate_loss(self, status: EstimateStatus, yaw_rad: float | None) -> None:
        """Estimate lost: brake and hold on the autopilot's estimate until the companion's estimate
        is back (not lost: fresh and finite; it may still be degraded, which slows the flight) for
        ``RECOVERED_AFTER_S`` (return), at most ``failsafe.lost_hold_s``; then raise
        :class:`FailsafeLanding`."""
        self.record_failsafe("estimate_lost", f"{status.reason}: holding on the autopilot's estimate")
        self.hold_on_autopilot(yaw_rad)
        started = clock.now()
        healthy_since: float | None = None
        while clock.now() - started < self.failsafe.lost_hold_s:
            await self.control_tick(clock.now() + 1.0 / self.control.rate_hz)
            self.check_takeover()
            if self.estimate_status().state == State.LOST:
                healthy_since = None
                continue
            healthy_since = healthy_since if healthy_since is not None else clock.now()
            if clock.now() - healthy_since >= RECOVERED_AFTER_S:
                log.info("estimate back after %.1f s: flying on", clock.now() - started)
                return
        raise FailsafeLanding(f"estimate lost for {self.failsafe.lost_hold_s:g} s ({status.reason}): landing")
