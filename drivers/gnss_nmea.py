"""A GNSS receiver speaking NMEA 0183 on a serial port: ``kind: gnss, backend: nmea``.

Lines are read without blocking the event loop (pyserial opens and configures the port in a
worker thread, then ``loop.add_reader`` reads its descriptor), checked and parsed with pynmea2.
A line that is not a sentence, has a bad or missing checksum, is not ASCII, is longer than
:data:`MAX_LINE` or has a field that does not decode raises CorruptFrame (the frontend counts it
and reads on); a well-formed sentence of a type not used here (GSV, GLL, TXT, proprietary) is
skipped quietly.

The sentences of one epoch are combined into one :class:`~companion.messages.GnssFix`:

- GGA (required): position (WGS-84 degrees), altitude above mean sea level (m), satellites in
  use, fix quality: 0 no fix, 1 GPS and 3 PPS a 3-D fix, 2 DGPS, 4 RTK fixed, 5 RTK float
  (MAVLink GPS_FIX_TYPE numbers); 6 (dead reckoning), 7 (manual) and 8 (simulation) are not
  measurements: no fix (its position fields 0). A GGA without a time (a receiver that has not
  found one yet) is a no-fix report on its own;
- GSA: its fix mode 1 (no fix) or 2 (2-D) lowers the fix type to that;
- RMC (else VTG): ground speed and course over ground (degrees from true north, clockwise)
  give north = v cos(course), east = v sin(course), m/s. NMEA carries no vertical velocity, so
  down is NaN: "not measured": use the velocity horizontally only. Given only with a
  3-D fix or better and a valid RMC (status A) / VTG (mode not N);
- GST: 1-sigma errors; horizontal accuracy = sqrt(sigma_lat^2 + sigma_lon^2) (as ArduPilot's
  NMEA driver), vertical = sigma_alt, m. No velocity accuracy in NMEA: None. ``jamming`` False.

An epoch is the UTC time field of GGA, RMC and GST; GSA and VTG carry none and join the epoch
whose timed sentence came before them (dropped if that epoch was already handed out). An epoch
is handed out as soon as it holds every sentence type expected, else when a sentence with the
next time starts a new epoch: the first epoch and one that lost a sentence come one epoch late.
The expected types are learnt from the receiver's output: those of the first epoch, then those
of the second of two epochs in a row that ended incomplete (its output changed; one alone lost
a sentence), plus any type that arrives after its epoch was handed out. A fix's ``t_capture``
is the arrival of the first byte of its epoch's first sentence on the daemon clock, minus
``latency_s``.

No fix for ``timeout_s`` (the receiver silent, or sending nothing decodable: a wrong baud rate
shows as corrupt frames), a read error or a port that closes (unplugged) raise DeviceLost; a
port that cannot be opened raises OSError (pyserial's SerialException): the frontend reopens
it with backoff.
"""

from __future__ import annotations

import asyncio
import datetime
import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pynmea2
import serial

from companion.messages import GNSS_2D, GNSS_3D, GNSS_DGPS, GNSS_NO_FIX, GNSS_RTK_FIXED, GNSS_RTK_FLOAT, GnssFix
from companion.plugins import register_backend
from companion.schema import meta
from drivers.base import Backend, CorruptFrame, DeviceLost
from drivers.serial_fd import SerialFd

MAX_LINE = 120  # bytes; NMEA allows 82, some receivers' proprietary sentences are longer
QUEUE_LINES = 1000  # lines read but not yet decoded: many epochs of a 10 Hz receiver
READ_BYTES = 4096
KNOT_MPS = 1852.0 / 3600.0
KMPH_MPS = 1.0 / 3.6
QUALITY_FIX = {0: GNSS_NO_FIX, 1: GNSS_3D, 2: GNSS_DGPS, 3: GNSS_3D, 4: GNSS_RTK_FIXED, 5: GNSS_RTK_FLOAT}


