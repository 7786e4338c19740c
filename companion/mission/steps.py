"""Mission files (config/missions/*.yaml): ``name`` plus ``steps``, each step a mapping with one key.

- ``wait_ready: {timeout_s}``: the origin is confirmed and home settled, the autopilot reports a
  position, the companion's estimate is healthy (fresh, every navigation component ok) and, if the
  autopilot fuses it, its position is within 0.2 m of it (its EKF has converged onto it);
- ``mode: NAME``: switch flight mode (GUIDED on ArduPilot; OFFBOARD on PX4, after streaming a
  hold setpoint for a second first, as PX4 requires);
- ``arm: {timeout_s}``: arm, only if the config's ``mission.allow_arm`` is true;
- ``takeoff: {altitude_m, timeout_s}``: take off and wait until within 0.1 m of the altitude, settled
  (a fixed wing: 5 m, climbing slower than 1 m/s). In the autopilot's TAKEOFF mode (ArduPlane: switch
  to it, then arm) the autopilot climbs to its TKOFF_ALT by itself, which must be ``altitude_m``;
- ``hold: {seconds}``: hold where the vehicle is (a position setpoint);
- ``goto: {position, seconds}``: one position target, flown by the autopilot's own guidance for
  ``seconds``: a copter flies there and holds; a fixed wing flies there and circles it at its
  loiter radius (WP_LOITER_RAD), as ArduPlane flies a guided waypoint. A fixed wing's flight plan is
  a list of these (``fly`` is a multicopter's trajectory controller). The vehicle must be flying: after
  a ``takeoff``, or already armed in the air (a fixed wing started in flight). The target must lie
  inside the companion's geofence;
- ``fly: {waypoints, speed_mps, ...}``: plan a smooth trajectory from where the vehicle is
  through the waypoints (minimum-snap by default, within the speed / acceleration / jerk
  limits and a corridor around the straight legs) and fly it with the outer-loop controller
  of ``control`` (RPT by default) at ``control.rate_hz``. A waypoint may stop, hold, or be a
  window / door pass with a tolerance (see :class:`Waypoint`);
- ``payload_drop: {hold_s}``: hold, release the payload (``mission.payload``), keep holding;
- ``land: {timeout_s}``: switch to LAND and wait for the autopilot to disarm (a fixed wing: RTL, its
  pilot lands it);
- ``return_to_base: {timeout_s, land_timeout_s}``: hand the flight to the pipeline that can
  fly the vehicle itself (a :class:`companion.pipeline.GuidanceSource`, e.g. the EKF-SLAM return
  to base): ask it to start if it has not taken over already, fly its guidance (position
  targets with velocity feed-forward) until it says land, then hold its landing point until settled
  over it (0.3 m, 0.2 m/s by the companion's estimate; at most 30 s) and land. The pipeline ending its
  guidance (GNSS back) ends the step and the mission goes on. While airborne, a pipeline taking
  over on its own (GNSS lost) jumps the mission to its next ``return_to_base`` step if
  ``failsafe.gnss_loss`` is ``return_to_base`` (without one, the guidance is flown to its
  landing and the mission ends failed, naming the takeover);
- ``pose_source: {source}``: command the pose source (a pipeline of ``pipelines.sources``): it
  feeds the autopilot while it has fresh estimates; ``source: null`` returns to the priority
  order. A switch increments ``reset_counter`` once, as any switch does.

Positions are LOCAL_NED metres at the EKF origin (x north, y east, z down: z = -1 is 1 m up).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from companion.schema import load_file, meta

Vec3 = tuple[float, float, float]
REPEATED_M = 0.02  # consecutive waypoints closer than this are one point (a trajectory cannot join them)


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
    position: Vec3 = field(metadata=meta("The target, LOCAL_NED metres (z negative = up)."))
    seconds: float = field(metadata=meta("Fly towards it (and hold or circle there) this long.", (0, 3600)))


@dataclass
class Waypoint:
    position: Vec3 = field(metadata=meta("LOCAL_NED metres (z negative = up)."))
    speed_mps: float | None = field(default=None, metadata=meta(
        "Speed limit on the leg that ends here (e.g. slower through a door); null = the step's.", (0.05, 5)))
    stop: bool = field(default=False, metadata=meta("Come to rest here (e.g. lined up in front of a window)."))
    hold_s: float = field(default=0.0, metadata=meta("Come to rest here and hold this long.", (0, 3600)))
    pass_tolerance_m: float | None = field(default=None, metadata=meta(
        "A window or door: within 1 m of it, the estimate must stay this close to the reference, else the "
        "flight stops and holds (mission failed).", (0.02, 2)))
    name: str | None = field(default=None, metadata=meta("Shown in logs and telemetry."))

    @property
    def label(self) -> str:
        return self.name or f"[{', '.join(f'{c:g}' for c in self.position)}]"


@dataclass
class FlyStep:
    waypoints: list[Waypoint] = field(metadata=meta("Where to fly, in order; the trajectory starts where the vehicle is."))
    speed_mps: float = field(default=0.5, metadata=meta("Speed limit of every leg without its own.", (0.05, 5)))
    accel_mps2: float = field(default=0.5, metadata=meta("Acceleration limit of the trajectory.", (0.05, 5)))
    jerk_mps3: float | None = field(default=1.0, metadata=meta("Jerk limit of the trajectory; null = none.", (0.05, 50)))
    kind: Literal["minimum_snap", "minimum_jerk"] = field(default="minimum_snap", metadata=meta("Spline type."))
    corridor_m: float | None = field(default=0.15, metadata=meta(
        "Largest distance of the trajectory from the straight legs (what was checked against walls and doors); "
        "null = none.", (0.02, 5)))
    yaw: Literal["hold", "face_next", "fixed"] = field(default="hold", metadata=meta(
        "hold: keep the heading at the start; face_next: turn towards the next waypoint; fixed: turn to yaw_deg."))
    yaw_deg: float | None = field(default=None, metadata=meta("Heading for yaw: fixed, degrees from north.", (-360, 360)))
    arrival_tolerance_m: float = field(default=0.15, metadata=meta(
        "Done when the estimate is this close to the last waypoint at the end of the trajectory.", (0.02, 5)))
    timeout_s: float | None = field(default=None, metadata=meta(
        "Give up after this long; null = twice the planned duration plus the holds plus 30 s.", (1, 7200)))

    def validate(self) -> tuple[str, str] | None:
        if not self.waypoints:
            return "waypoints", "needs at least one waypoint"
        if self.yaw == "fixed" and self.yaw_deg is None:
            return "yaw_deg", "yaw: fixed needs yaw_deg"
        for i in range(1, len(self.waypoints)):
            a, b = self.waypoints[i - 1].position, self.waypoints[i].position
            if sum((x - y) ** 2 for x, y in zip(a, b)) < REPEATED_M ** 2:
                return f"waypoints[{i}].position", f"repeats waypoints[{i - 1}] (hold there with hold_s instead)"
        return None


@dataclass
class PayloadDropStep:
    hold_s: float = field(default=2.0, metadata=meta("Hold this long after the release command.", (0, 600)))


@dataclass
class LandStep:
    timeout_s: float = field(default=60.0, metadata=meta("Wait for disarm this long.", (1, 600)))


@dataclass
class ReturnToBaseStep:
    timeout_s: float = field(default=3600.0, metadata=meta("Give up (hold) after this long.", (1, 36000)))
    land_timeout_s: float = field(default=300.0, metadata=meta(
        "Wait for touchdown and disarm after the guidance says land this long (a descent from 100 m takes minutes).",
        (1, 3600)))


@dataclass
class PoseSourceStep:
    source: str | None = field(metadata=meta("A pose pipeline of pipelines.sources; null = the priority order again."))


@dataclass
class MissionStep:
    wait_ready: WaitReadyStep | None = None
    mode: str | None = None
    arm: ArmStep | None = None
    takeoff: TakeoffStep | None = None
    hold: HoldStep | None = None
    goto: GotoStep | None = None
    fly: FlyStep | None = None
    payload_drop: PayloadDropStep | None = None
    land: LandStep | None = None
    pose_source: PoseSourceStep | None = None
    return_to_base: ReturnToBaseStep | None = None

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
