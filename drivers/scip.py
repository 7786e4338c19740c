"""Hokuyo SCIP 2.0 protocol: character encodings, sums, requests and replies. Pure, no I/O.

Wire format (SCIP 2.0 specification; urg_library ``src/urg_sensor.c``):

- A request is a 2-character command, fixed-width decimal parameters, an optional
  ``;tag`` (at most 16 characters, echoed back) and LF.
- A reply is the echo of the request, a status line (2 characters + sum byte), data lines
  (each followed by its sum byte) and an empty line: it always ends with ``LF LF`` and never
  contains an empty line before that, which is how a reader frames it.
- Sum byte of a line: ``chr((sum of its bytes & 0x3F) + 0x30)``. In ``KEY:VALUE;S`` lines
  (VV, PP, II) the ``;`` is not summed; like urg_library we accept either convention.
- Numbers in data are groups of 6 bits offset by 0x30, most significant first: 2 characters
  (12 bit, MS/GS ranges), 3 characters (18 bit, MD/GD ranges), 4 characters (24 bit,
  timestamps: milliseconds, wrapping after 2^24 ms = 4.66 h).
- Range data are cut into blocks of 64 characters, each on its own line with its sum byte.

Units here are the sensor's: ranges in millimetres, timestamps in milliseconds, angles in
Hokuyo steps (``ARES`` per turn, counted counter-clockwise seen from above). Conversion to
the sensor frame of :mod:`companion.messages` is :meth:`SensorParams.angle_rad`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

LF = b"\n"
BLOCK_CHARS = 64  # characters of range data per line
TIMESTAMP_MODULUS_MS = 1 << 24  # the sensor clock wraps here (about 4.66 hours)
MAX_TAG_CHARS = 16

QT = b"QT\n"
BM = b"BM\n"
VV = b"VV\n"
PP = b"PP\n"
II = b"II\n"
RS = b"RS\n"
SCIP20 = b"SCIP2.0\n"


# --- errors ---------------------------------------------------------------------------

class ScipProtocolError(Exception):
    """Bytes that are not a well-formed SCIP 2.0 reply."""


class ChecksumError(ScipProtocolError):
    """A line's sum byte does not match its contents."""


class TruncatedReply(ScipProtocolError):
    """A reply (or its range data) is shorter than its header announces."""


class ScipError(ScipProtocolError):
    """The sensor answered with an error status."""

    def __init__(self, command: str, status: str) -> None:
        self.command = command
        self.status = status
        self.meaning = status_meaning(command, status)
        super().__init__(f"{command} status {status}: {self.meaning}")


_COMMON_STATUS = {
    "0A": "unable to create transmission data or reply command internally",
    "0B": "buffer shortage or command repeated that is already processed",
    "0C": "command with insufficient parameters (1)",
    "0D": "undefined command (1)",
    "0E": "undefined command (2); also the answer to anything but TM in time-adjust mode",
    "0F": "command with insufficient parameters (2)",
    "0G": "string in command exceeds 16 letters",
    "0H": "string has invalid letters",
    "0I": "sensor is in firmware update mode",
}
_MEASURE_STATUS = {
    "01": "starting step has non-numeric value",
    "02": "end step has non-numeric value",
    "03": "cluster count has non-numeric value",
    "04": "end step is out of range",
    "05": "end step is smaller than starting step",
    "06": "scan interval has non-numeric value",
    "07": "number of scans has non-numeric value",
    "10": "laser is off",
}
_COMMAND_STATUS = {
    "MD": _MEASURE_STATUS, "MS": _MEASURE_STATUS, "GD": _MEASURE_STATUS, "GS": _MEASURE_STATUS,
    "BM": {"01": "unable to control due to laser malfunction", "02": "laser is already on"},
    "TM": {"01": "invalid control code", "02": "adjust mode on requested while already on",
           "03": "adjust mode off requested while already off",
           "04": "time requested while adjust mode is off"},
}


