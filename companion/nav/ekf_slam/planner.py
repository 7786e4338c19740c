"""The recovery path planner of the seed (Lee and Tahk 2010, Sec. 4, Figs. 3-8) as pure logic.

A small state machine fed, at any rate, with the time, the vehicle's *estimated* pose and the
estimated positions of the landmarks in view and of the current sub-map; it answers with what to
fly now (:class:`PlannerOutput`): a ``carrot_ne`` point to steer to (a position setpoint for the
autopilot, or the point a simulated vehicle steers at) and the plan around it. It knows no
simulator and no autopilot: the daemon's recovery behaviour and ``sitl/slam_experiment.py`` use
it alike. Frames: LOCAL_NED north / east (m); headings clockwise from north (rad).

STEPs (seed Sec. 4.1):

1. start point = the last good fix (the pose at the first call), later the landmark of STEP 6;
2. heading to the base from the start point, ``atan2(e_base - e_0, n_base - n_0)`` (seed eq. 39
   with its ``tan^-1(dy / dx)`` made four-quadrant);
3. reference landmark = the landmark in view nearest the base (``reference`` variant);
4. a circle centred on it of radius ``circle_radius_factor * altitude * tan(half FOV)``; the
   ``larger_loop`` variant (seed Figs. 7-8) flies a circle of ``larger_loop_factor`` footprint
   radii whose centre lies on the way to the base, through the start point, no landmark needed;
5. ``loops`` full loops, counted once the vehicle is within ``on_circle_tolerance`` of the radius;
6. next start point = the mapped landmark nearest the base; on arriving above it the output says
   ``new_submap`` (keep that landmark, drop the rest) and the steps repeat from 2. With
   ``submap_keep: in_view`` (the default) the landmarks in view there are kept too: the seed
   drops them, but they are few (cost unchanged) and they carry the heading the vehicle had
   (sitl/slam_experiment.py compares both).

The base within ``final_leg_m``: fly straight to it; within ``land_radius_m``: ``land``. No
landmark in view when STEP 3 needs one (or none mapped at STEP 6): an expanding-square search
about the point where it started (legs ``search_leg_m``, ``2 search_leg_m``, ... turning
clockwise), then ``hold`` or ``land`` (``on_search_timeout``) after ``search_time_s``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

import numpy as np

from companion.nav.ekf_slam.config import RecoveryPlannerConfig
from companion.nav.ekf_slam.model import wrap

Kind = Literal["goto", "circle", "search", "land", "hold"]


@dataclass(frozen=True)
class PlannerOutput:
    """What to fly now. ``carrot_ne``: the point to steer to (m, NED); ``target_ne``: the goto
    point, the circle's centre, the search corner, or where to land / hold; ``radius_m`` for a
    circle; ``new_submap``: start a new sub-map now keeping landmark ``keep_landmark`` (None: keep
    none) and the landmarks ``also_keep`` (those in view, config ``submap_keep: in_view``); ``reference``: the reference landmark's id; ``loops_done``: full loops on this circle."""

    kind: Kind
    target_ne: tuple[float, float]
    carrot_ne: tuple[float, float]
    reason: str
    radius_m: float | None = None
    new_submap: bool = False
    keep_landmark: int | None = None
    reference: int | None = None
    loops_done: float = 0.0
    also_keep: tuple[int, ...] = ()


def _xy(p: object) -> np.ndarray:
    return np.asarray(p, dtype=float)[:2]


def _t(p: np.ndarray) -> tuple[float, float]:
    return float(p[0]), float(p[1])


