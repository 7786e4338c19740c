"""Health model: every component reports ok / degraded / lost with a reason.

The daemon's overall state is the worst component state. Changes are logged and passed to
listeners (the STATUSTEXT notifier, telemetry); the systemd watchdog is driven separately by
the nav loop's heartbeat (companion/sdnotify.py), so a wedged loop is caught even when every
component still claims to be fine.
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Callable
from dataclasses import dataclass

log = logging.getLogger("companion.health")


def often(count: int) -> bool:
    """Whether the ``count``-th occurrence of a repeated event is worth a log line (1st, 100th, 200th, ...)."""
    return count == 1 or count % 100 == 0


class State(enum.IntEnum):
    """Ordered so that max() gives the worst."""

    OK = 0
    DEGRADED = 1
    LOST = 2

    @property
    def label(self) -> str:
        return self.name.lower()


@dataclass(frozen=True)
class ComponentHealth:
    state: State
    reason: str
    since: float  # daemon clock, seconds


Listener = Callable[[str, ComponentHealth, ComponentHealth | None], None]


class Health:
    """Registry of component states; ``report`` is cheap and may be called every cycle."""

    def __init__(self, clock: Callable[[], float]) -> None:
        self._clock = clock
        self._components: dict[str, ComponentHealth] = {}
        self._listeners: list[Listener] = []

    def on_change(self, listener: Listener) -> None:
        """Call ``listener(name, new, old)`` whenever a component's state (not just reason) changes."""
        self._listeners.append(listener)

    def report(self, name: str, state: State, reason: str) -> None:
        """Set component ``name`` to ``state`` because of ``reason``."""
        old = self._components.get(name)
        if old is not None and old.state == state and old.reason == reason:
            return
        since = old.since if old is not None and old.state == state else self._clock()
        new = ComponentHealth(state, reason, since)
        self._components[name] = new
        if old is None or old.state != state:
            level = logging.INFO if state == State.OK else logging.WARNING
            log.log(level, "%s: %s (%s)", name, state.label, reason)
            for listener in self._listeners:
                listener(name, new, old)

    def now(self) -> float:
        """The health clock (the daemon clock), s."""
        return self._clock()

    def get(self, name: str) -> ComponentHealth | None:
        return self._components.get(name)

    def worst(self, prefix: str) -> tuple[State, str]:
        """The worst state among components named ``prefix...`` and "name: reason"; (OK, "") for none."""
        worst: tuple[State, str] = (State.OK, "")
        for name, c in sorted(self._components.items()):
            if name.startswith(prefix) and c.state > worst[0]:
                worst = (c.state, f"{name}: {c.reason}")
        return worst

    @property
    def overall(self) -> State:
        return max((c.state for c in self._components.values()), default=State.OK)

    def snapshot(self) -> dict:
        """JSON-ready {overall, components: {name: {state, reason, since}}}."""
        return {
            "overall": self.overall.label,
            "components": {
                name: {"state": c.state.label, "reason": c.reason, "since": c.since}
                for name, c in sorted(self._components.items())
            },
        }

    def summary(self) -> str:
        """One line for systemd STATUS=, e.g. 'ok' or 'degraded: link lost (no heartbeat)'."""
        bad = [f"{n} {c.state.label} ({c.reason})" for n, c in sorted(self._components.items()) if c.state != State.OK]
        return self.overall.label + (": " + "; ".join(bad) if bad else "")


class Alert:
    """A component that is degraded while something bad keeps arriving (spoofed heartbeats,
    garbage values) and ok again at the first good arrival ``hold_s`` after the last bad one;
    what it counts stays with the caller."""

    def __init__(self, health: Health, name: str, hold_s: float) -> None:
        self.health = health
        self.name = name
        self.hold_s = hold_s
        self.active = False  # degraded by bad(), until good() clears it
        self._last_bad = -float("inf")  # health clock of the last bad arrival

    def bad(self, reason: str) -> None:
        self.active = True
        self._last_bad = self.health.now()
        self.health.report(self.name, State.DEGRADED, reason)

    def good(self, reason: str) -> None:
        """A good arrival: ok with ``reason`` unless the last bad one is more recent than ``hold_s``."""
        if self.health.now() - self._last_bad >= self.hold_s:
            self.active = False
            self.health.report(self.name, State.OK, reason)
