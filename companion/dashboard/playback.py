"""The dashboard's playback source (``companion dashboard --play FILE.mcap``): a flight
recording's telemetry, fed to the hub as zenoh would have delivered it.

A :class:`Player` hands a recording's telemetry messages (companion/dashboard/recorded.py) to
a sink (``companion dashboard`` turns each into the key, encoding and exact bytes zenoh
carried, for the hub's :meth:`~companion.dashboard.hub.TelemetryHub.receive`, the path of live
samples) when the playback position reaches their log time, the position moving at ``speed``
times a wall clock. A seek tells the sink's owner to forget its state, then re-sends the
newest message of every stream at or before the target (of alerts, a list, the recent ones; of
a stream interleaving sources, its last few), so a page rebuilds its state without replaying
the flight. Every time is seconds of the daemon clock of the recording (its log time), unless
it says wall.
"""

from __future__ import annotations

import bisect
import time
from collections.abc import Callable, Sequence
from typing import Any

from companion.dashboard.hub import ALERT_HISTORY, PER_SOURCE_STREAMS
from companion.dashboard.recorded import TelemetryMessage

SPEEDS = (0.25, 1.0, 2.0, 4.0, 10.0)  # the page's choices; :meth:`Player.set_speed` takes any positive speed
PER_SOURCE_ON_SEEK = 16  # messages of a per-source stream re-sent on a seek: enough for every source's newest


class Player:
    """Plays ``messages`` (in log-time order) into ``deliver`` at ``speed`` times ``clock``.

    Call :meth:`advance` whenever convenient (:meth:`wait_s` says when the next message is
    due): it delivers every message whose time the position has reached. It starts paused at
    the first message's time (nothing delivered until :meth:`advance`), and pauses by itself
    at the end.
    """

    def __init__(self, messages: Sequence[TelemetryMessage], deliver: Callable[[TelemetryMessage], None],
                 reset: Callable[[], None] = lambda: None, clock: Callable[[], float] = time.monotonic) -> None:
        """``deliver``: gets each message; ``reset``: called on a seek, before the newest
        messages before the target are delivered again; ``clock``: a wall clock (s)."""
        self.messages = messages
        self.deliver = deliver
        self.reset = reset
        self.clock = clock
        self.start = messages[0].t if messages else 0.0
        self.end = messages[-1].t if messages else 0.0
        self.speed = 1.0
        self.playing = False
        self.seeks = 0  # seeks so far
        self._times = [m.t for m in messages]
        self._next = 0  # index of the next message to deliver
        self._anchor_t = self.start  # the position at wall time _anchor_wall
        self._anchor_wall = clock()
        self._keys: dict[str, list[int]] = {}  # key -> indices of its messages, in order
        for i, m in enumerate(messages):
            self._keys.setdefault(m.key, []).append(i)

    def position(self) -> float:
        """The playback position: daemon-clock time (s) of the recording shown now."""
        if not self.playing:
            return self._anchor_t
        return min(self.end, self._anchor_t + (self.clock() - self._anchor_wall) * self.speed)

    @property
    def ended(self) -> bool:
        """Every message has been delivered."""
        return self._next >= len(self.messages)

    def play(self) -> None:
        """Play from the position (from the start again when it has ended)."""
        if self.playing:
            return
        if self.ended:
            self.seek(self.start)
        self._anchor(self._anchor_t)
        self.playing = True

    def pause(self) -> None:
        """Stop the position where it is (the due messages are delivered first)."""
        if self.playing:
            self.advance()
            self._anchor(self.position())
            self.playing = False

    def set_speed(self, speed: float) -> None:
        """Play at ``speed`` times the wall clock from now on (0.25: four times slower).

        Raises:
            ValueError: ``speed`` is not a positive finite number.
        """
        if not 0.0 < speed < float("inf"):
            raise ValueError(f"speed must be a positive number, got {speed!r}")
        self._anchor(self.position())
        self.speed = float(speed)

    def seek(self, t: float) -> None:
        """Jump to ``t`` (clamped to the recording's span): ``reset``, then deliver again, in
        time order, the newest message of every key at or before ``t`` (of alerts the last
        :data:`ALERT_HISTORY`, of a per-source stream the last :data:`PER_SOURCE_ON_SEEK`);
        playing goes on playing from there."""
        t = min(max(float(t), self.start), self.end)
        self.seeks += 1
        self._anchor(t)
        self.reset()
        last = bisect.bisect_right(self._times, t) - 1  # the index of the last message at or before t
        chosen: list[int] = []
        for key, indices in self._keys.items():
            n = bisect.bisect_right(indices, last)
            chosen.extend(indices[max(0, n - _kept_on_seek(key)):n])
        for i in sorted(chosen):
            self.deliver(self.messages[i])
        self._next = bisect.bisect_right(self._times, t)

    def advance(self) -> int:
        """Deliver every message due at the position; how many. Pauses at the end."""
        now = self.position()
        delivered = 0
        while self._next < len(self.messages) and self._times[self._next] <= now:
            self.deliver(self.messages[self._next])
            self._next += 1
            delivered += 1
        if self.playing and self.ended:
            self._anchor(self.end)
            self.playing = False
        return delivered

    def wait_s(self) -> float | None:
        """Wall seconds until the next message is due; None when paused or ended."""
        if not self.playing or self.ended:
            return None
        return max(0.0, (self._times[self._next] - self.position()) / self.speed)

    def command(self, request: dict[str, Any]) -> dict[str, Any]:
        """Apply one request of the page: ``{"action": "play" | "pause"}``, ``{"action": "seek",
        "t": s}`` or ``{"action": "speed", "speed": x}`` (x one of :data:`SPEEDS`); the state after.

        Raises:
            ValueError: an unknown action or a missing or invalid value.
        """
        action = request.get("action")
        if action == "play":
            self.play()
        elif action == "pause":
            self.pause()
        elif action == "seek":
            t = request.get("t")
            if isinstance(t, bool) or not isinstance(t, (int, float)) or t != t:
                raise ValueError("seek needs a time t (s)")
            self.seek(t)
        elif action == "speed":
            speed = request.get("speed")
            if isinstance(speed, bool) or speed not in SPEEDS:
                raise ValueError(f"speed must be one of {', '.join(map(str, SPEEDS))}")
            self.set_speed(speed)
        else:
            raise ValueError(f"unknown action {action!r}: play, pause, seek or speed")
        return self.state()

    def state(self) -> dict[str, Any]:
        """What the page's playback bar shows: start, end and position ``t`` (s), speed,
        playing, ended, and ``seeks``."""
        return {"start": self.start, "end": self.end, "t": self.position(), "speed": self.speed,
                "playing": self.playing, "ended": self.ended and not self.playing, "seeks": self.seeks,
                "speeds": list(SPEEDS)}

    def _anchor(self, t: float) -> None:
        self._anchor_t = t
        self._anchor_wall = self.clock()


def _kept_on_seek(key: str) -> int:
    """How many of a key's latest messages a seek re-sends."""
    stream = key.rsplit("/", 1)[-1]
    return ALERT_HISTORY if stream == "alerts" else PER_SOURCE_ON_SEEK if stream in PER_SOURCE_STREAMS else 1
