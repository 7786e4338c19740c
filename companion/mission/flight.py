"""The ``fly`` step: plan a smooth trajectory and fly it with the outer-loop controller.

Every ``1 / control.rate_hz`` seconds: classify the companion's estimate (ok / degraded / lost),
advance the trajectory time (slower while degraded, paused during holds), sample the reference,
run the controller (RPT by default) on the companion's estimate, send the setpoint, and check
the geofence and any window / door pass. Frames: LOCAL_NED metres, yaw radians from north.

Failsafes here (``MissionContext`` has the shared ones):

- estimate degraded: the trajectory time runs at ``failsafe.degraded_speed_factor`` (ramped,
  the references stay smooth: ``companion.mission.timeline``), back to full speed when ok;
- estimate lost: brake and hold on the autopilot's estimate; if it comes back in time the rest
  of the waypoints are replanned from where the vehicle is, else the mission lands;
- geofence: the planned trajectory must stay inside (else the step fails before moving); the
  estimate leaving it stops the flight and holds (the mission fails: the pilot decides);
- window / door pass: within 1 m of the opening the estimate must stay within the waypoint's
  ``pass_tolerance_m`` of the reference, else the flight stops and holds.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import numpy as np

from companion import clock
from companion.config import ControlConfig
from companion.control.pid import PidController, PidGains
from companion.control.outer_loop import ControlOutput, MeasuredState, OuterLoopController, position_only_target
from companion.control.reference import Reference
from companion.control.rpt import ACCELERATION, VELOCITY, RptController, RptLimits, RptParams
from companion.control.trajectory import Trajectory, plan
from companion.health import State
from companion.mavlink.firmware import Firmware
from companion.mavlink.setpoints import Setpoint
from companion.mission.context import MissionContext, MissionFailed
from companion.mission.timeline import Timeline
from companion.mission.steps import FlyStep, Waypoint

# A degraded estimate slows the flight until it has been healthy this long (s): an estimate
# flickering between degraded and healthy (corners coming in and out of view) does not make the
# speed flicker with it.
DEGRADED_RECOVERY_S = 1.0

log = logging.getLogger("companion.mission")

SAME_POINT_M = 0.02  # a first waypoint this close to the start is where the vehicle already is
PASS_ZONE_M = 1.0  # the pass tolerance is enforced while the reference is this close to the opening
MOVING_MPS = 0.05  # slower than this the reference has no direction: the whole error counts
TRAJECTORY_SAMPLE_S = 0.25  # spacing of the path published on the trajectory stream


def output_mode(configured: str, firmware: Firmware | None) -> str:
    """The setpoint form to fly with: ``control.output``, with ``auto`` resolved for this
    firmware (pos_vel_acc where it takes acceleration targets, else pos_vel, which every
    autopilot with a GUIDED / OFFBOARD position + velocity mode takes)."""
    if configured != "auto":
        return configured
    return "pos_vel_acc" if firmware is not None and firmware.accepts_setpoint_acceleration else "pos_vel"


def make_controller(cfg: ControlConfig) -> OuterLoopController:
    """The configured outer loop (RPT, or the PID baseline with the same poles) with its limits."""
    lim = cfg.limits
    limits = RptLimits(speed_xy_mps=lim.speed_xy_mps, accel_xy_mps2=lim.accel_xy_mps2, jerk_xy_mps3=lim.jerk_xy_mps3,
                       climb_mps=lim.climb_mps, descent_mps=lim.descent_mps, accel_z_mps2=lim.accel_z_mps2)
    xy = RptParams(cfg.xy.epsilon, cfg.xy.omega_n, cfg.xy.zeta, cfg.xy.k_i)
    z = RptParams(cfg.z.epsilon, cfg.z.omega_n, cfg.z.zeta, 0.0)
    if cfg.law == "pid":
        return PidController(PidGains.matching(xy, ACCELERATION), PidGains.matching(z, VELOCITY), limits)
    return RptController(xy, z, limits)


@dataclass(frozen=True)
class FlightPlan:
    """A trajectory and the mission waypoints it flies through (``waypoints[i]`` is the
    trajectory's waypoint ``i + 1``; its waypoint 0 is the start)."""

    trajectory: Trajectory
    waypoints: tuple[Waypoint, ...]

    def time_of(self, i: int) -> float:
        return float(self.trajectory.waypoint_times[i + 1])


def plan_flight(step: FlyStep, start: np.ndarray, waypoints: tuple[Waypoint, ...], yaw_rad: float) -> FlightPlan:
    """Plan from ``start`` (NED m, at rest; not at the first waypoint) through ``waypoints``.
    Pure CPU work (~0.2 s for the patrol); ValueError / RuntimeError when it cannot be planned."""
    points = np.array([start] + [w.position for w in waypoints], dtype=float)
    speeds = [w.speed_mps or step.speed_mps for w in waypoints]
    stops = [i + 1 for i, w in enumerate(waypoints[:-1]) if w.stop or w.hold_s > 0]
    yaw_fixed = math.radians(step.yaw_deg) if step.yaw_deg is not None else None
    trajectory = plan(points, speeds, step.accel_mps2, step.jerk_mps3, kind=step.kind, yaw_mode=step.yaw,
                      yaw_fixed_rad=yaw_fixed, initial_yaw_rad=yaw_rad, stops=stops, corridor_m=step.corridor_m)
    return FlightPlan(trajectory, waypoints)


class TrajectoryFlight:
    """Flies one ``fly`` step; progress is readable while it runs (``tracking_error_m``, ``progress``)."""

    def __init__(self, step: FlyStep, ctx: MissionContext) -> None:
        self.step = step
        self.ctx = ctx
        self.tracking_error_m: float | None = None
        self.progress = 0.0
        self.passes: dict[str, float] = {}  # opening -> closest approach of the estimate (m)
        self.timeout_s = 0.0
        self._deadline = math.inf

    async def fly(self) -> None:
        """Plan and fly; after a lost estimate came back, replan what is left from where the vehicle holds."""
        remaining = tuple(self.step.waypoints)
        while remaining:
            measured = self.ctx.measured()
            if measured is None:
                raise MissionFailed("fly: no estimate to start from")
            first = remaining[0]
            if np.linalg.norm(np.asarray(first.position) - np.asarray(measured.position_ned)) < SAME_POINT_M:
                await self._hold_at(np.asarray(first.position, dtype=float), first.hold_s)  # already there
                remaining = remaining[1:]
                continue
            flight = await self._plan(np.asarray(measured.position_ned), remaining)
            if self._deadline == math.inf:
                holds = sum(w.hold_s for w in self.step.waypoints)
                self.timeout_s = (self.step.timeout_s or flight.trajectory.duration / self.ctx.failsafe.degraded_speed_factor
                                  + holds + 30.0)
                self._deadline = clock.now() + self.timeout_s
            remaining = await self._follow(flight)

    async def _plan(self, start: np.ndarray, waypoints: tuple[Waypoint, ...]) -> FlightPlan:
        ctx = self.ctx
        try:
            flight = await clock.compute(plan_flight, self.step, start, waypoints, ctx.yaw() or 0.0)
        except (ValueError, RuntimeError) as exc:
            raise MissionFailed(f"fly: cannot plan a trajectory: {exc}") from exc
        traj = flight.trajectory
        path = traj.sample_many(np.arange(0.0, traj.duration, TRAJECTORY_SAMPLE_S)).position
        path = np.vstack([path, traj.waypoints[-1]])
        if ctx.geofence is not None:
            why = ctx.geofence.first_violation(path)
            if why is not None:
                raise MissionFailed(f"fly: the trajectory leaves the geofence: {why}")
        log.info("fly: %d waypoints, %.1f s, max %.2f m/s", len(flight.waypoints), traj.duration, traj.max_speed)
        ctx.publish("trajectory", {"points_ned_m": path, "waypoints_ned_m": traj.waypoints, **traj.summary()})
        return flight

    async def _follow(self, flight: FlightPlan) -> tuple[Waypoint, ...]:
        """Fly ``flight`` to its end (returns ``()``), or until the estimate was lost and came back
        (returns what is left to fly: the waypoint being held with the rest of its hold, the
        waypoints the reference had not reached, and at least the last one, to arrive there)."""
        ctx, step = self.ctx, self.step
        controller = make_controller(ctx.control)
        timeline = Timeline(flight.trajectory, {i: (flight.time_of(i), w.hold_s)
                                                for i, w in enumerate(flight.waypoints) if w.hold_s > 0})
        passes = [(np.asarray(w.position, dtype=float), w) for w in flight.waypoints if w.pass_tolerance_m]
        goal = np.asarray(flight.trajectory.waypoints[-1], dtype=float)
        mode = output_mode(ctx.control.output, ctx.state.firmware)
        log.info("fly: %s setpoints (control.output %s, %s)", mode, ctx.control.output,
                 ctx.state.firmware.label if ctx.state.firmware else "firmware unknown")
        degraded = False
        healthy_since: float | None = None  # while degraded: when the estimate last became healthy
        period = 1.0 / ctx.control.rate_hz
        previous = next_tick = clock.now()
        while True:
            ctx.check_takeover()
            now = clock.now()
            if now > self._deadline:
                raise MissionFailed(f"fly: timed out after {self.timeout_s:.0f} s")
            dt, previous = max(now - previous, 1e-3), now
            status = ctx.estimate_status()
            if status.state == State.LOST:
                started = clock.now()
                await ctx.ride_out_estimate_loss(status, float(timeline.reference().yaw_rad))
                self._deadline += clock.now() - started
                return self._left_to_fly(flight, timeline)
            if status.state == State.DEGRADED:
                healthy_since = None
                if not degraded:
                    degraded = True
                    ctx.record_failsafe("estimate_degraded", f"{status.reason}: slowing to "
                                        f"{ctx.failsafe.degraded_speed_factor:g} of the speed")
            elif degraded:
                healthy_since = now if healthy_since is None else healthy_since
                degraded = now - healthy_since < DEGRADED_RECOVERY_S
            timeline.advance(dt, ctx.failsafe.degraded_speed_factor if degraded else 1.0)
            reference = timeline.reference()
            yaw = float(reference.yaw_rad)
            measured = ctx.measured()  # None only for a pipeline without velocity and no autopilot velocity
            if measured is not None:
                self._check(measured, reference, passes)  # before sending anything from this estimate
                self._send(controller.step(dt, reference, measured), yaw, mode)
                self.progress = timeline.tau / flight.trajectory.duration
                error_to_goal = float(np.linalg.norm(np.asarray(measured.position_ned) - goal))
                if timeline.finished and error_to_goal <= step.arrival_tolerance_m:
                    ctx.setpoints.command(Setpoint(position_ned=goal, yaw_rad=yaw))
                    return ()
            next_tick = max(next_tick + period, clock.now())  # after a stall: no burst to catch up
            await ctx.control_tick(next_tick)

    @staticmethod
    def _left_to_fly(flight: FlightPlan, timeline: Timeline) -> tuple[Waypoint, ...]:
        waypoints = flight.waypoints
        held = timeline.held
        left = [w for i, w in enumerate(waypoints) if flight.time_of(i) > timeline.tau and i != held]
        if held is not None:
            left.insert(0, dataclasses.replace(waypoints[held], hold_s=timeline.hold_left))
        if not left:  # the reference was at the end: still arrive there
            left = [dataclasses.replace(waypoints[-1], hold_s=0.0)]
        return tuple(left)

    def _send(self, output: ControlOutput, yaw_rad: float, mode: str) -> None:
        ctx = self.ctx
        g = ctx.control.autopilot_gains
        if mode == "position_only":
            target = position_only_target(output, pos_gain_xy=g.pos_xy_p, vel_gain_xy=g.vel_xy_p, pos_gain_z=g.pos_z_p)
            ctx.setpoints.command(Setpoint(position_ned=np.array(target), yaw_rad=yaw_rad))
        elif mode == "pos_vel":
            ctx.setpoints.command(Setpoint(**output.position_velocity_fields(g.vel_xy_p), yaw_rad=yaw_rad))
        else:
            ctx.setpoints.command(Setpoint(**output.setpoint_fields(), yaw_rad=yaw_rad))

    def _check(self, measured: MeasuredState, reference: Reference,
               passes: list[tuple[np.ndarray, Waypoint]]) -> None:
        """Tracking error, geofence and window / door passes; a breach raises :class:`MissionFailed`
        after commanding a hold. Through an opening the error that counts is the one across the
        path (lagging along it does not bring the vehicle nearer the frame)."""
        ctx = self.ctx
        p = np.asarray(measured.position_ned)
        r = np.asarray(reference.position)
        error = p - r
        self.tracking_error_m = float(np.linalg.norm(error))
        if ctx.geofence is not None:
            why = ctx.geofence.violation(p)
            if why is not None:
                self._stop("geofence", f"geofence breach: {why}")
        v = np.asarray(reference.velocity)
        speed = float(np.linalg.norm(v))
        across = error - (error @ v) * v / speed**2 if speed > MOVING_MPS else error
        for point, waypoint in passes:
            name = waypoint.label
            self.passes[name] = min(self.passes.get(name, math.inf), float(np.linalg.norm(p - point)))
            tolerance = waypoint.pass_tolerance_m or 0.0
            off = float(np.linalg.norm(across))
            if float(np.linalg.norm(r - point)) < PASS_ZONE_M and off > tolerance:
                self._stop("pass_tolerance", f"pass {name}: {off:.2f} m off the trajectory "
                           f"(tolerance {tolerance:g} m)")

    def _stop(self, kind: str, reason: str) -> None:
        self.ctx.record_failsafe(kind, f"{reason}: stopping and holding")
        self.ctx.hold_on_autopilot(self.ctx.yaw())
        raise MissionFailed(reason)

    async def _hold_at(self, position: np.ndarray, seconds: float) -> None:
        self.ctx.setpoints.command(Setpoint(position_ned=position, yaw_rad=self.ctx.yaw()))
        end = clock.now() + seconds
        await self.ctx.wait_for(lambda: clock.now() >= end, seconds + 1.0, "the end of the hold")
