"""Reading a flight recording (companion/recording/recorder.py) back: its parts in order, its
config and the files it named, and its messages in the order the daemon saw them.

A part cut by a crash or power loss (no summary, no footer, maybe half a chunk) is read record by
record up to its last whole chunk: :attr:`RecordedMessage` iteration stops there and the part is
listed in :attr:`Recording.truncated`.
"""

from __future__ import annotations

import json
import struct
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.exceptions import EndOfFile, McapError
from mcap.records import Attachment, Channel, Message, Metadata, Schema
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader

from companion.recording.mcap_files import CONFIG_METADATA, FILE_GLOB, RECORDING_METADATA, STATS_METADATA


class RecordingError(ValueError):
    """The file is not a companion recording, or not one that can be read."""


@dataclass(frozen=True)
class RecordedMessage:
    """One message: its topic, schema name, log time (daemon clock at recording, s) and its JSON
    document, decoded."""

    topic: str
    schema: str
    t: float
    doc: dict[str, Any]


@dataclass
class Recording:
    """A recording: the parts of one run of the daemon found next to the file it was opened from."""

    id: str
    parts: list[Path]
    config_yaml: str
    config_source: str
    attachments: dict[str, bytes] = field(default_factory=dict)  # {config key: file content}
    first_part: int = 1  # the index of the oldest part still on disk (1: the recording is whole at its start)
    truncated: list[Path] = field(default_factory=list)  # parts read to a cut (a crash), filled while iterating
    stats: dict[str, Any] = field(default_factory=dict)  # the recorder's snapshot when it finished ({}: cut by a crash)

    @classmethod
    def open(cls, path: str | Path) -> Recording:
        """The recording ``path`` (any of its parts) belongs to; RecordingError if it is not one."""
        path = Path(path)
        head = _head(path)
        info = head.get(RECORDING_METADATA)
        if info is None:
            raise RecordingError(f"{path}: not a companion recording (no {RECORDING_METADATA} metadata)")
        parts = [(int(info["part"]), path)]  # and its siblings (a renamed part stands alone)
        for candidate in sorted(path.parent.glob(FILE_GLOB)):
            meta = {} if candidate.samefile(path) else _head(candidate, quiet=True)
            if meta.get(RECORDING_METADATA, {}).get("id") == info["id"]:
                parts.append((int(meta[RECORDING_METADATA]["part"]), candidate))
        parts.sort()
        config = head.get(CONFIG_METADATA)
        if config is None:
            raise RecordingError(f"{path}: no {CONFIG_METADATA} metadata")
        recording = cls(id=info["id"], parts=[p for _, p in parts], config_yaml=config["yaml"],
                        config_source=config["source"], first_part=parts[0][0])
        recording.attachments = _attachments(recording.parts[0])
        recording.stats = _final_stats(recording.parts[-1])
        return recording

    def messages(self, topics: set[str] | None = None) -> Iterator[RecordedMessage]:
        """Every JSON message (of ``topics``, or all) in recorded order, part after part (the
        protobuf views for Foxglove, ``/sensors/<name>/laser_scan``, are left out)."""
        for part in self.parts:
            yield from self._read_part(part, topics)

    def _read_part(self, part: Path, topics: set[str] | None) -> Iterator[RecordedMessage]:
        schemas: dict[int, str] = {}
        channels: dict[int, tuple[str, str]] = {}
        with open(part, "rb") as f:
            try:
                for record in StreamReader(f).records:
                    if isinstance(record, Schema):
                        schemas[record.id] = record.name
                    elif isinstance(record, Channel) and record.message_encoding == "json":
                        channels[record.id] = (record.topic, schemas.get(record.schema_id, ""))
                    elif isinstance(record, Message) and record.channel_id in channels:
                        topic, schema = channels[record.channel_id]
                        if topics is None or topic in topics:
                            yield RecordedMessage(topic, schema, record.log_time * 1e-9, json.loads(record.data))
            except EndOfFile:  # cut short by a crash: read up to its last whole record
                self.truncated.append(part)
            except (McapError, ValueError, KeyError) as exc:
                raise RecordingError(f"{part}: corrupt: {exc!r}") from exc

    def materialise_config(self, directory: Path) -> Path:
        """Write the recorded config and the files it named into ``directory``; the config's path.
        Load it with :func:`companion.config.load_config` and pass :meth:`file_overrides`."""
        path = directory / "companion.yaml"
        path.write_text(self.config_yaml)
        return path

    def file_overrides(self, directory: Path) -> dict[str, Path]:
        """{config key: the recorded copy of its file}, written into ``directory``."""
        out = {}
        for i, (key, data) in enumerate(sorted(self.attachments.items())):
            name = Path(key.replace("/", "_")).name
            target = directory / f"{i:03d}-{name}"
            target.write_bytes(data)
            out[key] = target
        return out

    def temporary_directory(self) -> tempfile.TemporaryDirectory:
        return tempfile.TemporaryDirectory(prefix=f"replay-{self.id[:8]}-")


def _head(path: Path, quiet: bool = False) -> dict[str, dict[str, str]]:
    """{metadata name: metadata} from the start of a part (before its first message)."""
    found: dict[str, dict[str, str]] = {}
    try:
        with open(path, "rb") as f:
            for record in StreamReader(f).records:
                if isinstance(record, Metadata):
                    found[record.name] = dict(record.metadata)
                elif isinstance(record, (Message, Attachment, Channel)) and RECORDING_METADATA in found \
                        and CONFIG_METADATA in found:
                    break
    except (OSError, McapError, EOFError, ValueError) as exc:
        if quiet:
            return found
        if isinstance(exc, OSError):
            raise
        if not found:
            raise RecordingError(f"{path}: not an MCAP file: {exc}") from exc
    return found


def _final_stats(path: Path) -> dict[str, Any]:
    """The recorder's snapshot written when it finished ``path`` (from its summary); {} for a part
    cut by a crash (no summary)."""
    try:
        with open(path, "rb") as f:
            for record in make_reader(f).iter_metadata():
                if record.name == STATS_METADATA:
                    return json.loads(record.metadata.get("snapshot", "{}"))
    except (McapError, EOFError, ValueError, struct.error):
        pass
    return {}


def _attachments(path: Path) -> dict[str, bytes]:
    out: dict[str, bytes] = {}
    with open(path, "rb") as f:
        try:
            for record in StreamReader(f).records:
                if isinstance(record, Attachment):
                    out[record.name] = bytes(record.data)
                elif isinstance(record, Message):
                    break
        except (McapError, EOFError, ValueError):
            pass
    return out

