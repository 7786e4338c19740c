"""The flight recorder's files: MCAP parts in ``record.dir`` (companion/recording/recorder.py feeds
them from its writer thread).

Each part starts with the recording's id and part number (metadata ``companion.recording``), the
config (``companion.config``) and a copy of every file it names (attachments, by config key), so any
part replays on another machine. Messages go in zstd chunks of ``record.chunk_kb``, a chunk at least
every ``record.flush_s``. A part is finished (summary, footer, the recorder's counters as metadata
``companion.recorder_stats``) when it reaches ``record.max_file_mb``; the oldest parts in the
directory are removed to keep it under ``record.max_total_mb``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

from companion.recording import codec

log = logging.getLogger("companion.recording")

PROFILE = ""  # MCAP profile: none (JSON messages with JSON Schemas; "ros1"/"ros2" do not apply)
LIBRARY = "uav-companion"
FILE_GLOB = "companion-*.mcap"
RECORDING_METADATA = "companion.recording"
CONFIG_METADATA = "companion.config"
STATS_METADATA = "companion.recorder_stats"
MB = 1_000_000
SIZE_CHECK_EVERY = 64  # messages between two looks at a part's size (a tell() each: a system call)


@dataclass
class _Part:
    path: Path
    file: Any
    writer: Writer
    channels: dict[str, int] = field(default_factory=dict)  # topic -> channel id
    messages: int = 0


class McapFiles:
    """The parts of one recording (a sink of the recorder; called from its writer thread only).
    OSError from any method: the disk is full or gone; the recorder stops using this sink."""

    name = "files"

    def __init__(self, settings: Any, directory: Path, recording_id: str, config_text: str, config_source: str,
                 files: dict[str, Path]) -> None:
        """``settings``: the ``record`` config section; ``files``: {config key: file} to copy in (read
        when the recording opens: the daemon passes the config's ``referenced``, filled as files load)."""
        self.settings = settings
        self.directory = directory
        self.id = recording_id
        self.started = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        self.parts: list[str] = []  # the files of this recording, in order
        self.removed: list[str] = []  # parts (of any recording) removed by the size cap
        self.bytes_written = 0
        self._config = {"yaml": config_text, "source": config_source}
        self._files = files
        self._attachments: dict[str, bytes] = {}
        self._part: _Part | None = None
        self._finished_bytes = 0
        self._stats: Callable[[], dict[str, Any]] = dict  # the recorder's counters, kept in each finished part

    @property
    def current(self) -> Path | None:
        return self._part.path if self._part is not None else None

    def open(self, stats: Callable[[], dict[str, Any]]) -> None:
        """Create the directory and the first part; ``stats`` gives the recorder's counters, kept in
        each part as it is finished."""
        self._stats = stats
        self._attachments = {key: path.read_bytes() for key, path in self._files.items() if path.is_file()}
        self.directory.mkdir(parents=True, exist_ok=True)
        self._open_part()

    def write(self, topic: str, schema: codec.ChannelSchema, data: bytes, log_ns: int, publish_ns: int) -> None:
        part = self._part
        if part is None:
            return
        channel = part.channels.get(topic)
        if channel is None:
            schema_id = part.writer.register_schema(schema.name, schema.encoding, schema.data)
            channel = part.channels[topic] = part.writer.register_channel(topic, schema.message_encoding, schema_id)
        part.writer.add_message(channel, log_time=log_ns, data=data, publish_time=publish_ns)
        part.messages += 1
        if part.messages % SIZE_CHECK_EVERY == 0:
            self._check_size()

    def flush(self) -> None:
        """Write the chunk in progress (what a crash from now on cannot take)."""
        if self._part is not None:
            self._part.writer.flush()
            self._check_size()

    def _check_size(self) -> None:
        """Count the bytes written; a part past ``record.max_file_mb`` is finished and the next begun."""
        size = self._part.file.tell()
        self.bytes_written = self._finished_bytes + size
        if size >= self.settings.max_file_mb * MB:
            self._finish_part()
            self._open_part()

    def close(self) -> None:
        """Finish the current part (summary, footer)."""
        self._finish_part()

    def abandon(self) -> None:
        """After a failed write: close the file as it is (readable up to its last whole chunk)."""
        part, self._part = self._part, None
        if part is not None:
            try:
                part.file.close()
            except OSError:
                pass

    def snapshot(self) -> dict[str, Any]:
        return {"bytes_written": self.bytes_written, "parts": list(self.parts), "removed": len(self.removed)}

    def _open_part(self) -> None:
        index = len(self.parts) + 1
        path = self.directory / f"companion-{self.started}-{self.id[:8]}-{index:04d}.mcap"
        file = open(path, "wb")
        writer = Writer(file, chunk_size=self.settings.chunk_kb * 1024, compression=CompressionType.ZSTD)
        writer.start(PROFILE, LIBRARY)
        writer.add_metadata(RECORDING_METADATA, {"id": self.id, "part": str(index), "started_utc": self.started})
        writer.add_metadata(CONFIG_METADATA, self._config)
        for key, data in self._attachments.items():
            writer.add_attachment(log_time=0, create_time=0, name=key, media_type="application/octet-stream", data=data)
        self._part = _Part(path, file, writer)
        self.parts.append(path.name)
        self._keep_under_cap()

    def _finish_part(self) -> None:
        part = self._part
        if part is None:
            return
        self._part = None
        part.writer.add_metadata(STATS_METADATA, {"snapshot": codec.dumps(self._stats()).decode()})
        part.writer.finish()
        part.file.close()
        self._finished_bytes += part.path.stat().st_size
        self.bytes_written = self._finished_bytes

    def _keep_under_cap(self) -> None:
        """Remove the oldest parts in the directory (of any recording, never the one being written)
        until the directory's recordings fit ``record.max_total_mb``."""
        cap = self.settings.max_total_mb * MB
        parts = sorted(self.directory.glob(FILE_GLOB))
        total = sum(p.stat().st_size for p in parts)
        for p in parts:
            if total <= cap:
                break
            if p == self.current:
                continue
            total -= p.stat().st_size
            p.unlink(missing_ok=True)
            self.removed.append(p.name)
            log.info("recorder: removed %s (record.max_total_mb %.0f)", p.name, self.settings.max_total_mb)
