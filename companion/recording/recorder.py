"""The flight recorder: what the daemon sees and does, as typed JSON messages with schemas, to MCAP
files (companion/recording/mcap_files.py, ``record.enabled``) and, optionally, live to the Foxglove
app (companion/recording/foxglove_live.py, ``record.foxglove_server``).

The daemon's event loop only queues (O(1), no encoding, no I/O): a bounded queue, a message that
finds it full is dropped and counted per topic. One thread encodes (companion/recording/codec.py)
and hands each message to the sinks, and flushes them every ``record.flush_s`` (a chunk written: a
file cut by a crash or power loss is readable up to its last chunk, companion/recording/reader.py).
A sink whose write fails (disk full, device gone) is dropped and the reason kept in
``stopped``; the daemon flies on.

Topics (README "Flight recorder and replay" lists them with their schemas):

- ``/sensors/<name>``: every message a sensor's driver delivered, logged at the daemon time it was
  delivered (a camera's frames at most ``record.frame_rate_hz``); a scan also as Foxglove's
  ``foxglove.LaserScan`` on ``/sensors/<name>/laser_scan``;
- ``/nav/cycle``: every nav cycle: its time and every estimate the pipelines made in it, and the
  pose source selected; ``/nav/pose``: that pose (``foxglove.PoseInFrame``, at most ``record.view_hz``);
- ``/nav/source_command``, ``/nav/guidance_request``: what changes the pipelines or the selection
  from outside them (a mission step, a ground station);
- ``/mavlink/in``, ``/mavlink/out``: every MAVLink message received and sent (wire bytes, in batches);
- ``/telemetry/<stream>``: every telemetry message published; ``/health/changes``.
"""

from __future__ import annotations

import base64
import errno
import logging
import math
import threading
import time
import uuid
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from companion.messages import Estimate, Frame, PoseEstimate, Scan
from companion.recording import codec
from companion.telemetry.publisher import ENCODINGS, JSON_ENCODING, encode_json

log = logging.getLogger("companion.recording")

# The writer thread writes everything queued at most every BATCH_S, right after a nav cycle (the
# loop is then idle until its next tick, so the writer's hold of the GIL does not stretch a cycle),
# or after BATCH_S without one. One wake-up per message (a queue.Queue's) cost more than the
# encoding, in thread switches and GIL hand-overs; one per cycle (50 Hz) a point of a core more.
BATCH_S = 0.05


class Sink(Protocol):
    """Where the writer thread puts the encoded messages (MCAP files, the Foxglove server). Called
    from the writer thread only; OSError from any method drops the sink."""

    name: str

    def open(self, stats: Callable[[], dict[str, Any]]) -> None:
        """Start; ``stats`` gives the recorder's counters (MCAP parts keep them when they end)."""
    def write(self, topic: str, schema: codec.ChannelSchema, data: bytes, log_ns: int, publish_ns: int) -> None: ...
    def flush(self) -> None: ...
    def close(self) -> None: ...
    def abandon(self) -> None: ...
    def snapshot(self) -> dict[str, Any]: ...


