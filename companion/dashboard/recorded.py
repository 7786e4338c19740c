"""A flight recording's telemetry as the dashboard plays it: an index in memory, the bytes read
when they are played.

Opening reads only each part's summary and the message indexes of its ``/telemetry/*``
channels (uncompressed, beside each chunk), so even a long recording opens in about a second
without decompressing its chunks (mostly sensor and MAVLink data). A message's bytes are read
from its chunk when it is played (the last few chunks are kept decompressed). A part without a
summary (cut by a crash, or still being written) is read whole instead, up to its last whole
record, its telemetry kept in memory. Times are seconds of the daemon clock (MCAP log time).
"""

from __future__ import annotations

import base64
import functools
import json
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import lz4.frame
import yaml
import zstandard
from mcap.exceptions import EndOfFile, McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader

from companion.recording.reader import Recording, RecordingError
from companion.recording.recorder import TELEMETRY_BINARY_SCHEMA, TELEMETRY_SCHEMA
from companion.telemetry.keys import KEY_PREFIX
from companion.telemetry.publisher import JSON_ENCODING

TOPIC_PREFIX = "/telemetry/"
JSON_SCHEMA = TELEMETRY_SCHEMA.name  # the message is the JSON zenoh carried
BINARY_SCHEMA = TELEMETRY_BINARY_SCHEMA.name  # {"t", "encoding", "base64": the bytes zenoh carried}
DEFAULT_SYSID = 1  # vehicle.sysid when the recorded config does not set it
CHUNKS_CACHED = 8
_CHUNK_HEAD = struct.Struct("<BQQQQI")  # opcode, length, start time, end time, uncompressed size, crc
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")  # opcode, length, channel, sequence, log time, publish time
_INDEX_HEAD = struct.Struct("<BQHI")  # opcode, length, channel, length of the entries


@dataclass(frozen=True, slots=True)
class TelemetryMessage:
    """One recorded telemetry message: where it was published, when, and where its bytes are."""

    t: float  # log time: the daemon clock when it was published (s)
    key: str  # uav/<sysid>/<stream>
    binary: bool  # recorded as companion.TelemetryBinary (encoding and base64 bytes), else the JSON itself
    data: bytes | None  # the recorded message data; None: in chunk ``chunk`` at ``offset``
    chunk: int  # -1: ``data`` holds it, ``offset`` counts the messages read whole before it
    offset: int

    @property
    def stream(self) -> str:
        return self.key.rsplit("/", 1)[1]