@dataclass
class NmeaGnssSettings:
    """``settings:`` of a gnss with ``backend: nmea``."""

    port: str = field(metadata=meta("Serial device of the receiver, e.g. /dev/ttyUSB0 or /dev/serial/by-id/..."))
    baud: int = field(default=9600, metadata=meta(
        "Serial bit rate: 9600 is most receivers' factory setting; 5-10 Hz output needs 38400 or more.",
        (1200, 921600)))
    latency_s: float = field(default=0.0, metadata=meta(
        "Subtracted from the arrival of an epoch's first byte to give its capture time: the receiver's delay "
        "from the measurement epoch to its first sentence, seconds.", (0.0, 1.0)))
    timeout_s: float = field(default=3.0, metadata=meta(
        "No fix (GGA) for this long: the receiver is lost (reopened), seconds. More than two output periods.",
        (0.2, 30.0)))


# --- sentences: decoded fields --------------------------------------------------------------

@dataclass(frozen=True)
class _Position:
    """What one GGA says: MAVLink fix type from its quality, WGS-84 degrees, m above mean sea level."""

    fix_type: int
    lat_deg: float = 0.0
    lon_deg: float = 0.0
    alt_m: float = 0.0
    satellites: int | None = None


def _float(value: Any, what: str) -> float | None:
    """``value`` (a pynmea2 field: number, numeric string, '' or None) as a finite float, or None."""
    if value is None or value == "":
        return None
    number = float(value)
    if not math.isfinite(number):
        raise ValueError(f"{what} is {value!r}")
    return number


def _position(gga: pynmea2.GGA) -> _Position:
    fix_type = QUALITY_FIX.get(int(gga.gps_qual or 0), GNSS_NO_FIX)
    satellites = None if gga.num_sats in ("", None) else int(gga.num_sats)
    if fix_type == GNSS_NO_FIX:
        return _Position(fix_type, satellites=satellites)
    if not (gga.lat and gga.lon and gga.lat_dir in ("N", "S") and gga.lon_dir in ("E", "W")):
        raise ValueError(f"GGA fix (quality {gga.gps_qual}) without a latitude or longitude")
    alt = _float(gga.altitude, "altitude")
    if alt is None or gga.altitude_units != "M":
        raise ValueError(f"GGA fix without an altitude in metres ({gga.altitude!r} {gga.altitude_units!r})")
    lat, lon = float(gga.latitude), float(gga.longitude)
    if not (abs(lat) <= 90.0 and abs(lon) <= 180.0):
        raise ValueError(f"GGA latitude {lat} or longitude {lon} out of range")
    return _Position(fix_type, lat, lon, alt, satellites)


def _horizontal_velocity(speed_mps: float | None, course_deg: float | None) -> tuple[float, float] | None:
    """North, east from ground speed (m/s) and course over ground (degrees from true north, clockwise)."""
    if speed_mps is None or course_deg is None:
        return None
    course = math.radians(course_deg)
    return speed_mps * math.cos(course), speed_mps * math.sin(course)


def _rmc_velocity(rmc: pynmea2.RMC) -> tuple[float, float] | None:
    if rmc.status != "A" or rmc.mode_indicator == "N":
        return None
    speed = _float(rmc.spd_over_grnd, "RMC speed")
    return _horizontal_velocity(None if speed is None else speed * KNOT_MPS, _float(rmc.true_course, "RMC course"))


def _vtg_velocity(vtg: pynmea2.VTG) -> tuple[float, float] | None:
    if vtg.faa_mode == "N":
        return None
    speed = _float(vtg.spd_over_grnd_kmph, "VTG speed")
    return _horizontal_velocity(None if speed is None else speed * KMPH_MPS, _float(vtg.true_track, "VTG course"))


def _accuracy(gst: pynmea2.GST) -> tuple[float | None, float | None]:
    """Horizontal and vertical 1-sigma position accuracy, m (None: not given)."""
    lat = _float(gst.std_dev_latitude, "GST latitude error")
    lon = _float(gst.std_dev_longitude, "GST longitude error")
    return (None if lat is None or lon is None else math.hypot(lat, lon)), _float(gst.std_dev_altitude, "GST altitude error")


def _gsa_mode(gsa: pynmea2.GSA) -> int | None:
    return None if gsa.mode_fix_type in ("", None) else int(gsa.mode_fix_type)


DECODERS = {"GGA": _position, "RMC": _rmc_velocity, "VTG": _vtg_velocity, "GST": _accuracy, "GSA": _gsa_mode}
TIMED = ("GGA", "RMC", "GST")