EVENT_SCHEMAS: dict[str, codec.ChannelSchema] = {
    "/nav/cycle": codec.event_schema(
        "companion.NavCycle", "One nav cycle: daemon time `now` (s), every estimate the pipelines made in it "
        "(exact encodings of PoseEstimate, AttitudeEstimate, RangeEstimate with their `type`), and `selected`: "
        "the pose source whose pose was forwarded to the autopilot (null: none).",
        {"now": codec.NUMBER, "estimates": {"type": "array", "items": {"type": "object", "required": ["type"]}},
         "selected": {"type": ["string", "null"]}}),
    "/nav/source_command": codec.event_schema(
        "companion.SourceCommand", "A commanded pose source (a mission's pose_source step); null: automatic.",
        {"source": {"type": ["string", "null"]}}),
    "/nav/guidance_request": codec.event_schema(
        "companion.GuidanceRequest", "A request to a guidance pipeline to take over (mission step, command).",
        {"reason": {"type": "string"}}),
    "/health/changes": codec.event_schema(
        "companion.HealthChange", "A component's health changed.",
        {"component": {"type": "string"}, "state": {"type": "string"}, "reason": {"type": "string"}}),
}
MAVLINK_SCHEMA = codec.event_schema(
    "companion.MavlinkMessages", "The MAVLink messages of one direction received or sent within the recorder's "
    "batch (at most 50 ms), in order: each one's daemon time `t` (s), name, source ids and its bytes as on the wire "
    "(MAVLink 1 or 2, signature included; pymavlink's parse_buffer decodes them). Raw bytes, not decoded fields, "
    "and batched: exact, and the cheapest to record (some 700 messages a second).",
    {"messages": {"type": "array", "items": {
        "type": "object", "required": ["t", "name", "sysid", "compid", "base64"],
        "properties": {"t": {"type": "number"}, "name": {"type": "string"}, "sysid": {"type": "integer"},
                       "compid": {"type": "integer"}, "base64": {"type": "string", "contentEncoding": "base64"}}}}})
TELEMETRY_SCHEMA = codec.event_schema(
    "companion.Telemetry", "A telemetry message exactly as zenoh carries it (docs/telemetry.md): the envelope `v`, "
    "`t` (daemon clock, s) and the stream's payload (NaN as null).",
    {"v": {"type": "integer"}, "t": {"type": "number"}})
TELEMETRY_BINARY_SCHEMA = codec.event_schema(
    "companion.TelemetryBinary", "A telemetry message of a binary stream (docs/telemetry.md, e.g. scan): its zenoh "
    "encoding and bytes.",
    {"t": {"type": "number"}, "encoding": {"type": "string"}, "base64": {"type": "string", "contentEncoding": "base64"}})


@dataclass
class RecorderStats:
    """Counters of the recorder (published as ``system.recorder``)."""

    queued: int = 0
    written: int = 0  # messages encoded and handed to the sinks (a batch of MAVLink messages counts once)
    frames_skipped: int = 0  # camera frames not recorded by the rate cap (record.frame_rate_hz)
    encode_errors: int = 0
    stopped: str | None = None  # why a sink stopped early (disk full, ...); None while all work
    thread_cpu_s: float = 0.0  # CPU time of the writer thread (encoding, compression, writing), s


