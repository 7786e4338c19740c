"""Estimate-source selection: which pipeline's pose feeds the autopilot and the missions.

Like ArduPilot's EK3_SRC sets, the config lists the pose sources in priority order
(``pipelines.sources``). The active source alone is forwarded (VISION_POSITION_ESTIMATE /
VISION_SPEED_ESTIMATE, and what missions fly on); every source stays visible on telemetry.

Rules, evaluated every nav cycle at daemon time ``now`` (s):

- a source is *fresh* while its newest finite pose is at most ``timeout_s`` old; a pipeline
  that is lost or unhealthy stops producing poses, so it goes stale;
- a source is *good* while fresh, its poses are not marked ``degraded`` by its pipeline (e.g. a
  localizer coasting without fixes) and their horizontal position 1-sigma is at most
  ``max_sigma_m``;
- when the active source goes stale (or there is none), the first good source in priority
  order takes over, else the first fresh one; when it is degraded and a good one exists, the
  first good one takes over;
- a source earlier in the list than the active one takes back over once it has been good
  for ``return_s`` without a break (hysteresis: a flapping primary does not make the estimate
  jump back and forth);
- :meth:`SourceSelector.command` pins a source (while it is fresh) or unpins (a mission's
  ``pose_source`` step);
- every change of the active source calls ``on_switch(old, new, reason)``; when the autopilot
  was fed by another source before, the first forwarded estimate of the new one is marked
  ``reset`` (so the autopilot's ``reset_counter`` increments exactly once and its EKF jumps to
  the new source instead of treating the offset as drift).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from companion.messages import PoseEstimate


@dataclass
class SourceStatus:
    """What the selection knows of one source."""

    last: PoseEstimate | None = None  # newest finite pose
    last_t: float | None = None  # daemon time it was offered, s
    good_since: float | None = None  # daemon time since which it has been good without a break, s


def horizontal_sigma_m(estimate: PoseEstimate | None) -> float:
    """The larger of the north and east position 1-sigma of ``estimate``, m (inf for None)."""
    if estimate is None:
        return math.inf
    return math.sqrt(max(float(estimate.pose_covariance[0, 0]), float(estimate.pose_covariance[1, 1]), 0.0))


class SourceSelector:
    """Chooses the active pose source; see the module docstring."""

    def __init__(self, priority: Sequence[str], timeout_s: float, return_s: float, max_sigma_m: float = math.inf,
                 on_switch: Callable[[str | None, str | None, str], None] = lambda old, new, why: None) -> None:
        if not priority:
            raise ValueError("no pose source to select from")
        self.priority = list(priority)
        self.timeout_s = timeout_s
        self.return_s = return_s
        self.max_sigma_m = max_sigma_m
        self.on_switch = on_switch
        self.sources = {name: SourceStatus() for name in self.priority}
        self.active: str | None = None
        self.pinned: str | None = None
        self.switches = 0  # changes of the source feeding the autopilot
        self._fed_by: str | None = None  # the source of the last forwarded estimate
        self._reset_pending = False

    def offer(self, estimate: PoseEstimate, now: float) -> None:
        """A new pose from pipeline ``estimate.source`` (ignored if not a listed source or not finite)."""
        status = self.sources.get(estimate.source)
        if status is None or not estimate.is_finite():
            return
        if estimate.degraded or horizontal_sigma_m(estimate) > self.max_sigma_m:
            status.good_since = None
        elif status.good_since is None or status.last_t is None or now - status.last_t > self.timeout_s:
            status.good_since = now
        status.last, status.last_t = estimate, now

    def command(self, source: str | None) -> None:
        """Pin ``source`` (used while fresh; ValueError if not a listed source), or unpin with None."""
        if source is not None and source not in self.sources:
            raise ValueError(f"{source!r} is not a pose source ({', '.join(self.priority)})")
        self.pinned = source

    def good(self, name: str, now: float) -> bool:
        return self.fresh(name, now) and self.sources[name].good_since is not None

    def fresh(self, name: str, now: float) -> bool:
        t = self.sources[name].last_t
        return t is not None and now - t <= self.timeout_s

    def select(self, now: float, new: dict[str, PoseEstimate]) -> PoseEstimate | None:
        """Update the active source at ``now``; the estimate to forward this cycle: the active
        source's pose in ``new`` (this cycle's poses by source), ``reset`` after a switch; None
        if the active source made none this cycle. Only finite poses keep a source fresh, but a
        non-finite one of the active source is returned: the estimate output drops, counts and
        reports it."""
        choice, reason = self._choose(now)
        if choice != self.active:
            old, self.active = self.active, choice
            # a jump only if the autopilot was fed by another source (not at the first estimate, not
            # when the one source comes back after a gap)
            self._reset_pending = choice is not None and self._fed_by not in (None, choice)
            self.on_switch(old, choice, reason)
        estimate = new.get(self.active) if self.active is not None else None
        if estimate is None:
            return None  # (a non-finite one goes on: the estimate output drops, counts and reports it)
        if self._reset_pending:
            self._reset_pending = False
            self.switches += 1
            estimate = dataclasses.replace(estimate, reset=True)
        self._fed_by = self.active
        return estimate

    def _choose(self, now: float) -> tuple[str | None, str]:
        """(the source that should be active, why it changed if it did)."""
        if self.pinned is not None and self.fresh(self.pinned, now):
            return self.pinned, "commanded"
        fresh = [name for name in self.priority if self.fresh(name, now)]
        good = [name for name in fresh if self.good(name, now)]
        active = self.active
        if active is None or active not in fresh:
            if not fresh:
                return None, f"{active} lost, no other source" if active else "no source"
            return (good or fresh)[0], f"{active} lost" if active else "first estimate"
        if active not in good and good:
            return good[0], f"{active} degraded"
        for name in good:
            if self.priority.index(name) >= self.priority.index(active):
                break
            since = self.sources[name].good_since
            if since is not None and now - since >= self.return_s:
                return name, f"{name} back for {now - since:.1f} s"
        return active, ""

    @property
    def current(self) -> PoseEstimate | None:
        """The active source's newest pose (what missions fly on), or None."""
        return self.sources[self.active].last if self.active is not None else None

    def snapshot(self, now: float) -> dict[str, object]:
        """Telemetry: the active source, the priority, and each source's age (s) and newest pose."""
        return {"active": self.active, "pinned": self.pinned, "priority": self.priority, "switches": self.switches,
                "sources": {name: {"fresh": self.fresh(name, now), "good": self.good(name, now),
                                   "age_s": None if s.last_t is None else now - s.last_t,
                                   "position_ned_m": None if s.last is None else s.last.position_ned,
                                   "yaw_rad": None if s.last is None else s.last.euler_rad[2]}
                            for name, s in self.sources.items()}}