def status_meaning(command: str, status: str) -> str:
    """Human-readable meaning of ``status`` in the reply to ``command`` (e.g. "MD", "TM")."""
    if status in ("0", "00"):
        return "command received without error"
    if status == "99":
        return "measurement data follow"
    if status in _COMMON_STATUS:
        return _COMMON_STATUS[status]
    specific = _COMMAND_STATUS.get(command[:2], {})
    if status in specific:
        return specific[status]
    if status.isdigit():
        code = int(status)
        if 21 <= code <= 49:
            return "processing stopped to verify an error"
        if 50 <= code <= 97:
            return "hardware trouble (laser, motor or similar malfunction)"
        if code == 98:
            return "processing resumed after confirming normal laser operation"
    return "unknown status"


# --- sums and encodings ---------------------------------------------------------------

def sum_byte(data: bytes) -> int:
    """The SCIP sum byte of ``data``: (sum of bytes & 0x3F) + 0x30."""
    return (sum(data) & 0x3F) + 0x30


def check_line(line: bytes) -> bytes:
    """The payload of ``line`` (without LF) after checking its trailing sum byte.

    ``KEY:VALUE;S`` lines pass whether or not the sensor summed the ``;``.
    """
    if len(line) < 2:
        raise TruncatedReply(f"line too short for a sum byte: {line!r}")
    payload, got = line[:-1], line[-1]
    if got == sum_byte(payload):
        return payload
    if payload.endswith(b";") and got == sum_byte(payload[:-1]):
        return payload
    raise ChecksumError(f"bad sum byte {chr(got)!r} (expected {chr(sum_byte(payload))!r}) in {line[:24]!r}")


def encode(value: int, width: int) -> bytes:
    """``value`` in ``width`` (2, 3 or 4) SCIP characters, e.g. ``encode(1234, 2) == b"CB"``."""
    if not 0 <= value < 1 << (6 * width):
        raise ValueError(f"{value} does not fit in {width} SCIP characters")
    return bytes(((value >> (6 * (width - 1 - i))) & 0x3F) + 0x30 for i in range(width))


def decode(chars: bytes) -> int:
    """The number encoded by ``chars`` (any width), e.g. ``decode(b"1Dh") == 5432``."""
    value = 0
    for c in chars:
        if not 0x30 <= c <= 0x6F:
            raise ScipProtocolError(f"invalid SCIP character {chr(c)!r}")
        value = (value << 6) | (c - 0x30)
    return value


def encode_array(values: np.ndarray, width: int) -> bytes:
    """Vectorised :func:`encode` of a 1-D integer array, concatenated."""
    v = np.asarray(values, dtype=np.int64)
    if v.size and (v.min() < 0 or v.max() >= 1 << (6 * width)):
        raise ValueError(f"values outside 0 .. {(1 << (6 * width)) - 1} for {width} SCIP characters")
    shifts = 6 * np.arange(width - 1, -1, -1)
    chars = ((v[:, None] >> shifts) & 0x3F) + 0x30
    return chars.astype(np.uint8).tobytes()


def decode_array(chars: bytes | np.ndarray, width: int) -> np.ndarray:
    """Vectorised :func:`decode` of concatenated ``width``-character numbers -> int64 array
    (``chars``: bytes, or a uint8 array of them)."""
    c = np.frombuffer(chars, dtype=np.uint8) if isinstance(chars, bytes) else chars
    if c.size % width:
        raise TruncatedReply(f"{c.size} data characters is not a multiple of {width}")
    digits = c - np.uint8(0x30)  # wraps below '0': one test catches both ends
    if c.size and digits.max() > 0x3F:
        raise ScipProtocolError("invalid SCIP character in data")
    columns = digits.reshape(-1, width).astype(np.int64)
    value = columns[:, 0]
    for i in range(1, width):
        value = (value << 6) | columns[:, i]
    return value


def decode_data_lines(lines: Sequence[bytes], width: int) -> np.ndarray:
    """Check the sum of every data line (64-character blocks), join them and decode.

    ``lines`` are the data lines of one reply without LF, each ending in its sum byte.
    Raises :class:`ChecksumError` naming the first bad line.
    """
    if not lines:
        return decode_array(b"", width)
    lengths = tuple(map(len, lines))
    if min(lengths) < 2:
        raise TruncatedReply("empty data line")
    starts, sum_bytes, payload = _line_layout(lengths)
    joined = np.frombuffer(b"".join(lines), dtype=np.uint8)
    totals = np.add.reduceat(joined, starts, dtype=np.int64)  # payload + sum byte
    got = joined[sum_bytes]
    bad = np.flatnonzero(((totals - got) & 0x3F) + 0x30 != got)
    if bad.size:
        raise ChecksumError(f"bad sum byte in data line {int(bad[0]) + 1} of {len(lines)}")
    return decode_array(joined[payload], width)


