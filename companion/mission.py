"""Missions: YAML step lists (config/missions/*.yaml) and the runner that flies them.

A mission file is ``name`` plus ``steps``; each step is a mapping with exactly one key:

- ``wait_ready: {timeout_s}``: the origin is confirmed and the autopilot reports a position;
- ``mode: NAME``: switch flight mode (GUIDED on ArduPilot, OFFBOARD on PX4);
- ``arm: {}``: arm, only if the config's ``mission.allow_arm`` is true;
- ``takeoff: {altitude_m, timeout_s}``: take off and wait until within 0.15 m of the altitude;
- ``hold: {seconds}``: stream a position setpoint where the vehicle is, at the takeoff height;
- ``goto: {position, speed_mps, tolerance_m, hold_s, timeout_s}``: fly a straight line to a
  LOCAL_NED position at a constant speed (a moving position + velocity setpoint), wait until
  the autopilot is within the tolerance, then hold there (smooth trajectories: issue 4);
- ``land: {timeout_s}``: switch to LAND and wait for the autopilot to disarm.

The runner stops commanding at once if the pilot changes mode (the mission is then
``aborted``); a step that fails or times out ends the mission as ``failed`` with the reason.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from companion import clock
from companion.mavlink.autopilot import AutopilotState
from companion.mavlink.commands import CommandFailed, Commander
from companion.mavlink.origin import OriginSetter
from companion.mavlink.setpoints import Setpoint, SetpointStream
from companion.schema import load_file, meta

log = logging.getLogger("companion.mission")


@dataclass
class WaitReadyStep:
    timeout_s: float = field(default=60.0, metadata=meta("Give up after this long.", (0.1, 3600)))


@dataclass
class ArmStep:
    timeout_s: float = field(default=10.0, metadata=meta(
        "Keep asking (pre-arm checks can be transient) and wait for the armed HEARTBEAT this long.", (0.1, 60)))


@dataclass
class TakeoffStep:
    altitude_m: float = field(metadata=meta("Height above home.", (0.3, 100)))
    timeout_s: float = field(default=20.0, metadata=meta("Give up after this long.", (1, 600)))


@dataclass
class HoldStep:
    seconds: float = field(metadata=meta("How long to hold.", (0, 3600)))


@dataclass
class GotoStep:
    position: tuple[float, float, float] = field(metadata=meta("Target, LOCAL_NED metres (z negative = up)."))
    speed_mps: float = field(default=0.5, metadata=meta("Speed along the straight line.", (0.05, 5)))
    tolerance_m: float = field(default=0.15, metadata=meta("Arrived when the autopilot position is this close.", (0.02, 5)))
    hold_s: float = field(default=0.0, metadata=meta("Hold at the target after arriving.", (0, 3600)))
    timeout_s: float = field(default=120.0, metadata=meta("Give up after this long.", (1, 3600)))


@dataclass
class LandStep:
    timeout_s: float = field(default=60.0, metadata=meta("Wait for disarm this long.", (1, 600)))


@dataclass
class MissionStep:
    wait_ready: WaitReadyStep | None = None
    mode: str | None = None
    arm: ArmStep | None = None
    takeoff: TakeoffStep | None = None
    hold: HoldStep | None = None
    goto: GotoStep | None = None
    land: LandStep | None = None

    def validate(self) -> tuple[str, str] | None:
        present = [name for name, value in vars(self).items() if value is not None]
        if len(present) != 1:
            return ("", f"a step has exactly one of {', '.join(vars(self))}; got {present or 'none'}")
        return None

    @property
    def kind(self) -> str:
        return next(name for name, value in vars(self).items() if value is not None)


@dataclass
class Mission:
    name: str = field(metadata=meta("Mission name."))
    steps: list[MissionStep] = field(metadata=meta("Steps, flown in order."))


def load_mission(path: str | Path) -> Mission:
    """Load a mission file; errors name file, key path and line."""
    return load_file(path, Mission)


class MissionFailed(Exception):
    pass


class MissionRunner:
    """Flies one mission once; publishes its progress through ``publish``."""

    def __init__(self, mission: Mission, allow_arm: bool, state: AutopilotState, commander: Commander,
                 setpoints: SetpointStream, origin: OriginSetter, publish: Callable[[dict], None]) -> None:
        self.mission = mission
        self.allow_arm = allow_arm
        self.state = state
        self.commander = commander
        self.setpoints = setpoints
        self.origin = origin
        self.publish = publish
        self.status = "pending"
        self.step_index = -1
        self.reason = ""
        self._takeoff_altitude = 1.0
        self._takeover = asyncio.Event()
        setpoints.on_takeover = self._on_takeover

    def snapshot(self) -> dict:
        step = self.mission.steps[self.step_index].kind if 0 <= self.step_index < len(self.mission.steps) else None
        return {"name": self.mission.name, "state": self.status, "step": self.step_index,
                "step_kind": step, "steps": len(self.mission.steps), "reason": self.reason}

    async def run(self) -> None:
        """Fly the mission (once; a restart after completion does nothing)."""
        if self.status in ("completed", "failed", "aborted"):
            await asyncio.Event().wait()
        self._set("running")
        try:
            for index, step in enumerate(self.mission.steps):
                self.step_index = index
                self._set("running")
                await self._run_step(step)
        except MissionFailed as exc:
            self.setpoints.stop()
            self._set("aborted" if self._takeover.is_set() else "failed", str(exc))
        else:
            self._set("completed")
        await asyncio.Event().wait()

    def _set(self, status: str, reason: str = "") -> None:
        self.status, self.reason = status, reason
        if status in ("failed", "aborted"):
            log.error("mission %s %s: %s", self.mission.name, status, reason)
        else:
            log.info("mission %s: %s step %d", self.mission.name, status, self.step_index)
        self.publish(self.snapshot())

    async def _run_step(self, step: MissionStep) -> None:
        if self._takeover.is_set():
            raise MissionFailed("pilot took over")
        kind = step.kind
        try:
            await getattr(self, f"_{kind}")(getattr(step, kind))
        except CommandFailed as exc:
            raise MissionFailed(f"{kind}: {exc}") from exc

    async def _wait_for(self, condition: Callable[[], bool], timeout_s: float, what: str) -> None:
        deadline = clock.now() + timeout_s
        while not condition():
            if self._takeover.is_set():
                raise MissionFailed("pilot took over")
            if clock.now() > deadline:
                raise MissionFailed(f"timed out after {timeout_s:g} s waiting for {what}")
            await asyncio.sleep(0.05)

    def _position_fresh(self) -> bool:
        t = self.state.local_position_time
        return t is not None and clock.now() - t < 1.0

    async def _wait_ready(self, step: WaitReadyStep) -> None:
        await self._wait_for(lambda: self.origin.confirmed and self._position_fresh(), step.timeout_s,
                             "a confirmed origin and an autopilot position")

    async def _mode(self, name: str) -> None:
        self.setpoints.expect_mode(name)
        await self.commander.set_mode(name)
        await self._wait_for(lambda: self.state.mode == name, 3.0, f"mode {name}")

    async def _arm(self, step: ArmStep) -> None:
        if not self.allow_arm:
            raise MissionFailed("arming is not allowed by the config (mission.allow_arm: false)")
        deadline = clock.now() + step.timeout_s
        while True:  # a refusal (pre-arm check) is retried every second until the timeout
            try:
                await self.commander.arm()
                break
            except CommandFailed:
                if clock.now() + 1.0 > deadline:
                    raise
                log.info("arming refused (see the autopilot's PreArm message); retrying")
                await asyncio.sleep(1.0)
        await self._wait_for(lambda: self.state.armed, max(1.0, deadline - clock.now()), "the armed state")

    async def _takeoff(self, step: TakeoffStep) -> None:
        self._takeoff_altitude = step.altitude_m
        await self.commander.takeoff(step.altitude_m)

        def reached() -> bool:
            p = self.state.local_position_ned
            return p is not None and self._position_fresh() and abs(-p[2] - step.altitude_m) < 0.15
        await self._wait_for(reached, step.timeout_s, f"{step.altitude_m:g} m altitude")

    async def _hold(self, step: HoldStep) -> None:
        p = self.state.local_position_ned
        if p is None:
            raise MissionFailed("hold: no autopilot position")
        target = np.array([p[0], p[1], -self._takeoff_altitude])
        self.setpoints.command(Setpoint(position_ned=target))
        end = clock.now() + step.seconds
        await self._wait_for(lambda: clock.now() >= end, step.seconds + 1.0, "the end of the hold")

    async def _goto(self, step: GotoStep) -> None:
        current = self.setpoints.current
        if current is not None and current.position_ned is not None:
            start = np.asarray(current.position_ned, dtype=float)
        elif self.state.local_position_ned is not None:
            start = np.asarray(self.state.local_position_ned, dtype=float)
        else:
            raise MissionFailed("goto: no autopilot position")
        goal = np.asarray(step.position, dtype=float)
        distance = float(np.linalg.norm(goal - start))
        direction = (goal - start) / distance if distance > 0 else np.zeros(3)
        began = clock.now()
        deadline = began + step.timeout_s
        while True:  # a target moving along the line at speed_mps, with velocity feed-forward
            if self._takeover.is_set():
                raise MissionFailed("pilot took over")
            if clock.now() > deadline:
                raise MissionFailed(f"goto: timed out after {step.timeout_s:g} s")
            travelled = step.speed_mps * (clock.now() - began)
            if travelled >= distance:
                break
            self.setpoints.command(Setpoint(position_ned=start + direction * travelled,
                                            velocity_ned=direction * step.speed_mps))
            await asyncio.sleep(0.05)
        self.setpoints.command(Setpoint(position_ned=goal))

        def arrived() -> bool:
            p = self.state.local_position_ned
            return p is not None and self._position_fresh() and float(np.linalg.norm(p - goal)) <= step.tolerance_m
        await self._wait_for(arrived, max(1.0, deadline - clock.now()), f"arrival within {step.tolerance_m:g} m of {list(goal)}")
        end = clock.now() + step.hold_s
        await self._wait_for(lambda: clock.now() >= end, step.hold_s + 1.0, "the end of the hold")

    async def _land(self, step: LandStep) -> None:
        self.setpoints.stop()
        self.setpoints.expect_mode("LAND")
        await self.commander.land()
        await self._wait_for(lambda: not self.state.armed, step.timeout_s, "touchdown and disarm")

    def _on_takeover(self, mode: str) -> None:
        self._takeover.set()