class Recorder:
    """Encodes what the daemon sees for ``sinks``; :meth:`start` it, feed it from the event loop,
    :meth:`close` it."""

    def __init__(self, settings: Any, sinks: list[Sink], clock: Callable[[], float], recording_id: str | None = None) -> None:
        """``settings``: the ``record`` config section; ``clock``: the daemon clock (s), which stamps a
        sensor message when it is delivered."""
        self.settings = settings
        self.sinks = sinks
        self.clock = clock
        self.id = recording_id or uuid.uuid4().hex
        self.stats = RecorderStats()
        self._queue: deque[tuple[str, str, float, Any, str]] = deque()  # append/popleft are atomic under the GIL
        self._dropped: Counter[str] = Counter()
        self._pose_views = _RateCap(settings.view_hz)
        self._closing = threading.Event()
        self._wake = threading.Event()  # set after each nav cycle
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)

    # -- the event loop's side: O(1), never blocks ---------------------------------------------------

    def start(self) -> None:
        """Open every sink (raises OSError if one cannot: nothing started), start the writer thread."""
        opened: list[Sink] = []
        try:
            for sink in self.sinks:
                sink.open(self.snapshot)
                opened.append(sink)
        except BaseException:
            for sink in opened:
                sink.abandon()
            self.sinks = []  # every hook becomes a no-op: nothing is queued for a thread that will not run
            raise
        self._thread.start()

    def sensor(self, name: str) -> Callable[[Any], None]:
        """A driver subscriber that records sensor ``name``'s messages (``/sensors/<name>``; a scan's
        Foxglove view at most ``record.view_hz``, a camera's frames at most ``record.frame_rate_hz``)."""
        topic = f"/sensors/{name}"
        frames = _RateCap(self.settings.frame_rate_hz)
        views = _RateCap(self.settings.view_hz)

        def record(msg: Any) -> None:
            if isinstance(msg, Frame) and not frames.due(msg.t_capture):
                self.stats.frames_skipped += 1
                return
            view = isinstance(msg, Scan) and self.settings.view_hz > 0 and views.due(msg.t_capture)
            self._put(topic, "message+view" if view else "message", self.clock(), msg, name)
        return record

    def cycle(self, now: float, estimates: list[Estimate], selected: PoseEstimate | None) -> None:
        """One nav cycle (the nav loop's recorder hook)."""
        self._put("/nav/cycle", "cycle", now, (now, estimates, selected))
        if selected is not None and self.settings.view_hz > 0 and self._pose_views.due(now):
            self._put("/nav/pose", "message", now, selected)
        self._wake.set()

    def event(self, topic: str, t: float, payload: dict[str, Any]) -> None:
        """One of :data:`EVENT_SCHEMAS`' events at daemon time ``t``."""
        self._put(topic, "event", t, payload)

    def mavlink(self, direction: str, t: float, msg: Any) -> None:
        """A MAVLink message ``direction`` "in" or "out" at daemon time ``t``."""
        self._put(f"/mavlink/{direction}", "mavlink", t, msg)

    def telemetry(self, stream: str, t: float, payload: dict[str, Any]) -> None:
        """A telemetry message published at daemon time ``t`` (its payload is not mutated later)."""
        self._put(f"/telemetry/{stream}", "telemetry", t, (t, payload))

    def close(self, timeout_s: float = 1.0) -> None:
        """Write what is queued, finish the sinks (a file's summary and footer), stop the thread."""
        self._closing.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout=timeout_s)
        if self._thread.is_alive():
            log.warning("recorder: not finished within %.1f s; the last part is readable up to its last chunk",
                        timeout_s)

    def snapshot(self) -> dict[str, Any]:
        """The counters as plain values (``system.recorder``)."""
        s = self.stats
        out = {"id": self.id, "queued": s.queued, "written": s.written, "dropped": dict(self._dropped),
               "frames_skipped": s.frames_skipped, "encode_errors": s.encode_errors, "stopped": s.stopped,
               "thread_cpu_s": s.thread_cpu_s}
        for sink in list(self.sinks):
            out.update(sink.snapshot())
        return out

    def _put(self, topic: str, kind: str, t: float, obj: Any, sensor: str = "") -> None:
        if not self.sinks:
            return
        if len(self._queue) >= self.settings.queue_size:
            self._dropped[topic] += 1
            return
        self._queue.append((topic, kind, t, obj, sensor))
        self.stats.queued += 1

    # -- the writer thread ----------------------------------------------------------------------

    def _run(self) -> None:
        last_flush = last_batch = time.monotonic()
        while self.sinks:
            self._wake.wait(BATCH_S)
            self._wake.clear()
            closing = self._closing.is_set()
            if not closing and time.monotonic() - last_batch < BATCH_S:
                continue  # a cycle ended, but the last batch was written less than BATCH_S ago
            last_batch = time.monotonic()
            mavlink: dict[str, list[tuple[float, Any]]] = {}
            while self._queue and self.sinks:
                item = self._queue.popleft()
                if item[1] == "mavlink":
                    mavlink.setdefault(item[0], []).append((item[2], item[3]))
                else:
                    self._write(*item)
            for topic, batch in mavlink.items():  # one MCAP message per batch: a tenth of the writer's time
                self._write(topic, "mavlink", batch[0][0], batch, "")
            if time.monotonic() - last_flush >= self.settings.flush_s:
                last_flush = time.monotonic()
                self._each_sink(lambda sink: sink.flush())
                self.stats.thread_cpu_s = time.thread_time()
            if closing:
                break
        self.stats.thread_cpu_s = time.thread_time()
        self._each_sink(lambda sink: sink.close())
        self._queue.clear()  # what a stopped sink left (nothing more is queued without sinks)

    def _write(self, topic: str, kind: str, t: float, obj: Any, sensor: str) -> None:
        try:
            schema, data, stamp = self._encode(topic, kind, t, obj, sensor)
            view = codec.laser_scan_view(obj, sensor) if kind == "message+view" else None
        except (TypeError, ValueError) as exc:
            self.stats.encode_errors += 1
            log.error("recorder: cannot encode a message of %s: %s", topic, exc)
            return
        log_ns, publish_ns = _ns(t), _ns(stamp)
        self._each_sink(lambda sink: sink.write(topic, schema, data, log_ns, publish_ns))
        if view is not None:  # Foxglove's view of the scan (companion/recording/codec.py)
            self._each_sink(lambda sink: sink.write(f"{topic}/laser_scan", codec.LASER_SCAN_SCHEMA, view, log_ns, publish_ns))
        self.stats.written += 1

    def _each_sink(self, action: Callable[[Sink], None]) -> None:
        """``action`` on every sink; one that raises OSError is dropped (:meth:`_stop`)."""
        for sink in list(self.sinks):
            try:
                action(sink)
            except OSError as exc:
                self._stop(sink, exc)

    def _encode(self, topic: str, kind: str, t: float, obj: Any, sensor: str) -> tuple[codec.ChannelSchema, bytes, float]:
        """(schema, JSON bytes, the data's own stamp s: MCAP publish time) of one queued item."""
        if kind.startswith("message"):
            return codec.message_schema(type(obj)), codec.dumps(codec.encode_message(obj, sensor)), _stamp_of(obj)
        if kind == "cycle":
            now, estimates, selected = obj
            doc = {"now": codec.exact(now), "estimates": [codec.encode_estimate(e) for e in estimates],
                   "selected": selected.source if selected is not None else None}
            return EVENT_SCHEMAS["/nav/cycle"], codec.dumps(doc), now
        if kind == "event":
            return EVENT_SCHEMAS[topic], codec.dumps(codec.exact(obj)), t
        if kind == "mavlink":
            doc = {"messages": [{"t": stamp_t, "name": msg.get_type(), "sysid": msg.get_srcSystem(),
                                 "compid": msg.get_srcComponent(), "base64": base64.b64encode(msg.get_msgbuf()).decode()}
                                for stamp_t, msg in obj]}
            return MAVLINK_SCHEMA, codec.dumps(doc), t
        stamp_t, payload = obj
        stream = topic.removeprefix("/telemetry/")
        encode, encoding = ENCODINGS.get(stream, (encode_json, JSON_ENCODING))
        data = encode(stamp_t, payload)
        if encoding == JSON_ENCODING:
            return TELEMETRY_SCHEMA, data, stamp_t
        return TELEMETRY_BINARY_SCHEMA, codec.dumps(
            {"t": stamp_t, "encoding": encoding, "base64": base64.b64encode(data).decode()}), stamp_t

    def _stop(self, sink: Sink, exc: OSError) -> None:
        """A write failed: stop using ``sink`` (a file stays readable up to its last whole chunk)."""
        what = "disk full" if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG) else "write failed"
        self.stats.stopped = f"{what}: {exc.strerror or exc}"
        log.error("recorder: %s; recording stopped (%s), kept up to its last chunk", self.stats.stopped, sink.name)
        sink.abandon()
        self.sinks.remove(sink)


class _RateCap:
    """At most ``rate_hz`` per second of the stamps it is given (0: no cap)."""

    def __init__(self, rate_hz: float) -> None:
        self.interval = 1.0 / rate_hz if rate_hz > 0 else 0.0
        self.next_t = -math.inf

    def due(self, t: float) -> bool:
        if t < self.next_t:
            return False
        self.next_t = t + self.interval * 0.999  # a stamp's jitter must not skip every other one
        return True


def _ns(t: float) -> int:
    return max(0, int(round(t * 1e9)))


def _stamp_of(msg: Any) -> float:
    """A message's own daemon-clock stamp (s)."""
    return msg.t_capture if hasattr(msg, "t_capture") else msg.t