def parse_line(raw: bytes) -> pynmea2.TalkerSentence | None:
    """The sentence on one line (None: a blank line or a sentence type not used here); CorruptFrame
    for anything that is not a well-formed sentence with a good checksum."""
    text = raw.strip()
    if not text:
        return None
    if len(text) > MAX_LINE or not text.startswith(b"$"):
        raise CorruptFrame(f"not an NMEA sentence: {text[:40]!r}")
    try:
        sentence = pynmea2.parse(text.decode("ascii"), check=True)
    except pynmea2.SentenceTypeError:
        return None
    except (UnicodeDecodeError, ValueError) as exc:  # pynmea2's ParseError and ChecksumError are ValueErrors
        raise CorruptFrame(f"{exc}: {text[:40]!r}") from None
    if not isinstance(sentence, pynmea2.TalkerSentence) or sentence.sentence_type not in DECODERS:
        return None
    return sentence


# --- epochs -----------------------------------------------------------------------------------

@dataclass
class _Epoch:
    utc: datetime.time
    t_first: float  # daemon clock, s: arrival of the first byte of its first sentence
    parts: dict[str, Any] = field(default_factory=dict)  # sentence type -> decoded fields (first one wins)


class EpochAssembler:
    """Combines the sentences of each epoch into one GnssFix (see the module docstring)."""

    def __init__(self, receiver_id: str, latency_s: float) -> None:
        self.receiver_id = receiver_id
        self.latency_s = latency_s
        self._epoch: _Epoch | None = None
        self._expected: set[str] | None = None  # the sentence types an epoch is complete with
        self._ended_incomplete = False  # the last epoch was ended by the next one's start
        self._handed_out: datetime.time | None = None  # UTC of the last epoch ended

    def feed(self, t: float, sentence: pynmea2.TalkerSentence) -> list[GnssFix]:
        """Add ``sentence`` (its first byte arrived at daemon time ``t``, s); the fixes now complete.
        ValueError if a field does not decode (the sentence is then not used)."""
        kind = sentence.sentence_type
        value = DECODERS[kind](sentence)
        fixes: list[GnssFix] = []
        if kind in TIMED:
            utc = sentence.timestamp
            if utc is None:
                if kind == "GGA":  # a receiver without a time has no fix either
                    fixes += self._hand_out()
                    fixes.append(self._fix(t, {kind: _Position(GNSS_NO_FIX, satellites=value.satellites)}))
                return fixes
            if self._epoch is not None and self._epoch.utc != utc:  # it ended without every expected type
                first = self._expected is None
                if first or self._ended_incomplete:  # twice in a row: the receiver's output changed
                    self._expected = set(self._epoch.parts)
                self._ended_incomplete = not first  # (once: a lost sentence, expected as before)
                fixes += self._hand_out()
            if self._epoch is None and utc != self._handed_out:
                self._epoch = _Epoch(utc, t)
        if self._epoch is None:  # late for the epoch handed out: waited for from the next one on
            if self._expected is not None:
                self._expected.add(kind)
            return fixes
        self._epoch.parts.setdefault(kind, value)
        if self._expected is not None and "GGA" in self._epoch.parts and self._expected <= self._epoch.parts.keys():
            self._ended_incomplete = False
            fixes += self._hand_out()
        return fixes

    def _hand_out(self) -> list[GnssFix]:
        epoch, self._epoch = self._epoch, None
        if epoch is None:
            return []
        self._handed_out = epoch.utc
        return [self._fix(epoch.t_first, epoch.parts)] if "GGA" in epoch.parts else []

    def _fix(self, t_first: float, parts: dict[str, Any]) -> GnssFix:
        position: _Position = parts["GGA"]
        fix_type = position.fix_type
        if fix_type != GNSS_NO_FIX and parts.get("GSA") in (GNSS_NO_FIX, GNSS_2D):
            fix_type = parts["GSA"]
        horizontal = parts.get("RMC") or parts.get("VTG")
        velocity = None if horizontal is None or fix_type < GNSS_3D else np.array([*horizontal, math.nan])
        h_acc, v_acc = parts.get("GST", (None, None))
        return GnssFix(self.receiver_id, t_first - self.latency_s, fix_type, position.lat_deg, position.lon_deg,
                       position.alt_m, velocity, h_acc, v_acc, None, position.satellites)


