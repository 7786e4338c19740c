"""The mission runner: flies the steps of one mission file once (steps: companion/mission/steps.py).

Outcomes (``status``): ``completed``; ``aborted`` when the pilot (or a ground station) changed
mode (the setpoint stream stopped at that instant: no fighting the pilot); ``failed`` with the
reason otherwise, also when the autopilot's own failsafe changed the mode (it announced it by
STATUSTEXT, e.g. "EKF Failsafe": the reason quotes it and the failsafe is recorded as ``autopilot``).
A failed mission leaves an airborne vehicle holding position on the autopilot's estimate (the
hold setpoint keeps streaming, so PX4 stays in OFFBOARD and ArduPilot in GUIDED) unless a
failsafe decided to land: then the runner switches to LAND and waits for the disarm. While
airborne, every step watches the estimate: lost -> brake and hold on the autopilot's estimate
for at most ``failsafe.lost_hold_s``, then LAND (``MissionContext.ride_out_estimate_loss``).
The daemon stopping in flight leaves a hold target and switches to LAND (``mission.on_daemon_stop``,
:meth:`MissionRunner.on_daemon_stop`).
"""

from __future__ import annotations

import asyncio
import logging

import numpy as np

from companion import clock
from companion.health import State
from companion.mavlink.commands import CommandFailed
from companion.mavlink.setpoints import Setpoint
from companion.mission.context import FailsafeLanding, GuidanceTakeover, MissionContext, MissionFailed
from companion.mission.flight import TrajectoryFlight
from companion.mission.steps import (ArmStep, FlyStep, GotoStep, HoldStep, LandStep, Mission, MissionStep, PayloadDropStep,
                                     PoseSourceStep, ReturnToBaseStep, TakeoffStep, WaitReadyStep)

log = logging.getLogger("companion.mission")

OFFBOARD_PRESTREAM_S = 1.0  # PX4 refuses OFFBOARD unless setpoints already stream (> 2 Hz)
FAILSAFE_LAND_TIMEOUT_S = 120.0
TAKEOFF_REACHED_M = 0.1  # the take-off is done within this of the altitude ...
TAKEOFF_SETTLED_MPS = 0.1  # ... climbing no faster than this
# A fixed wing never comes to rest: ArduPlane's TECS holds its height within a few metres, and
# its take-off overshoots and settles (ArduPlane 4.0.7 SITL to 60 m: 70 m at 10 s, 55-59 m at 20-40 s)
FIXED_WING_TAKEOFF_REACHED_M = 5.0
FIXED_WING_TAKEOFF_SETTLED_MPS = 1.0
LAND_SETTLE_M = 0.3  # a guidance's landing waits until the estimate is within this of its point (horizontal) ...
LAND_SETTLE_MPS = 0.2  # ... and slower than this (LAND holds where the vehicle stops: from 5 m/s, metres on)
LAND_SETTLE_TIMEOUT_S = 30.0  # ... for at most this long, then lands where it is


