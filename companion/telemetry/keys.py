"""The telemetry key space (the contract is docs/telemetry.md).

Every stream is published on ``uav/<sysid>/<stream>``, where ``sysid`` is the vehicle's
MAVLink system id (1..255). JSON payloads are objects carrying ``"v": SCHEMA_VERSION``,
``"t"`` (the daemon's monotonic clock in seconds when the message was produced) and the
stream's fields; ``scan`` is binary instead (companion/telemetry/scan_codec.py).
``SCHEMA_VERSION`` increases when a field is removed or changes meaning; adding a field, or a
stream with another encoding, does not change it.
"""

from __future__ import annotations

import re

SCHEMA_VERSION = 1
KEY_PREFIX = "uav"

STREAMS: tuple[str, ...] = (
    "pose",
    "velocity",
    "health",
    "rates",
    "link",
    "autopilot",
    "system",
    "mission",
    "setpoint",
    "estimate_stats",
    "alerts",
    "trajectory",
    "sources",
    "attitude_check",
    "scan",
    "lines",
    "corners",
    "map",
)

_STREAM_SET = frozenset(STREAMS)
_STREAM_NAME = re.compile(r"[a-z][a-z0-9_]{0,40}")


def is_stream_name(name: str) -> bool:
    """Whether ``name`` is spelled as a stream (a lower-case word: letters, digits, ``_``), as
    every one of :data:`STREAMS` is and a pipeline's own streams must be."""
    return _STREAM_NAME.fullmatch(name) is not None


def key(sysid: int, stream: str, extra: tuple[str, ...] = ()) -> str:
    """Key expression of one stream of one vehicle, e.g. ``key(1, "pose") == "uav/1/pose"``.
    ``extra``: streams allowed besides :data:`STREAMS` (those the pipelines declare), each a
    lower-case word (letters, digits, ``_``).

    Raises:
        ValueError: ``sysid`` outside 1..255 or ``stream`` neither in :data:`STREAMS` nor a valid name in ``extra``.
    """
    if isinstance(sysid, bool) or not isinstance(sysid, int) or not 1 <= sysid <= 255:
        raise ValueError(f"sysid must be an int in 1..255, got {sysid!r}")
    if stream not in _STREAM_SET and not (stream in extra and is_stream_name(stream)):
        raise ValueError(f"unknown telemetry stream {stream!r}; known: {', '.join(STREAMS)}")
    return f"{KEY_PREFIX}/{sysid}/{stream}"
