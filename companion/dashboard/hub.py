"""The dashboard's telemetry hub: zenoh samples in, browser events out.

zenoh delivers samples on its own threads; :meth:`TelemetryHub.on_sample` only appends them to
a bounded inbox (the oldest dropped and counted when full) and wakes the asyncio loop once per
batch. On the loop every sample becomes one event, a JSON text (JSON payloads are parsed and
re-serialised, binary scans decoded), which replaces the cached event of its key and is
offered to every browser. Every stream name of the key space passes, a pipeline's own streams
(``telemetry_streams``) too, so a new pipeline needs no change here. A browser that joins gets
the cache at once: the newest status, the last sample of every key and the recent alerts. Each
browser has a bounded outbox holding the newest event per key, so a slow browser sees fewer
updates but never holds the hub back. A stream that interleaves several sources
(``attitude_check``: one message per attitude source, often at the same instant) is cached and
queued per key and source, so the newest message of one source never replaces another's.

Events (the page's input, docs/dashboard.md):

* ``{"type": "sample", "key", "sysid", "stream", "rx", "data"}``: ``rx`` is the hub's clock
  (s) at arrival, ``data`` the payload (a decoded scan has ``ranges_mm`` as a list);
* ``{"type": "status", "now", "vehicles": {sysid: {"age_s", "streams": {stream: {"count",
  "rate_hz", "age_s", "bad"}}}}, "inbox_dropped", "browsers", ...}`` every second: ``age_s``
  is the time since the last sample of the vehicle or stream (s), ``bad`` counts samples that
  could not be decoded;
* ``{"type": "reset"}`` (playback only, on a seek): forget every vehicle's state, the samples
  that follow rebuild it.
"""

from __future__ import annotations

import asyncio
import json
import logging
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import zenoh

from companion.telemetry.keys import KEY_PREFIX, is_stream_name
from companion.telemetry.rate import RateWindow
from companion.telemetry.scan_codec import SCAN_ENCODING, decode_scan

log = logging.getLogger("companion.dashboard")

INBOX_SIZE = 1024  # samples waiting for the loop, all keys together
OUTBOX_SIZE = 256  # events waiting for one browser (one per key; each recent alert is one)
ALERT_HISTORY = 50  # alerts a joining browser gets (the alerts stream is a list, not a state)
PER_SOURCE_STREAMS = ("attitude_check",)  # their messages name a `source`: the newest per source is kept
SUBSCRIPTION = f"{KEY_PREFIX}/*/*"
RESET_EVENT = '{"type":"reset"}'


class Browser:
    """One connected browser: a bounded outbox keeping the newest event per slot, in order."""

    def __init__(self, size: int = OUTBOX_SIZE) -> None:
        self.size = size
        self.wake = asyncio.Event()
        self.dropped = 0  # events discarded because the outbox was full
        self._pending: OrderedDict[str, str] = OrderedDict()

    def offer(self, slot: str, text: str) -> None:
        """Queue ``text`` under ``slot``, replacing an unsent event of the same slot."""
        if slot not in self._pending and len(self._pending) >= self.size:
            self._pending.popitem(last=False)
            self.dropped += 1
        self._pending[slot] = text
        self.wake.set()

    def take(self) -> list[str]:
        """Every queued event, oldest slot first; the outbox is empty afterwards."""
        texts = list(self._pending.values())
        self._pending.clear()
        self.wake.clear()
        return texts


@dataclass
class StreamStats:
    """What the hub saw of one stream of one vehicle; times on the hub's clock (s)."""

    count: int = 0
    bad: int = 0
    last_rx: float | None = None
    arrivals: RateWindow = field(default_factory=RateWindow)

    def summary(self, now: float) -> dict[str, Any]:
        return {"count": self.count, "bad": self.bad, "rate_hz": self.arrivals.rate_hz(now),
                "age_s": None if self.last_rx is None else now - self.last_rx}


