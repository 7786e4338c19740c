"""The flight recorder: what the daemon sees and does, to MCAP files (``record:`` in the config).

The daemon's event loop only queues (O(1), no encoding, no I/O): a bounded queue, a message that
finds it full is dropped and counted per topic. One thread encodes (companion/recording/codec.py),
compresses (zstd, per chunk) and writes. A chunk is written when it is full or
``record.flush_s`` old, so a file cut by a crash or power loss is readable up to its last chunk
(companion/recording/reader.py). A recording is split into parts of ``record.max_file_mb``; the
oldest parts in ``record.dir`` are removed to keep it under ``record.max_total_mb``. A write that
fails (disk full, device gone) stops the recording and says why in :attr:`Recorder.stats`; the
daemon flies on.

Topics (README "Flight recorder" lists them with their schemas):

- ``/sensors/<name>``: every message a sensor's driver delivered, stamped with the daemon time it
  was delivered (a camera's frames at most ``record.frame_rate_hz``);
- ``/nav/cycle``: every nav cycle: its time and every estimate the pipelines made in it, and the
  pose source selected; ``/nav/pose``: that pose (``foxglove.PoseInFrame``);
- ``/nav/source_command``, ``/nav/guidance_request``: what changes the pipelines or the selection
  from outside them (a mission step, a ground station);
- ``/mavlink/in``, ``/mavlink/out``: every MAVLink message received and sent;
- ``/telemetry/<stream>``: every telemetry message published; ``/health/changes``.

Each part holds the config (metadata ``companion.config``) and a copy of every file it names
(attachments, named by config key), so the recording replays on another machine.
"""

from __future__ import annotations

import base64
import errno
import json
import logging
import queue
import threading
import time
import uuid
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

from companion.messages import Estimate, Frame, PoseEstimate
from companion.recording import codec
from companion.telemetry.publisher import ENCODINGS, JSON_ENCODING, encode_json

log = logging.getLogger("companion.recording")

PROFILE = ""  # MCAP profile: none (JSON messages with JSON Schemas; "ros1"/"ros2" do not apply)
FILE_GLOB = "companion-*.mcap"
RECORDING_METADATA = "companion.recording"
CONFIG_METADATA = "companion.config"
STATS_METADATA = "companion.recorder_stats"
QUEUE_POLL_S = 0.1  # the writer thread wakes at least this often (flush, stop)
MB = 1_000_000

EVENT_SCHEMAS: dict[str, tuple[str, dict[str, Any]]] = {
    "/nav/cycle": ("companion.NavCycle", codec.event_schema(
        "companion.NavCycle", "One nav cycle: daemon time `now` (s), every estimate the pipelines made in it "
        "(exact encodings of PoseEstimate, AttitudeEstimate, RangeEstimate with their `type`), and `selected`: "
        "the pose source whose pose was forwarded to the autopilot (null: none).",
        {"now": codec.NUMBER, "estimates": {"type": "array", "items": {"type": "object", "required": ["type"]}},
         "selected": {"type": ["string", "null"]}})),
    "/nav/source_command": ("companion.SourceCommand", codec.event_schema(
        "companion.SourceCommand", "A commanded pose source (a mission's pose_source step); null: automatic.",
        {"source": {"type": ["string", "null"]}})),
    "/nav/guidance_request": ("companion.GuidanceRequest", codec.event_schema(
        "companion.GuidanceRequest", "A request to a guidance pipeline to take over (mission step, command).",
        {"reason": {"type": "string"}})),
    "/health/changes": ("companion.HealthChange", codec.event_schema(
        "companion.HealthChange", "A component's health changed.",
        {"component": {"type": "string"}, "state": {"type": "string"}, "reason": {"type": "string"}})),
}
MAVLINK_SCHEMA = ("companion.MavlinkMessage", codec.event_schema(
    "companion.MavlinkMessage", "A MAVLink message as pymavlink decodes it: name, source ids, fields (non-finite "
    "floats as \"nan\", \"inf\", \"-inf\").",
    {"name": {"type": "string"}, "sysid": {"type": "integer"}, "compid": {"type": "integer"}, "fields": {"type": "object"}}))
