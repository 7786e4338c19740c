"""The binary encoding of the ``scan`` stream, schema ``uav.scan.v1`` (docs/telemetry.md).

A 1081-beam scan is 2.2 kB instead of ~15 kB of JSON. Little-endian, in this order:

====== ====== ==============================================================================
offset type   field
====== ====== ==============================================================================
0      u8     format version, 1
1      u16    ``count``: number of beams
3      f64    ``t``: the daemon clock (s) when the message was produced (the JSON envelope's t)
11     f64    ``t_capture``: first beam's capture time, daemon clock (s)
19     u32    ``sequence``: scan counter of the sensor (gaps are lost scans)
23     f32    ``sweep_s``: time from the first to the last beam (s)
27     f32    ``angle_min_rad``: first beam's angle in the sensor frame (companion/messages.py)
31     f32    ``angle_increment_rad``: beam i is at ``angle_min_rad + i * angle_increment_rad``
35     3xf32  ``mount``: the sensor in the body frame: x forward m, y right m, yaw rad
47     3xf32  ``pose``: the body in the world (LOCAL_NED) at capture: x north m, y east m, yaw
              rad, as the localizer fixed it for this scan; NaN x 3 when it had no pose
59     u8     ``n``: length of the sensor name
60     n      the sensor name, UTF-8
60+n   count  ranges, u16 millimetres; 0 = no valid return (out of range, no echo)
       x u16
====== ====== ==============================================================================

A beam's point in the levelled body frame is ``mount_xy + R(mount_yaw) (r cos a, r sin a)``
and in the world ``pose_xy + R(pose_yaw) (that)``, with ``R(psi) = [[cos, -sin], [sin, cos]]``
acting on (x, y); roll and pitch are not applied (a display approximation; the lines and
corners streams are levelled).
"""

from __future__ import annotations

import math
import struct
from typing import Any

import numpy as np

SCAN_SCHEMA = "uav.scan.v1"
SCAN_ENCODING = f"application/octet-stream;{SCAN_SCHEMA}"
FORMAT_VERSION = 1
MAX_RANGE_MM = 65535
ANGLE_TOLERANCE_RAD = 1e-5  # beam angles must be this close to a uniform spacing

_HEADER = struct.Struct("<BHddIfff3f3fB")


def encode_scan(t: float, payload: dict[str, Any]) -> bytes:
    """Pack one scan message; ``t`` is the envelope time (s, daemon clock).

    ``payload`` keys: ``sensor`` (str), ``t_capture`` (s), ``sequence`` (int), ``sweep_s``
    (s), ``angles_rad`` (N,) uniformly spaced, ``ranges_m`` (N,) metres, ``valid`` (N,) bool,
    ``mount`` (x m, y m, yaw rad), ``pose`` (x m, y m, yaw rad) or None. Ranges are rounded
    to the millimetre and capped at 65.535 m; invalid or non-finite ones become 0.

    Raises:
        ValueError: more than 65535 beams, a sensor name longer than 255 bytes, or angles that
            are not uniformly spaced.
    """
    angles = np.asarray(payload["angles_rad"], dtype=float)
    count = angles.shape[0]
    name = str(payload["sensor"]).encode()
    if count > 0xFFFF or len(name) > 0xFF:
        raise ValueError(f"scan too large to encode: {count} beams, sensor name of {len(name)} bytes")
    first = float(angles[0]) if count else 0.0
    step = float(angles[-1] - angles[0]) / (count - 1) if count > 1 else 0.0
    if count > 1 and np.max(np.abs(angles - (first + step * np.arange(count)))) > ANGLE_TOLERANCE_RAD:
        raise ValueError("scan angles are not uniformly spaced")
    ranges = np.asarray(payload["ranges_m"], dtype=float)
    ok = np.asarray(payload["valid"], dtype=bool) & np.isfinite(ranges)
    millimetres = np.where(ok, np.clip(np.rint(ranges * 1e3), 1, MAX_RANGE_MM), 0).astype("<u2")
    pose = payload["pose"] if payload["pose"] is not None else (math.nan,) * 3
    header = _HEADER.pack(FORMAT_VERSION, count, t, payload["t_capture"], payload["sequence"], payload["sweep_s"],
                          first, step, *payload["mount"], *pose, len(name))
    return header + name + millimetres.tobytes()


def decode_scan(data: bytes) -> dict[str, Any]:
    """Unpack a ``uav.scan.v1`` message into ``t``, ``sensor``, ``t_capture``, ``sequence``,
    ``sweep_s``, ``angle_min_rad``, ``angle_increment_rad``, ``mount`` [3], ``pose`` [3] or
    None, and ``ranges_mm`` ((count,) uint16, 0 = no return). Units as in the module docstring.

    Raises:
        ValueError: an unknown format version or a truncated message.
    """
    if len(data) < _HEADER.size:
        raise ValueError(f"scan message of {len(data)} bytes is shorter than its {_HEADER.size}-byte header")
    version, count, t, t_capture, sequence, sweep_s, first, step, *rest = _HEADER.unpack_from(data)
    if version != FORMAT_VERSION:
        raise ValueError(f"scan format version {version}, this decoder reads {FORMAT_VERSION}")
    mount, pose, name_length = rest[0:3], rest[3:6], rest[6]
    body = _HEADER.size + name_length
    if len(data) != body + 2 * count:
        raise ValueError(f"scan message of {len(data)} bytes, expected {body + 2 * count} for {count} beams")
    return {
        "t": t, "sensor": data[_HEADER.size:body].decode(errors="replace"), "t_capture": t_capture,
        "sequence": sequence, "sweep_s": sweep_s, "angle_min_rad": first, "angle_increment_rad": step,
        "mount": list(mount), "pose": None if any(math.isnan(v) for v in pose) else list(pose),
        "ranges_mm": np.frombuffer(data, dtype="<u2", count=count, offset=body),
    }