@lru_cache(maxsize=16)
def _line_layout(lengths: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where lines of these ``lengths`` (bytes, sum byte included) lie once joined: index arrays
    of every line's first byte, of its sum byte, and of the payload bytes. Cached: the replies of
    one stream all share a layout (building it was about a sixth of a parse)."""
    ends = np.cumsum(lengths)  # one past each line's sum byte
    sum_bytes = ends - 1
    payload = np.ones(int(ends[-1]), dtype=bool)
    payload[sum_bytes] = False
    layout = (ends - np.asarray(lengths), sum_bytes, np.flatnonzero(payload))
    for array in layout:
        array.setflags(write=False)
    return layout


# --- requests ---------------------------------------------------------------------------

def request(command: str, params: str = "", tag: str = "") -> bytes:
    """A request line: command, parameters, optional ``;tag`` (<= 16 printable chars), LF."""
    if len(tag) > MAX_TAG_CHARS or any(not (0x20 < ord(c) < 0x7F) or c == ";" for c in tag):
        raise ValueError(f"invalid SCIP tag {tag!r}: at most 16 printable characters, no ';'")
    return f"{command}{params}{';' + tag if tag else ''}\n".encode("ascii")


def _steps(start: int, end: int, cluster: int) -> str:
    if not (0 <= start <= end <= 9999 and 0 <= cluster <= 99):
        raise ValueError(f"invalid step range {start}..{end} / cluster {cluster}")
    return f"{start:04d}{end:04d}{cluster:02d}"


def md_request(start: int, end: int, cluster: int = 1, interval: int = 0, scans: int = 0,
               *, two_char: bool = False, tag: str = "") -> bytes:
    """MD (3-character ranges) or MS (2-character) request; ``scans=0`` streams until QT."""
    if not (0 <= interval <= 9 and 0 <= scans <= 99):
        raise ValueError(f"invalid scan interval {interval} / number of scans {scans}")
    command = "MS" if two_char else "MD"
    return request(command, f"{_steps(start, end, cluster)}{interval:01d}{scans:02d}", tag)


def gd_request(start: int, end: int, cluster: int = 1, *, two_char: bool = False, tag: str = "") -> bytes:
    """GD (3-character ranges) or GS (2-character) request for the latest scan (needs BM)."""
    return request("GS" if two_char else "GD", _steps(start, end, cluster), tag)


def tm_request(control: int, tag: str = "") -> bytes:
    """TM0 (adjust mode on), TM1 (read the sensor clock), TM2 (adjust mode off)."""
    if control not in (0, 1, 2):
        raise ValueError(f"TM control code must be 0, 1 or 2, got {control}")
    return request("TM", str(control), tag)


# --- replies ----------------------------------------------------------------------------

@dataclass(frozen=True)
class Reply:
    """One reply split into lines. ``lines`` exclude echo and status, sums still attached."""

    echo: bytes  # the echoed request, without LF
    status: str  # "00", "99", ... (SCIP 1.1 answers carry a 1-character status such as "E")
    lines: tuple[bytes, ...]

    @property
    def command(self) -> str:
        """The echoed command: "SCIP2.0" or its first two characters."""
        return "SCIP2.0" if self.echo.startswith(b"SCIP2.0") else self.echo[:2].decode("ascii", "replace")

    def raise_for_status(self, ok: Iterable[str] = ("00",)) -> None:
        """Raise :class:`ScipError` unless the status is one of ``ok``."""
        if self.status not in ok:
            raise ScipError(self.command, self.status)


def split_reply(raw: bytes) -> Reply:
    """Split one reply (everything up to and including its ``LF LF``), checking the status sum."""
    if not raw.endswith(b"\n\n"):
        raise TruncatedReply(f"reply does not end with an empty line: {raw[-24:]!r}")
    lines = raw[:-2].split(LF)
    if len(lines) < 2:
        raise TruncatedReply(f"reply without a status line: {raw[:24]!r}")
    echo, status_line, rest = lines[0], lines[1], tuple(lines[2:])
    if len(status_line) == 1:  # SCIP 1.1: one status character, no sum
        return Reply(echo, status_line.decode("ascii", "replace"), rest)
    if len(status_line) != 3:
        raise ScipProtocolError(f"malformed status line {status_line!r}")
    return Reply(echo, check_line(status_line).decode("ascii", "replace"), rest)


@dataclass(frozen=True)
class DistanceEcho:
    """The parameters echoed by MD/MS (15 characters) or GD/GS (12 characters)."""

    command: str  # "MD", "MS", "GD" or "GS"
    start: int
    end: int
    cluster: int
    interval: int = 0  # MD/MS only
    scans: int = 0  # MD/MS only: remaining scans ("00" while streaming forever)

    @property
    def width(self) -> int:
        """Characters per range value: 2 for MS/GS, 3 for MD/GD."""
        return 2 if self.command[1] == "S" else 3

    @property
    def values(self) -> int:
        """Number of range values in one scan: steps start..end grouped by ``cluster``."""
        return math.ceil((self.end - self.start + 1) / max(self.cluster, 1))


def parse_distance_echo(echo: bytes) -> DistanceEcho:
    """Parse the echo line of an MD/MS/GD/GS reply (a ``;tag`` is ignored)."""
    text = echo.split(b";", 1)[0].decode("ascii", "replace")
    command = text[:2]
    expected = 15 if command in ("MD", "MS") else 12 if command in ("GD", "GS") else 0
    if len(text) != expected or not text[2:].isdigit():
        raise ScipProtocolError(f"not a distance echo: {echo!r}")
    start, end, cluster = int(text[2:6]), int(text[6:10]), int(text[10:12])
    if expected == 12:
        return DistanceEcho(command, start, end, cluster)
    return DistanceEcho(command, start, end, cluster, int(text[12]), int(text[13:15]))


@dataclass(frozen=True)
class DistanceData:
    """One scan of range data from an MD/MS/GD/GS reply."""

    echo: DistanceEcho
    timestamp_ms: int  # the sensor's 24-bit millisecond clock at the scan's step 0
    ranges_mm: np.ndarray  # (echo.values,) int64; values below DMIN are error codes


def parse_distance_data(reply: Reply) -> DistanceData:
    """Timestamp and ranges of a data reply (MD/MS status 99, GD/GS status 00).

    Raises ScipError for another status, ChecksumError for any bad line and TruncatedReply
    when fewer values arrive than the echo announces.
    """
    echo = parse_distance_echo(reply.echo)
    reply.raise_for_status(("99",) if echo.command[0] == "M" else ("00",))
    if not reply.lines:
        raise TruncatedReply("data reply without a timestamp")
    stamp = check_line(reply.lines[0])
    if len(stamp) != 4:
        raise ScipProtocolError(f"malformed timestamp line {reply.lines[0]!r}")
    ranges = decode_data_lines(reply.lines[1:], echo.width)
    if ranges.size < echo.values:
        raise TruncatedReply(f"{ranges.size} of {echo.values} range values")
    if ranges.size > echo.values:
        raise ScipProtocolError(f"{ranges.size} range values, {echo.values} expected")
    return DistanceData(echo, decode(stamp), ranges)


def parse_timestamp_reply(reply: Reply) -> int:
    """The sensor clock (ms, 24 bit) from a TM1 reply."""
    reply.raise_for_status()
    if len(reply.lines) != 1:
        raise TruncatedReply(f"TM1 reply with {len(reply.lines)} data lines")
    stamp = check_line(reply.lines[0])
    if len(stamp) != 4:
        raise ScipProtocolError(f"malformed TM1 time {reply.lines[0]!r}")
    return decode(stamp)


def parse_info(reply: Reply) -> dict[str, str]:
    """``KEY:VALUE`` lines of a VV/PP/II reply as a dict (sums checked, both conventions)."""
    reply.raise_for_status()
    fields: dict[str, str] = {}
    for line in reply.lines:
        payload = check_line(line).rstrip(b";").decode("ascii", "replace")
        key, sep, value = payload.partition(":")
        if not sep:
            raise ScipProtocolError(f"not a KEY:VALUE line: {line!r}")
        fields[key] = value
    return fields


# --- reply formatting (the emulator's side) -----------------------------------------------

def format_line(payload: bytes) -> bytes:
    """``payload`` + sum byte + LF (a status, timestamp or data line)."""
    return payload + bytes((sum_byte(payload),)) + LF


def format_info_line(key: str, value: str) -> bytes:
    """``KEY:VALUE;S`` + LF with the sum over ``KEY:VALUE`` (the specification's convention)."""
    payload = f"{key}:{value}".encode("ascii")
    return payload + b";" + bytes((sum_byte(payload),)) + LF


def format_data_lines(values: np.ndarray, width: int) -> bytes:
    """Range values encoded and cut into 64-character lines, each with its sum byte and LF."""
    chars = encode_array(values, width)
    return b"".join(format_line(chars[i:i + BLOCK_CHARS]) for i in range(0, len(chars), BLOCK_CHARS))


def format_reply(echo: bytes, status: str, body: bytes = b"") -> bytes:
    """A complete reply: echo LF, status + sum LF, ``body`` (formatted lines), LF."""
    return echo + LF + format_line(status.encode("ascii")) + body + LF


# --- sensor description -------------------------------------------------------------------

@dataclass(frozen=True)
class SensorParams:
    """What a PP reply says about a sensor. Distances in mm, angles in steps."""

    model: str  # MODL, e.g. "UTM-30LX" or "URG-04LX(Hokuyo Automatic Co., Ltd.)"
    dmin_mm: int  # DMIN: shorter values are error codes
    dmax_mm: int  # DMAX: longest range the sensor reports
    ares: int  # ARES: steps per full turn
    amin: int  # AMIN: first measurable step
    amax: int  # AMAX: last measurable step
    afrt: int  # AFRT: step along the sensor's front (sensor-frame x)
    scan_rpm: int  # SCAN: standard motor speed, one scan per turn

    @classmethod
    def from_pp(cls, fields: dict[str, str]) -> SensorParams:
        """From :func:`parse_info` of a PP reply; ScipProtocolError if a field is missing."""
        try:
            return cls(fields["MODL"], int(fields["DMIN"]), int(fields["DMAX"]), int(fields["ARES"]),
                       int(fields["AMIN"]), int(fields["AMAX"]), int(fields["AFRT"]), int(fields["SCAN"]))
        except (KeyError, ValueError) as exc:
            raise ScipProtocolError(f"incomplete PP reply {fields}: {exc}") from exc

    def pp_fields(self) -> dict[str, str]:
        """The PP reply fields, in the order a sensor sends them."""
        return {"MODL": self.model, "DMIN": str(self.dmin_mm), "DMAX": str(self.dmax_mm),
                "ARES": str(self.ares), "AMIN": str(self.amin), "AMAX": str(self.amax),
                "AFRT": str(self.afrt), "SCAN": str(self.scan_rpm)}

    @property
    def steps(self) -> int:
        """Number of measurable steps (AMIN..AMAX inclusive)."""
        return self.amax - self.amin + 1

    @property
    def step_rad(self) -> float:
        """Angle between neighbouring steps, radians."""
        return 2 * math.pi / self.ares

    @property
    def scan_period_s(self) -> float:
        """One turn of the mirror, s (one scan)."""
        return 60.0 / self.scan_rpm

    @property
    def step_time_s(self) -> float:
        """Time the mirror takes from one step to the next, s."""
        return self.scan_period_s / self.ares

    def angle_rad(self, steps: np.ndarray | float) -> np.ndarray | float:
        """Sensor-frame angle of (possibly fractional) steps: -(step - AFRT) * 2 pi / ARES.

        Positive angles turn from the front to the right (:mod:`companion.messages`); Hokuyo steps
        count counter-clockwise seen from above, so the first step is on the right.
        """
        return -(np.asarray(steps, dtype=float) - self.afrt) * self.step_rad

    def beam_steps(self, start: int, end: int, cluster: int = 1) -> np.ndarray:
        """Centre step of each value of a start..end scan grouped by ``cluster`` steps."""
        c = max(cluster, 1)
        first = np.arange(start, end + 1, c, dtype=float)
        last = np.minimum(first + c - 1, end)
        return (first + last) / 2