TELEMETRY_SCHEMA = ("companion.Telemetry", codec.event_schema(
    "companion.Telemetry", "A telemetry message exactly as zenoh carries it (docs/telemetry.md): the envelope `v`, "
    "`t` (daemon clock, s) and the stream's payload (NaN as null).",
    {"v": {"type": "integer"}, "t": {"type": "number"}}))
TELEMETRY_BINARY_SCHEMA = ("companion.TelemetryBinary", codec.event_schema(
    "companion.TelemetryBinary", "A telemetry message of a binary stream (docs/telemetry.md, e.g. scan): its zenoh "
    "encoding and bytes.",
    {"t": {"type": "number"}, "encoding": {"type": "string"}, "base64": {"type": "string", "contentEncoding": "base64"}}))


@dataclass
class RecorderStats:
    """Counters of the recorder (published as ``system.recorder``)."""

    queued: int = 0
    written: int = 0
    dropped: dict[str, int] = field(default_factory=dict)  # {topic: messages dropped because the queue was full}
    frames_skipped: int = 0  # camera frames not recorded by the rate cap (record.frame_rate_hz)
    encode_errors: int = 0
    bytes_written: int = 0  # of the parts finished so far and the current one
    parts: list[str] = field(default_factory=list)  # the files of this recording, in order
    removed: list[str] = field(default_factory=list)  # parts of older recordings removed by the size cap
    stopped: str | None = None  # why the recording stopped early (disk full, ...); None while it records
    thread_cpu_s: float = 0.0  # CPU time of the writer thread (encoding, compression, writing), s


@dataclass
class _Part:
    path: Path
    file: Any
    writer: Writer
    channels: dict[str, int] = field(default_factory=dict)  # topic -> channel id


