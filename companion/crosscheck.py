"""Attitude cross-check: a pipeline's attitude-only estimate against the autopilot's ATTITUDE.

An attitude estimate is never sent to the autopilot as a pose; it checks the autopilot's own
attitude at the estimate's capture time (an estimate is published late: it waits for its GNSS
fixes, and in a 30 deg/s roll-in the newest ATTITUDE would differ from it by the turn since; an
estimate without an autopilot attitude near its time is not compared). When they differ by more than ``threshold_deg`` (largest of the roll, pitch, yaw
differences, wrapped, over the angles the estimate measures: NaN is an angle it cannot see, e.g.
the yaw of a level floor's tilt) for ``hold_s`` without a break (an estimate that agrees, or
none for more than half of ``hold_s``: two diverging estimates with nothing between them do not
show a divergence that lasted), the check reports
``crosscheck:<source>`` degraded (health announces it by STATUSTEXT and telemetry), and OK again
once they agree.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from companion.frames import wrap_pi
from companion.health import Health, State
from companion.messages import AttitudeEstimate


class AttitudeCrossCheck:
    """Compares attitude estimates with ``autopilot_euler(t)``: the autopilot's roll, pitch, yaw
    (rad) at daemon time ``t`` (s), or None when it has none for that time."""

    def __init__(self, autopilot_euler: Callable[[float], tuple[float, float, float] | None], health: Health,
                 publish: Callable[[str, dict], None], threshold_deg: float, hold_s: float) -> None:
        self.autopilot_euler = autopilot_euler
        self.health = health
        self.publish = publish
        self.threshold_rad = math.radians(threshold_deg)
        self.hold_s = hold_s
        self._since: dict[str, float | None] = {}  # per source: capture time the divergence began
        self._last: dict[str, float] = {}  # per source: capture time of the last estimate compared

    def submit(self, estimate: AttitudeEstimate) -> None:
        reference = self.autopilot_euler(estimate.t_capture)
        if reference is None:
            return
        measured = [(a, b) for a, b in zip(estimate.euler_rad, reference) if math.isfinite(a)]
        if not measured:
            return
        diff = max(abs(wrap_pi(a - b)) for a, b in measured)
        component = f"crosscheck:{estimate.source}"
        since = self._since.get(estimate.source)
        last = self._last.get(estimate.source)
        self._last[estimate.source] = estimate.t_capture
        if self.hold_s > 0.0 and last is not None and estimate.t_capture - last > 0.5 * self.hold_s:
            since = None  # a gap: whatever diverged before it is not known to have lasted
        alarm = False
        if diff <= self.threshold_rad:
            self._since[estimate.source] = None
            self.health.report(component, State.OK, "attitude agrees with the autopilot's")
        elif since is None:
            self._since[estimate.source] = estimate.t_capture
        elif estimate.t_capture - since >= self.hold_s:
            alarm = True
            self.health.report(component, State.DEGRADED,
                               f"attitude differs from the autopilot's by {math.degrees(diff):.1f} deg")
        self.publish("attitude_check", {"source": estimate.source, "t_capture": estimate.t_capture,
                                        "euler_rad": estimate.euler_rad, "autopilot_euler_rad": reference,
                                        "difference_deg": math.degrees(diff), "alarm": alarm})