class MissionRunner:
    """Flies one mission once; publishes its progress on the ``mission`` stream."""

    def __init__(self, mission: Mission, allow_arm: bool, ctx: MissionContext, on_stop: str = "land") -> None:
        self.mission = mission
        self.allow_arm = allow_arm
        self.on_stop = on_stop  # mission.on_daemon_stop
        self.ctx = ctx
        self.status = "pending"
        self.step_index = -1
        self.reason = ""
        self.flight: TrajectoryFlight | None = None
        self._takeoff_altitude: float | None = None
        ctx.setpoints.on_takeover = ctx.on_mode_taken

    def snapshot(self) -> dict:
        steps = self.mission.steps
        kind = steps[self.step_index].kind if 0 <= self.step_index < len(steps) else None
        flight = self.flight
        done = max(self.step_index, 0) + (flight.progress if flight is not None and kind == "fly" else 0.0)
        failsafes = self.ctx.failsafes
        return {"name": self.mission.name, "state": self.status, "step": self.step_index, "step_kind": kind,
                "steps": len(steps), "reason": self.reason,
                "progress": 1.0 if self.status == "completed" else done / len(steps),
                "tracking_error_m": flight.tracking_error_m if flight is not None and kind == "fly" else None,
                "passes": dict(flight.passes) if flight is not None else {},  # a copy: the publisher encodes later
                "failsafe": failsafes[-1]["kind"] if failsafes else None, "failsafes": list(failsafes),
                "failsafe_counts": dict(self.ctx.failsafe_counts)}

    async def run(self) -> None:
        """Fly the mission once. It is never restarted: a bug in a step ends the mission as failed
        (holding, if airborne), and a run after that (a supervisor restart) only waits."""
        if self.status != "pending":
            await asyncio.Event().wait()
        try:
            await self._run_steps()
        except FailsafeLanding as exc:
            self._set("failed", str(exc))
            await self._failsafe_land()
        except MissionFailed as exc:
            await self._end_failed(str(exc))
        except Exception as exc:  # a bug: never re-fly from step 0 in the air
            log.exception("mission %s: step %d crashed", self.mission.name, self.step_index)
            await self._end_failed(f"internal error in step {self.step_index}: {type(exc).__name__}: {exc}")
        else:
            self._set("completed")
        await asyncio.Event().wait()

    async def _run_steps(self) -> None:
        """The steps in order; a pipeline's takeover (GNSS lost) jumps to the next
        ``return_to_base`` step, or without one flies its guidance and ends the mission failed."""
        steps = self.mission.steps
        index = 0
        while index < len(steps):
            self.step_index = index
            self._set("running")
            try:
                await self._run_step(steps[index])
            except GuidanceTakeover as exc:
                self.ctx.record_failsafe("guidance", f"{exc}: following the pipeline's guidance")
                later = next((k for k in range(index + 1, len(steps)) if steps[k].kind == "return_to_base"), None)
                if later is None:
                    await self._return_to_base(ReturnToBaseStep())
                    raise MissionFailed(f"{exc}: the pipeline's guidance was flown instead of the mission") from exc
                index = later
                continue
            index += 1

    async def on_daemon_stop(self, mode_timeout_s: float) -> None:
        """The daemon is stopping: if the mission commands the vehicle in flight, leave it safe.

        A position target at the autopilot's stopping point first (whatever feed-forward was
        streaming must not carry the vehicle on), then, with ``on_daemon_stop: land``, LAND,
        waiting at most ``mode_timeout_s`` for the COMMAND_ACK.
        """
        ctx = self.ctx
        if not (ctx.airborne and ctx.state.armed and ctx.setpoints.commanding and not ctx.takeover.is_set()):
            return
        try:
            ctx.hold_on_autopilot(ctx.yaw())
        except FailsafeLanding:
            pass  # no autopilot position to hold at: LAND regardless of the setting
        else:
            if self.on_stop == "hold":
                log.warning("daemon stopping in flight: left holding in %s", ctx.state.mode)
                return
        log.warning("daemon stopping in flight: switching to %s", ctx.commander.landing_mode)
        ctx.setpoints.expect_mode(ctx.commander.landing_mode)
        try:
            await asyncio.wait_for(ctx.commander.land(), mode_timeout_s)
        except TimeoutError:
            log.error("%s on daemon stop: no COMMAND_ACK within %.1f s", ctx.commander.landing_mode, mode_timeout_s)
        except CommandFailed as exc:
            log.error("%s on daemon stop: %s", ctx.commander.landing_mode, exc)

    # -- outcome ----------------------------------------------------------------------------

    def _set(self, status: str, reason: str = "") -> None:
        self.status, self.reason = status, reason
        if status in ("failed", "aborted"):
            log.error("mission %s %s: %s", self.mission.name, status, reason)
        else:
            log.info("mission %s: %s step %d", self.mission.name, status, self.step_index)
        self.ctx.publish("mission", self.snapshot())

    async def _end_failed(self, reason: str) -> None:
        ctx = self.ctx
        if ctx.takeover.is_set():
            ctx.setpoints.stop()  # (stopped at the takeover already; a step may have commanded since)
            self._set("failed" if ctx.autopilot_failsafe else "aborted", ctx.takeover_reason)
            return
        if not (ctx.airborne and ctx.state.armed):
            ctx.setpoints.stop()
            self._set("failed", reason)
            return
        try:
            if not ctx.failsafes or ctx.failsafes[-1]["kind"] not in ("geofence", "pass_tolerance"):
                ctx.hold_on_autopilot(ctx.yaw())  # (those two already hold where they braked)
        except FailsafeLanding as exc:
            self._set("failed", f"{reason}; {exc}")
            await self._failsafe_land()
            return
        self._set("failed", reason)

    async def _failsafe_land(self) -> None:
        try:
            await self._land(LandStep(timeout_s=FAILSAFE_LAND_TIMEOUT_S))
        except (MissionFailed, CommandFailed) as exc:
            log.error("failsafe landing: %s", exc)
        self.ctx.publish("mission", self.snapshot())

    # -- steps ------------------------------------------------------------------------------

    async def _run_step(self, step: MissionStep) -> None:
        kind = step.kind
        if kind != "return_to_base":  # (that step follows the guidance a takeover would hand it)
            self.ctx.check_takeover()
        try:
            await getattr(self, f"_{kind}")(getattr(step, kind))
        except CommandFailed as exc:
            raise MissionFailed(f"{kind}: {exc}") from exc

    async def _wait_ready(self, step: WaitReadyStep) -> None:
        ctx = self.ctx
        await self.ctx.wait_for(lambda: ctx.origin.ready and ctx.autopilot_position_fresh()
                                and ctx.estimate_status().state == State.OK and ctx.autopilot_agrees(),
                                step.timeout_s, "a confirmed origin and home, an autopilot position that agrees "
                                "with a healthy estimate")

    async def _mode(self, name: str) -> None:
        ctx = self.ctx
        if name == "OFFBOARD":
            ctx.hold_on_autopilot(ctx.yaw())
            await asyncio.sleep(OFFBOARD_PRESTREAM_S)
        ctx.setpoints.expect_mode(name)
        await ctx.commander.set_mode(name)
        await self.ctx.wait_for(lambda: ctx.state.mode == name, 3.0, f"mode {name}")

    async def _arm(self, step: ArmStep) -> None:
        ctx = self.ctx
        if not self.allow_arm:
            raise MissionFailed("arming is not allowed by the config (mission.allow_arm: false)")
        deadline = clock.now() + step.timeout_s
        while True:  # a refusal (pre-arm check) is retried every second until the timeout
            try:
                await ctx.commander.arm()
                break
            except CommandFailed:
                if clock.now() + 1.0 > deadline:
                    raise
                log.info("arming refused (see the autopilot's PreArm message); retrying")
                await asyncio.sleep(1.0)
        await self.ctx.wait_for(lambda: ctx.state.armed, max(1.0, deadline - clock.now()), "the armed state")

    async def _takeoff(self, step: TakeoffStep) -> None:
        """MAV_CMD_NAV_TAKEOFF, then wait until at ``step.altitude_m`` (m above home) and settled. In
        the autopilot's TAKEOFF mode (ArduPlane, which takes no NAV_TAKEOFF command in GUIDED: armed in
        TAKEOFF, it climbs to its TKOFF_ALT by itself) only the wait; a fixed wing's tolerance is its own."""
        ctx = self.ctx
        if ctx.state.mode != "TAKEOFF":
            await ctx.commander.takeoff(step.altitude_m)
        ctx.airborne = True
        self._takeoff_altitude = step.altitude_m
        firmware = ctx.state.firmware
        fixed_wing = firmware is not None and firmware.vehicle == "plane"
        reached_m = FIXED_WING_TAKEOFF_REACHED_M if fixed_wing else TAKEOFF_REACHED_M
        settled_mps = FIXED_WING_TAKEOFF_SETTLED_MPS if fixed_wing else TAKEOFF_SETTLED_MPS

        def reached() -> bool:  # and settled: a trajectory planned from here starts at rest
            p, v = ctx.state.local_position_ned, ctx.state.local_velocity_ned
            return (p is not None and v is not None and ctx.autopilot_position_fresh()
                    and abs(-p[2] - step.altitude_m) < reached_m and abs(v[2]) < settled_mps)

        def climb_on() -> None:  # the hold of a ride-out replaced the take-off: climb as a position target
            ctx.hold_on_autopilot(ctx.yaw(), height_m=step.altitude_m)
        await ctx.wait_for(reached, step.timeout_s, f"{step.altitude_m:g} m altitude", after_ride_out=climb_on)

    async def _hold(self, step: HoldStep) -> None:
        """Hold the current position target, or (right after the take-off) where the autopilot is,
        at the take-off height."""
        ctx = self.ctx
        ctx.check_takeover()
        current = ctx.setpoints.current
        if current is not None and current.position_ned is not None:
            ctx.setpoints.command(Setpoint(position_ned=current.position_ned, yaw_rad=current.yaw_rad))
        else:
            ctx.hold_on_autopilot(ctx.yaw(), height_m=self._takeoff_altitude)
        await self._fly_on_for(step.seconds, "the end of the hold")

    async def _goto(self, step: GotoStep) -> None:
        """One position target, flown by the autopilot for ``step.seconds`` (steps.py, ``goto``)."""
        ctx = self.ctx
        if not ctx.state.armed:
            raise MissionFailed("goto: the vehicle is not flying (take off first)")
        ctx.airborne = True  # also a fixed wing started in the air, which had no take-off step
        target = np.array(step.position, dtype=float)
        why = ctx.geofence.violation(target) if ctx.geofence is not None else None
        if why is not None:
            raise MissionFailed(f"goto: the target is outside the geofence: {why}")
        ctx.check_takeover()
        ctx.setpoints.command(Setpoint(position_ned=target))
        await self._fly_on_for(step.seconds, f"the end of the goto to {tuple(round(c, 1) for c in step.position)}")

    async def _fly_on_for(self, seconds: float, what: str) -> None:
        """Let the commanded setpoint be flown for ``seconds`` (the estimate watched meanwhile)."""
        end = clock.now() + seconds
        await self.ctx.wait_for(lambda: clock.now() >= end, seconds + 1.0, what)

    async def _fly(self, step: FlyStep) -> None:
        self.flight = TrajectoryFlight(step, self.ctx)
        await self.flight.fly()

    async def _payload_drop(self, step: PayloadDropStep) -> None:
        await self._hold(HoldStep(seconds=0.0))
        self.ctx.check_takeover()  # never release after the pilot took over
        await self.ctx.commander.release_payload(self.ctx.payload)
        log.info("payload released")
        await self._hold(HoldStep(seconds=step.hold_s))

    async def _return_to_base(self, step: ReturnToBaseStep) -> None:
        """Fly the guidance source's wishes (steps.py, ``return_to_base``) until it lands or stops."""
        ctx = self.ctx
        ctx.following_guidance = True
        try:
            ctx.check_takeover()  # the pilot's
            if ctx.guidance() is None:
                problem = ctx.request_guidance("mission step return_to_base")
                if problem is not None:
                    raise MissionFailed(f"return_to_base: {problem}")
            deadline = clock.now() + step.timeout_s
            while True:
                ctx.check_takeover()
                wish = ctx.guidance()
                if wish is None:
                    log.info("return_to_base: the guidance ended (GNSS back?): the mission goes on")
                    current = ctx.setpoints.current
                    if current is not None and current.position_ned is not None:  # no feed-forward left streaming
                        ctx.setpoints.command(Setpoint(position_ned=current.position_ned, yaw_rad=current.yaw_rad))
                    return
                if not wish.is_finite():
                    raise MissionFailed(f"return_to_base: non-finite guidance ({wish.reason})")
                if wish.kind == "land":
                    await self._settle_over(wish.position_ned, wish.yaw_rad)
                    log.info("return_to_base: landing (%s)", wish.reason)
                    await self._land(LandStep(timeout_s=step.land_timeout_s))
                    return
                ctx.setpoints.command(Setpoint(position_ned=wish.position_ned,
                                               velocity_ned=wish.velocity_ned if wish.kind == "fly" else None,
                                               yaw_rad=wish.yaw_rad))
                status = ctx.estimate_status()
                if status.state == State.LOST:
                    started = clock.now()
                    await ctx.ride_out_estimate_loss(status, ctx.yaw())
                    deadline += clock.now() - started
                if clock.now() > deadline:
                    raise MissionFailed(f"return_to_base: not landed after {step.timeout_s:g} s ({wish.reason})")
                await ctx.control_tick(clock.now() + 1.0 / ctx.control.rate_hz)
        finally:
            ctx.following_guidance = False

    async def _settle_over(self, point_ned: np.ndarray, yaw_rad: float | None) -> None:
        """Hold ``point_ned`` (LOCAL_NED m) until the companion's estimate is within
        ``LAND_SETTLE_M`` of it horizontally and slower than ``LAND_SETTLE_MPS``, at most
        ``LAND_SETTLE_TIMEOUT_S``: the autopilot's LAND holds the point where the vehicle comes to
        rest, so a landing switched at cruise speed ends metres past its point."""
        ctx = self.ctx
        # position with a zero velocity, not position alone: ArduCopter 4.0 flies a position-only
        # GUIDED target as a new waypoint leg, and streamed at the setpoint rate it crept 8 m back
        # to the point at 0.3 m/s until the 30 s ran out (ArduCopter 4.0.5 SITL)
        ctx.setpoints.command(Setpoint(position_ned=np.asarray(point_ned, dtype=float), velocity_ned=np.zeros(3),
                                       yaw_rad=ctx.yaw() if yaw_rad is None else yaw_rad))
        give_up = clock.now() + LAND_SETTLE_TIMEOUT_S

        def settled() -> bool:
            now = ctx.measured()
            if now is None:
                return False
            off = np.hypot(now.position_ned[0] - point_ned[0], now.position_ned[1] - point_ned[1])
            return bool(off < LAND_SETTLE_M and np.linalg.norm(now.velocity_ned) < LAND_SETTLE_MPS)

        await ctx.wait_for(lambda: settled() or clock.now() > give_up, LAND_SETTLE_TIMEOUT_S + 5.0,
                           "the vehicle to settle over its landing point")
        if not settled():
            log.warning("return_to_base: not settled over the landing point after %.0f s: landing where it is",
                        LAND_SETTLE_TIMEOUT_S)

    async def _pose_source(self, step: PoseSourceStep) -> None:
        self.ctx.select_source(step.source)
        log.info("pose source commanded: %s", step.source or "the priority order")

    async def _land(self, step: LandStep) -> None:
        ctx = self.ctx
        ctx.setpoints.stop()
        ctx.setpoints.expect_mode(ctx.commander.landing_mode)
        await ctx.commander.land()
        ctx.airborne = False
        await self.ctx.wait_for(lambda: not ctx.state.armed, step.timeout_s, "touchdown and disarm")