class RecoveryPlanner:
    """The seed's recovery path (module docstring). ``base_ne``: the base (m, NED)."""

    def __init__(self, config: RecoveryPlannerConfig, base_ne: tuple[float, float]) -> None:
        self.config = config
        self.base = _xy(base_ne)
        self.state = "start"
        self.start_ne: np.ndarray | None = None
        self.heading_to_base: float | None = None
        self.reference: int | None = None
        self.centre: np.ndarray | None = None
        self.radius = config.circle_radius_m
        self.direction = 1.0 if config.clockwise else -1.0  # +: bearing from the centre increases
        self._counting = False
        self._last_angle = 0.0
        self._swept = 0.0
        self.next_start: int | None = None
        self.next_start_ne: np.ndarray | None = None
        self._search_t0 = 0.0
        self._search_origin = np.zeros(2)
        self._search_corners: list[np.ndarray] = []
        self._search_index = 0
        self._terminal_ne = np.zeros(2)
        self.submaps = 0
        self.circles = 0

    # ------------------------------------------------------------------------------------------

    def target(self, t_s: float, pose: object, in_view: Mapping[int, object],
               mapped: Mapping[int, object]) -> PlannerOutput:
        """The output for now. ``pose``: estimated ``(n, e, ...)``; ``in_view``: estimated
        positions ``(n, e, ...)`` of the landmarks the sensor sees now, by id; ``mapped``: every
        landmark of the current sub-map, by id."""
        pos = _xy(pose)
        cfg = self.config
        if self.state in ("land", "hold"):
            return self._terminal(self.state, "")
        if self.state == "start":  # STEP 1 and 2
            self._set_start(pos)
            self.state = "select"
        if np.linalg.norm(self.base - pos) <= cfg.final_leg_m:
            self.state = "final"
        if self.state == "final":
            if np.linalg.norm(self.base - pos) <= cfg.land_radius_m:
                self._terminal_ne = pos.copy()
                self.state = "land"
                return self._terminal("land", "at the base (by the estimate)")
            return PlannerOutput("goto", _t(self.base), _t(self.base), "final leg: the base is within reach")
        if self.state == "search":
            found = self._search_over(t_s, pos, in_view, mapped)
            if found is not None:
                return found
        if self.state == "select":
            out = self._select(t_s, pos, in_view)
            if out is not None:
                return out
        if self.state == "circle":
            return self._circle(t_s, pos, in_view, mapped)
        if self.state == "goto_start":
            return self._goto_start(t_s, pos, in_view, mapped)
        raise AssertionError(self.state)

    # ------------------------------------------------------------------------------------------

    def _set_start(self, start: np.ndarray) -> None:
        self.start_ne = start.copy()
        d = self.base - start
        self.heading_to_base = math.atan2(d[1], d[0])  # seed eq. 39

    def _select(self, t_s: float, pos: np.ndarray, in_view: Mapping[int, object]) -> PlannerOutput | None:
        """STEPs 3-4: choose the circle; None if the state went on to a search."""
        assert self.start_ne is not None and self.heading_to_base is not None
        if self.config.variant == "larger_loop":
            self.reference = None
            self.centre = self.start_ne + self.radius * np.array(
                [math.cos(self.heading_to_base), math.sin(self.heading_to_base)])
            why = "larger loop from the start point towards the base"
        else:
            if not in_view:
                self._start_search(t_s, pos)
                return self._search_output("no landmark in view for a reference (STEP 3)")
            self.reference = min(in_view, key=lambda i: float(np.linalg.norm(_xy(in_view[i]) - self.base)))
            self.centre = _xy(in_view[self.reference]).copy()
            why = f"circle around reference landmark {self.reference}, the one in view nearest the base"
        self.state = "circle"
        self.circles += 1
        self._counting = False
        self._swept = 0.0
        self._reason = why
        return None

    def _circle(self, t_s: float, pos: np.ndarray, in_view: Mapping[int, object],
                mapped: Mapping[int, object]) -> PlannerOutput:
        cfg = self.config
        if self.reference is not None and self.reference in mapped:
            self.centre = _xy(mapped[self.reference]).copy()  # follow the reference's estimate
        assert self.centre is not None
        rel = pos - self.centre
        r = float(np.hypot(rel[0], rel[1]))
        angle = math.atan2(rel[1], rel[0])
        if not self._counting and abs(r - self.radius) <= cfg.on_circle_tolerance * self.radius:
            self._counting = True
            self._last_angle = angle
        if self._counting:
            self._swept += self.direction * wrap(angle - self._last_angle)
            self._last_angle = angle
        loops = max(0.0, self._swept) / (2.0 * math.pi)
        if loops >= cfg.loops:  # STEP 6
            return self._choose_next_start(t_s, pos, in_view, mapped)
        ahead = angle + self.direction * cfg.lookahead_m / self.radius
        carrot = self.centre + self.radius * np.array([math.cos(ahead), math.sin(ahead)])
        return PlannerOutput("circle", _t(self.centre), _t(carrot), self._reason, radius_m=self.radius,
                             reference=self.reference, loops_done=loops)

    def _choose_next_start(self, t_s: float, pos: np.ndarray, in_view: Mapping[int, object],
                           mapped: Mapping[int, object]) -> PlannerOutput:
        assert self.start_ne is not None
        if not mapped:
            self._start_search(t_s, pos)
            return self._search_output("no landmark mapped for the next start point (STEP 6)")
        best = min(mapped, key=lambda i: float(np.linalg.norm(_xy(mapped[i]) - self.base)))
        best_ne = _xy(mapped[best])
        if np.linalg.norm(best_ne - self.base) >= np.linalg.norm(self.start_ne - self.base) - 1.0:
            # no mapped landmark nearer the base than this start point: a blind leg of one
            # footprint towards the base, then select again with whatever is in view there
            step = self.base - self.start_ne
            self.next_start = None
            self.next_start_ne = self.start_ne + step / max(np.linalg.norm(step), 1e-9) * min(
                self.config.footprint_radius_m, float(np.linalg.norm(step)))
        else:
            self.next_start = best
            self.next_start_ne = best_ne.copy()
        self.state = "goto_start"
        return self._goto_start(t_s, pos, in_view, mapped)

    def _goto_start(self, t_s: float, pos: np.ndarray, in_view: Mapping[int, object],
                    mapped: Mapping[int, object]) -> PlannerOutput:
        if self.next_start is not None and self.next_start in mapped:
            self.next_start_ne = _xy(mapped[self.next_start]).copy()
        assert self.next_start_ne is not None
        d = float(np.linalg.norm(self.next_start_ne - pos))
        self._goto_best = min(getattr(self, "_goto_best", math.inf), d)
        # arrived: within arrive_m, or passed it within 3 arrive_m (a vehicle whose turns are wider
        # than arrive_m could orbit the point for ever)
        passed = self._goto_best <= 3.0 * self.config.arrive_m and d > self._goto_best + 0.5
        if d > self.config.arrive_m and not passed:
            why = (f"STEP 6: to landmark {self.next_start}, the mapped one nearest the base" if self.next_start
                   is not None else "STEP 6: no mapped landmark nearer the base, a leg towards it")
            return PlannerOutput("goto", _t(self.next_start_ne), _t(self.next_start_ne), why)
        keep = self.next_start
        self._goto_best = math.inf
        self._set_start(self.next_start_ne)
        self.submaps += 1
        self.state = "select"
        out = self._select(t_s, pos, {k: v for k, v in in_view.items() if k in mapped or k == keep})
        if out is None:
            out = self._circle(t_s, pos, in_view, mapped)
        also = tuple(sorted(i for i in in_view if i != keep)) if self.config.submap_keep == "in_view" else ()
        return PlannerOutput(out.kind, out.target_ne, out.carrot_ne, "new sub-map; " + out.reason, out.radius_m,
                             new_submap=True, keep_landmark=keep, reference=out.reference, also_keep=also)

    # --- search ------------------------------------------------------------------------------

    def _start_search(self, t_s: float, pos: np.ndarray) -> None:
        self.state = "search"
        self._search_t0 = t_s
        self._search_origin = pos.copy()
        leg = self.config.search_leg_m
        corners, p, heading = [], pos.copy(), self.heading_to_base or 0.0
        for i in range(1, 41):  # expanding square: legs 1, 1, 2, 2, 3, 3, ... times leg, turning right
            length = leg * ((i + 1) // 2)
            p = p + length * np.array([math.cos(heading), math.sin(heading)])
            corners.append(p.copy())
            heading += math.pi / 2.0
        self._search_corners = corners
        self._search_index = 0

    def _search_output(self, why: str) -> PlannerOutput:
        corner = self._search_corners[min(self._search_index, len(self._search_corners) - 1)]
        return PlannerOutput("search", _t(corner), _t(corner), why)

    def _search_over(self, t_s: float, pos: np.ndarray, in_view: Mapping[int, object],
                     mapped: Mapping[int, object]) -> PlannerOutput | None:
        """The search's output, or None once a landmark is in view (the state is then select)."""
        if in_view:
            self.state = "select"
            if self.config.variant == "reference":
                self._set_start(pos)  # STEP 1 again where the search found a landmark
            return None
        if t_s - self._search_t0 > self.config.search_time_s:
            self._terminal_ne = pos.copy()
            self.state = self.config.on_search_timeout
            return self._terminal(self.state, f"no landmark found in {self.config.search_time_s:.0f} s of search")
        corner = self._search_corners[min(self._search_index, len(self._search_corners) - 1)]
        if np.linalg.norm(corner - pos) <= self.config.arrive_m:
            self._search_index += 1
        return self._search_output("searching for a landmark: expanding square")

    def _terminal(self, kind: Kind, why: str) -> PlannerOutput:
        self._why_terminal = why or getattr(self, "_why_terminal", "")
        p = _t(self._terminal_ne)
        return PlannerOutput(kind, p, p, self._why_terminal)