# --- the port ---------------------------------------------------------------------------------

class _SerialLines:
    """A serial port read through ``loop.add_reader``: its lines, each with the daemon time (s) at
    which its first byte was read (at most QUEUE_LINES waiting: a stalled reader loses the oldest).
    A read error or end of file ends it with DeviceLost."""

    def __init__(self, port: serial.SerialBase) -> None:
        self._loop = asyncio.get_running_loop()
        self._lines: deque[tuple[float, bytes]] = deque(maxlen=QUEUE_LINES)
        self._partial = bytearray()
        self._partial_t = 0.0
        self._error: DeviceLost | None = None
        self._ready = asyncio.Event()
        self._serial = SerialFd(port, "receiver", self._on_data, self._fail, READ_BYTES)

    @classmethod
    async def open(cls, path: str, baud: int) -> _SerialLines:
        port = await SerialFd.open_port(path, baud)
        try:
            return cls(port)
        except BaseException:
            port.close()
            raise

    def _on_data(self, data: bytes) -> None:
        now = self._loop.time()
        *complete, rest = data.split(b"\n")
        for piece in complete:
            self._add(now, piece)
            self._lines.append((self._partial_t, bytes(self._partial)))
            self._partial.clear()
        self._add(now, rest)
        if len(self._partial) > MAX_LINE:  # no line end in sight: hand it on to be refused
            self._lines.append((self._partial_t, bytes(self._partial)))
            self._partial.clear()
        self._ready.set()

    def _add(self, now: float, piece: bytes) -> None:
        if piece and not self._partial:
            self._partial_t = now
        self._partial += piece

    def _fail(self, error: DeviceLost) -> None:
        self._error = error
        self._ready.set()

    async def next(self, deadline: float) -> tuple[float, bytes]:
        """The next line and the arrival of its first byte; TimeoutError at daemon time ``deadline``."""
        while not self._lines:
            if self._error is not None:
                raise self._error
            self._ready.clear()
            await asyncio.wait_for(self._ready.wait(), max(0.0, deadline - self._loop.time()))
        return self._lines.popleft()

    def close(self) -> None:
        self._serial.close()


class NmeaGnss(Backend[GnssFix]):
    """A serial NMEA 0183 receiver; one GnssFix per epoch."""

    def __init__(self, settings: NmeaGnssSettings, receiver_id: str) -> None:
        self.settings = settings
        self.receiver_id = receiver_id
        self.description = f"NMEA receiver on {settings.port}"
        self._lines: _SerialLines | None = None
        self._assembler = EpochAssembler(receiver_id, settings.latency_s)
        self._fixes: deque[GnssFix] = deque()
        self._deadline = 0.0  # daemon clock, s: no fix by then means the receiver is lost

    async def open(self) -> None:
        await self.close()
        self._lines = await _SerialLines.open(self.settings.port, self.settings.baud)
        self._assembler = EpochAssembler(self.receiver_id, self.settings.latency_s)
        self._fixes.clear()
        self._deadline = asyncio.get_running_loop().time() + self.settings.timeout_s

    async def read(self) -> GnssFix:
        if self._lines is None:
            raise DeviceLost("not open")
        while not self._fixes:
            try:
                t, raw = await self._lines.next(self._deadline)
            except TimeoutError:
                raise DeviceLost(f"no fix (GGA) for {self.settings.timeout_s:g} s") from None
            sentence = parse_line(raw)
            if sentence is None:
                continue
            try:
                self._fixes.extend(self._assembler.feed(t, sentence))
            except ValueError as exc:
                raise CorruptFrame(f"{sentence.sentence_type}: {exc}") from None
        self._deadline = asyncio.get_running_loop().time() + self.settings.timeout_s
        return self._fixes.popleft()

    async def close(self) -> None:
        lines, self._lines = self._lines, None
        if lines is not None:
            lines.close()


@register_backend("gnss", "nmea", NmeaGnssSettings)
def _nmea_gnss(name: str, settings: NmeaGnssSettings, ctx: Any) -> NmeaGnss:
    """A receiver sending NMEA 0183 on a serial port."""
    return NmeaGnss(settings, receiver_id=name)