class Recorder:
    """Records to ``directory``; :meth:`start` it, feed it from the event loop, :meth:`close` it."""

    def __init__(self, settings: Any, directory: Path, config_text: str, config_source: str,
                 files: dict[str, Path], clock: Callable[[], float]) -> None:
        """``settings``: the ``record`` config section; ``config_text``/``config_source``: the config
        file's text and path; ``files``: {config key: file} of the files the config names (copied in);
        ``clock``: the daemon clock (s), which stamps a sensor message when it is delivered."""
        self.settings = settings
        self.clock = clock
        self.directory = directory
        self.id = uuid.uuid4().hex
        self.started = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        self.stats = RecorderStats()
        self._config = {"yaml": config_text, "source": config_source}
        self._attachments = {key: path.read_bytes() for key, path in files.items() if path.is_file()}
        self._queue: queue.Queue = queue.Queue(maxsize=settings.queue_size)
        self._frame_due: dict[str, float] = {}
        self._dropped: Counter[str] = Counter()
        self._part: _Part | None = None
        self._finished_bytes = 0
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)

    # -- the event loop's side: O(1), never blocks ---------------------------------------------------

    def start(self) -> None:
        """Create the directory and the first part (raises OSError if it cannot), start writing."""
        self.directory.mkdir(parents=True, exist_ok=True)
        self._open_part()
        self._thread.start()

    def sensor(self, name: str) -> Callable[[Any], None]:
        """A driver subscriber that records sensor ``name``'s messages (``/sensors/<name>``)."""
        topic = f"/sensors/{name}"
        min_interval = 1.0 / self.settings.frame_rate_hz if self.settings.frame_rate_hz > 0 else 0.0

        def record(msg: Any) -> None:
            if isinstance(msg, Frame) and min_interval > 0:
                if msg.t_capture < self._frame_due.get(name, -1.0):
                    self.stats.frames_skipped += 1
                    return
                self._frame_due[name] = msg.t_capture + min_interval * 0.999
            self._put(topic, "message", self.clock(), msg, name)
        return record

    def cycle(self, now: float, estimates: list[Estimate], selected: PoseEstimate | None) -> None:
        """One nav cycle (the nav loop's recorder hook)."""
        self._put("/nav/cycle", "cycle", now, (now, estimates, selected))
        if selected is not None:
            self._put("/nav/pose", "message", now, selected)

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
        """Write what is queued, finish the file (summary, footer), stop the thread."""
        self._closing.set()
        if self._thread.is_alive():
            self._thread.join(timeout=timeout_s)
        if self._thread.is_alive():
            log.warning("recorder: not finished within %.1f s; %s is readable up to its last chunk",
                        timeout_s, self._part.path if self._part else "the last part")

    def snapshot(self) -> dict[str, Any]:
        """The counters as plain values (``system.recorder``)."""
        s = self.stats
        return {"id": self.id, "queued": s.queued, "written": s.written, "dropped": dict(self._dropped),
                "frames_skipped": s.frames_skipped, "encode_errors": s.encode_errors,
                "bytes_written": s.bytes_written, "parts": list(s.parts), "removed": len(s.removed), "stopped": s.stopped,
                "thread_cpu_s": s.thread_cpu_s}

    def _put(self, topic: str, kind: str, t: float, obj: Any, sensor: str = "") -> None:
        if self.stats.stopped is not None:
            return
        try:
            self._queue.put_nowait((topic, kind, t, obj, sensor))
            self.stats.queued += 1
        except queue.Full:
            self._dropped[topic] += 1

    # -- the writer thread ----------------------------------------------------------------------

    def _run(self) -> None:
        last_flush = time.monotonic()
        while True:
            try:
                item = self._queue.get(timeout=QUEUE_POLL_S)
            except queue.Empty:
                item = None
                if self._closing.is_set():
                    break
            try:
                if item is not None:
                    self._write(*item)
                if time.monotonic() - last_flush >= self.settings.flush_s:
                    last_flush = time.monotonic()
                    self._flush()
                    self.stats.thread_cpu_s = time.thread_time()
            except OSError as exc:
                self._stop(exc)
                return
        self.stats.thread_cpu_s = time.thread_time()
        try:
            self._finish_part()
        except OSError as exc:
            self._stop(exc)

    def _write(self, topic: str, kind: str, t: float, obj: Any, sensor: str) -> None:
        try:
            schema, data, stamp = self._encode(topic, kind, t, obj, sensor)
        except (TypeError, ValueError) as exc:
            self.stats.encode_errors += 1
            log.error("recorder: cannot encode a message of %s: %s", topic, exc)
            return
        part = self._part
        channel = part.channels.get(topic)
        if channel is None:
            name, body = schema
            schema_id = part.writer.register_schema(name, codec.SCHEMA_ENCODING, codec.dumps(body))
            channel = part.channels[topic] = part.writer.register_channel(topic, codec.MESSAGE_ENCODING, schema_id)
        part.writer.add_message(channel, log_time=_ns(t), data=data, publish_time=_ns(stamp))
        self.stats.written += 1
        self.stats.bytes_written = self._finished_bytes + part.file.tell()
        if part.file.tell() >= self.settings.max_file_mb * MB:
            self._finish_part()
            self._open_part()

    def _encode(self, topic: str, kind: str, t: float, obj: Any, sensor: str) -> tuple[tuple[str, dict], bytes, float]:
        """(schema, JSON bytes, the data's own stamp s: MCAP publish time) of one queued item."""
        if kind == "message":
            doc = codec.encode_message(obj, sensor)
            return codec.message_schema(type(obj)), codec.dumps(doc), _stamp_of(obj)
        if kind == "cycle":
            now, estimates, selected = obj
            doc = {"now": codec.exact(now), "estimates": [codec.encode_estimate(e) for e in estimates],
                   "selected": selected.source if selected is not None else None}
            return EVENT_SCHEMAS["/nav/cycle"], codec.dumps(doc), now
        if kind == "event":
            return EVENT_SCHEMAS[topic], codec.dumps(codec.exact(obj)), t
        if kind == "mavlink":
            doc = {"name": obj.get_type(), "sysid": obj.get_srcSystem(), "compid": obj.get_srcComponent(),
                   "fields": codec.exact({k: v for k, v in obj.to_dict().items() if k != "mavpackettype"})}
            return MAVLINK_SCHEMA, codec.dumps(doc), t
        stamp_t, payload = obj
        stream = topic.removeprefix("/telemetry/")
        encode, encoding = ENCODINGS.get(stream, (encode_json, JSON_ENCODING))
        data = encode(stamp_t, payload)
        if encoding == JSON_ENCODING:
            return TELEMETRY_SCHEMA, data, stamp_t
        return TELEMETRY_BINARY_SCHEMA, codec.dumps(
            {"t": stamp_t, "encoding": encoding, "base64": base64.b64encode(data).decode()}), stamp_t

    def _open_part(self) -> None:
        index = len(self.stats.parts) + 1
        path = self.directory / f"companion-{self.started}-{self.id[:8]}-{index:04d}.mcap"
        file = open(path, "wb")
        writer = Writer(file, chunk_size=self.settings.chunk_kb * 1024, compression=CompressionType.ZSTD)
        writer.start(PROFILE, "uav-companion")
        writer.add_metadata(RECORDING_METADATA, {"id": self.id, "part": str(index), "started_utc": self.started})
        writer.add_metadata(CONFIG_METADATA, self._config)
        for key, data in self._attachments.items():
            writer.add_attachment(log_time=0, create_time=0, name=key, media_type="application/octet-stream", data=data)
        self._part = _Part(path, file, writer)
        self.stats.parts.append(path.name)
        self._keep_under_cap()

    def _finish_part(self) -> None:
        part = self._part
        if part is None:
            return
        self._part = None
        part.writer.add_metadata(STATS_METADATA, {"snapshot": json.dumps(self.snapshot())})
        part.writer.finish()
        part.file.close()
        self._finished_bytes += part.path.stat().st_size
        self.stats.bytes_written = self._finished_bytes

    def _flush(self) -> None:
        if self._part is not None:
            self._part.writer.flush()

    def _keep_under_cap(self) -> None:
        """Remove the oldest parts in the directory (of any recording, never the one being written)
        until the directory's recordings fit ``record.max_total_mb``."""
        cap = self.settings.max_total_mb * MB
        parts = sorted(self.directory.glob(FILE_GLOB))
        current = self._part.path if self._part is not None else None
        total = sum(p.stat().st_size for p in parts)
        for p in parts:
            if total <= cap:
                break
            if p == current:
                continue
            total -= p.stat().st_size
            p.unlink(missing_ok=True)
            self.stats.removed.append(p.name)
            log.info("recorder: removed %s (record.max_total_mb %.0f)", p.name, self.settings.max_total_mb)

    def _stop(self, exc: OSError) -> None:
        """A write failed: stop recording (the file stays readable up to its last whole chunk)."""
        what = "disk full" if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG) else "write failed"
        self.stats.stopped = f"{what}: {exc.strerror or exc}"
        log.error("recorder: %s; recording stopped, %s kept up to its last chunk", self.stats.stopped,
                  self._part.path if self._part else "the last part")
        if self._part is not None:
            try:
                self._part.file.close()
            except OSError:
                pass
            self._part = None
        while True:  # release what is queued (nothing more is queued once stopped)
            try:
                self._queue.get_nowait()
            except queue.Empty:
                break


def _ns(t: float) -> int:
    return max(0, int(round(t * 1e9)))


def _stamp_of(msg: Any) -> float:
    """A message's own daemon-clock stamp (s)."""
    return msg.t_capture if hasattr(msg, "t_capture") else msg.t