class TelemetryHub:
    """The last event of every key, per-stream statistics and the connected browsers.

    Every method but :meth:`on_sample` runs on the loop given at construction.
    """

    def __init__(self, loop: asyncio.AbstractEventLoop, clock: Callable[[], float] = time.monotonic) -> None:
        self.loop = loop
        self.clock = clock
        self.browsers: set[Browser] = set()
        self.inbox_dropped = 0
        self._inbox: deque[tuple[str, str, bytes, float]] = deque()
        self._inbox_lock = threading.Lock()
        self._drain_scheduled = False
        self._cache: dict[str, str] = {}  # slot (the key, or key#source) -> its newest sample event
        self._alerts: deque[str] = deque(maxlen=ALERT_HISTORY)
        self._alert_count = 0
        self._status_extra: dict[str, Any] = {}
        self._stats: dict[tuple[int, str], StreamStats] = {}

    # -- zenoh side --------------------------------------------------------------------------

    def on_sample(self, sample: zenoh.Sample) -> None:
        """zenoh subscriber callback (a zenoh thread): queue the sample, wake the loop."""
        item = (str(sample.key_expr), str(sample.encoding), sample.payload.to_bytes(), self.clock())
        with self._inbox_lock:
            if len(self._inbox) >= INBOX_SIZE:
                self._inbox.popleft()
                self.inbox_dropped += 1
            self._inbox.append(item)
            if self._drain_scheduled:
                return
            self._drain_scheduled = True
        try:
            self.loop.call_soon_threadsafe(self._drain)
        except RuntimeError:  # the loop is closed: the dashboard is stopping
            pass

    # -- loop side ---------------------------------------------------------------------------

    def _drain(self) -> None:
        with self._inbox_lock:
            items = list(self._inbox)
            self._inbox.clear()
            self._drain_scheduled = False
        for key, encoding, payload, rx in items:
            self.receive(key, encoding, payload, rx)

    def receive(self, key: str, encoding: str, payload: bytes, rx: float) -> None:
        """One sample as zenoh carries it (key expression, encoding, bytes), received at ``rx``
        (the hub's clock, s): decoded, cached and offered to every browser. The zenoh samples
        come here from the inbox; a playback (companion/dashboard/playback.py) calls it directly."""
        parts = key.split("/")
        if len(parts) != 3 or not (parts[1].isascii() and parts[1].isdigit()) or not is_stream_name(parts[2]):
            return  # not a vehicle stream: neither cached nor counted
        sysid, stream = int(parts[1]), parts[2]
        stats = self._stats.setdefault((sysid, stream), StreamStats())
        stats.count += 1
        stats.last_rx = rx
        stats.arrivals.add(rx)
        try:
            data = decode_payload(encoding, payload)
            text = json.dumps({"type": "sample", "key": key, "sysid": sysid, "stream": stream, "rx": rx,
                               "data": data}, separators=(",", ":"), allow_nan=False)
        except ValueError:  # not a payload the dashboard reads, or NaN in a scan header
            stats.bad += 1
            return
        slot = key
        if stream == "alerts":
            self._alert_count += 1
            slot = f"{key}#{self._alert_count}"
            self._alerts.append(text)
        else:
            if stream in PER_SOURCE_STREAMS and isinstance(data.get("source"), str):
                slot = f"{key}#{data['source']}"
            self._cache[slot] = text
        for browser in self.browsers:
            browser.offer(slot, text)

    def attach(self) -> Browser:
        """A new browser, its outbox already holding the status, the cache and recent alerts."""
        browser = Browser()
        browser.offer("status", self._status_text())
        for slot, text in self._cache.items():
            browser.offer(slot, text)
        for i, text in enumerate(self._alerts):
            browser.offer(f"alert-history#{i}", text)
        self.browsers.add(browser)
        return browser

    def reset(self) -> None:
        """Forget every cached sample, alert and statistic (a playback seeks): every browser's
        queued events are dropped and it gets ``{"type": "reset"}``, telling the page to forget its
        own state before the samples that follow."""
        self._cache.clear()
        self._alerts.clear()
        self._stats.clear()
        for browser in self.browsers:
            browser.take()
            browser.offer("reset", RESET_EVENT)

    def detach(self, browser: Browser) -> None:
        self.browsers.discard(browser)

    def status(self) -> dict[str, Any]:
        """Per-vehicle and per-stream arrival statistics now (see the module docstring)."""
        now = self.clock()
        vehicles: dict[str, dict[str, Any]] = {}
        for (sysid, stream), stats in sorted(self._stats.items()):
            vehicle = vehicles.setdefault(str(sysid), {"age_s": None, "streams": {}})
            summary = stats.summary(now)
            vehicle["streams"][stream] = summary
            if vehicle["age_s"] is None or summary["age_s"] < vehicle["age_s"]:
                vehicle["age_s"] = summary["age_s"]
        return {"type": "status", "now": now, "vehicles": vehicles, "inbox_dropped": self.inbox_dropped,
                "browsers": len(self.browsers), "browser_drops": sum(b.dropped for b in self.browsers)}

    def publish_status(self, extra: dict[str, Any]) -> None:
        """Send :meth:`status` plus ``extra`` (e.g. zenoh session facts, kept for the browsers
        joining later) to every browser."""
        self._status_extra = extra
        text = self._status_text()
        for browser in self.browsers:
            browser.offer("status", text)

    def _status_text(self) -> str:
        return json.dumps({**self.status(), **self._status_extra}, separators=(",", ":"))


def decode_payload(encoding: str, payload: bytes) -> dict[str, Any]:
    """A sample's payload as a JSON-ready dict: a JSON object, or a ``uav.scan.v1`` scan with
    ``ranges_mm`` as a list of integers.

    Raises:
        ValueError: another encoding, malformed JSON or scan, invalid UTF-8, NaN or infinity.
    """
    if encoding == SCAN_ENCODING:
        scan = decode_scan(payload)
        return {**scan, "ranges_mm": scan["ranges_mm"].tolist()}
    if encoding.split(";")[0] not in ("application/json", "text/json"):
        raise ValueError(f"the dashboard does not read {encoding!r} samples")
    data = json.loads(payload, parse_constant=_reject_constant)
    if not isinstance(data, dict):
        raise ValueError("a telemetry JSON payload is an object")
    return data


def _reject_constant(name: str) -> None:
    raise ValueError(f"{name} is not JSON")