class RecordedTelemetry:
    """The telemetry of the recording ``path`` (any of its parts), in log-time order.

    Raises (at construction):
        RecordingError: not a companion recording, or a corrupt one.
        OSError: a part cannot be read.
    """

    def __init__(self, path: str | Path) -> None:
        self.recording = Recording.open(path)
        config = yaml.safe_load(self.recording.config_yaml) or {}
        vehicle = config.get("vehicle") if isinstance(config, dict) else None
        self.sysid = int((vehicle or {}).get("sysid", DEFAULT_SYSID))
        self._chunks: list[tuple[Path, int, int]] = []  # (part, chunk start offset, chunk length)
        self._read_whole_count = 0
        self._chunk_records = functools.lru_cache(maxsize=CHUNKS_CACHED)(self._read_chunk)
        messages: list[TelemetryMessage] = []
        for part in self.recording.parts:
            try:
                messages.extend(self._index(part))
            except (McapError, EOFError, ValueError, KeyError, struct.error) as exc:
                raise RecordingError(f"{part}: corrupt: {exc!r}") from exc
        messages.sort(key=lambda m: (m.t, m.chunk, m.offset))  # the messages of one instant in recorded order
        self.messages = messages

    def sample(self, message: TelemetryMessage) -> tuple[str, bytes]:
        """(zenoh encoding, the exact bytes zenoh carried) of ``message``."""
        data = message.data if message.data is not None else self._message_data(message.chunk, message.offset)
        if not message.binary:
            return JSON_ENCODING, data
        doc = json.loads(data)
        return doc["encoding"], base64.b64decode(doc["base64"])

    # -- opening ------------------------------------------------------------------------------

    def _key(self, topic: str) -> str:
        return f"{KEY_PREFIX}/{self.sysid}/{topic.removeprefix(TOPIC_PREFIX)}"

    def _index(self, part: Path) -> list[TelemetryMessage]:
        with open(part, "rb") as f:
            try:
                summary = make_reader(f).get_summary()
            except (McapError, EOFError, ValueError, struct.error):
                summary = None
            if summary is None or not summary.chunk_indexes:
                f.seek(0)
                return self._read_whole(f)
            schema_of = {cid: summary.schemas[c.schema_id].name if c.schema_id in summary.schemas else ""
                         for cid, c in summary.channels.items()}
            wanted = {cid: (self._key(c.topic), schema_of[cid] == BINARY_SCHEMA) for cid, c in summary.channels.items()
                      if c.topic.startswith(TOPIC_PREFIX) and schema_of[cid] in (JSON_SCHEMA, BINARY_SCHEMA)}
            out: list[TelemetryMessage] = []
            for ci in summary.chunk_indexes:
                offsets = {cid: o for cid, o in ci.message_index_offsets.items() if cid in wanted}
                if not offsets:
                    continue
                base = ci.chunk_start_offset + ci.chunk_length  # the chunk's message indexes follow it
                f.seek(base)
                block = f.read(ci.message_index_length)
                chunk = len(self._chunks)
                self._chunks.append((part, ci.chunk_start_offset, ci.chunk_length))
                for cid, o in offsets.items():
                    key, binary = wanted[cid]
                    opcode, _, channel, size = _INDEX_HEAD.unpack_from(block, o - base)
                    if opcode != 0x07 or channel != cid:
                        raise ValueError(f"no message index for channel {cid} at {o}")
                    entries = struct.unpack_from(f"<{size // 8}Q", block, o - base + _INDEX_HEAD.size)
                    out.extend(TelemetryMessage(entries[i] * 1e-9, key, binary, None, chunk, entries[i + 1])
                               for i in range(0, len(entries), 2))
            return out

    def _read_whole(self, f: BinaryIO) -> list[TelemetryMessage]:
        """Every telemetry message of a part without a summary, up to its last whole record."""
        schemas: dict[int, str] = {}
        channels: dict[int, tuple[str, str]] = {}
        out: list[TelemetryMessage] = []
        try:
            for record in StreamReader(f).records:
                if isinstance(record, Schema):
                    schemas[record.id] = record.name
                elif isinstance(record, Channel):
                    channels[record.id] = (record.topic, schemas.get(record.schema_id, ""))
                elif isinstance(record, Message):
                    topic, schema = channels[record.channel_id]
                    if topic.startswith(TOPIC_PREFIX) and schema in (JSON_SCHEMA, BINARY_SCHEMA):
                        out.append(TelemetryMessage(record.log_time * 1e-9, self._key(topic),
                                                    schema == BINARY_SCHEMA, bytes(record.data), -1,
                                                    self._read_whole_count))
                        self._read_whole_count += 1
        except EndOfFile:  # cut by a crash, or still being written
            pass
        return out

    # -- playing ------------------------------------------------------------------------------

    def _message_data(self, chunk: int, offset: int) -> bytes:
        records = self._chunk_records(chunk)
        opcode, length, *_ = _MESSAGE_HEAD.unpack_from(records, offset)
        if opcode != 0x05:
            raise RecordingError(f"no message at offset {offset} of chunk {chunk}")
        return records[offset + _MESSAGE_HEAD.size:offset + 9 + length]

    def _read_chunk(self, chunk: int) -> bytes:
        """The uncompressed records of a chunk (``_chunk_records``: the same, the last few kept)."""
        part, start, length = self._chunks[chunk]
        with open(part, "rb") as f:
            f.seek(start)
            raw = f.read(length)
        _, _, _, _, size, _ = _CHUNK_HEAD.unpack_from(raw)
        pos = _CHUNK_HEAD.size
        (name_length,) = struct.unpack_from("<I", raw, pos)
        compression = raw[pos + 4:pos + 4 + name_length].decode()
        pos += 4 + name_length
        (data_length,) = struct.unpack_from("<Q", raw, pos)
        data = raw[pos + 8:pos + 8 + data_length]
        if compression == "zstd":
            return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
        if compression == "lz4":
            return lz4.frame.decompress(data)
        if compression == "":
            return data
        raise RecordingError(f"{part}: chunk compression {compression!r} is not supported")

