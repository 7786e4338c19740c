"""Hokuyo scanners over SCIP 2.0 (URG-04LX, UTM-30LX, ...): USB/serial or Ethernet (TCP).

:class:`HokuyoScip` is the ``real`` lidar backend (drivers/base.py). ``open()`` does what
urg_library does before measuring, then synchronises the clocks and starts streaming:

1. QT, skipping whatever a previous session left streaming. A SCIP 1.1 answer ("E") gets
   ``SCIP2.0``; status 0E (stuck in time-adjust mode) gets TM2; then QT again.
2. VV (logged) and PP: step count, angles, range limits and scan period all come from PP.
3. TM0, several TM1 (the one with the shortest round trip maps the sensor's 24-bit
   millisecond clock to the host clock, ``loop.time()``), TM2; see :class:`SensorClock`.
4. BM (laser on) and MD start..end, cluster, every scan, until QT (scans "00").

``read()`` returns the next :class:`~companion.messages.Scan`: ranges in metres, angles in the
sensor frame of companion/messages.py (``angle = -(step - AFRT) * 2 pi / ARES``), values below
DMIN (error codes; UTM-30LX uses 1..5) or above DMAX invalid, ``t_capture`` the host time of
the first beam. Every line's sum byte is checked; a bad or truncated scan raises
CorruptFrame and reading resumes at the next reply (replies are framed by their empty
line). Status 98 and unknown statuses are CorruptFrame; 21-49 (the sensor stopped to check
an error) restart MD; 50-97 (hardware trouble) and EOF, disconnection or silence longer than
``timeout_s`` raise DeviceLost, so the frontend reopens the device with backoff.

The event loop never blocks: TCP uses asyncio streams; a serial port is opened with
pyserial in a worker thread and then read through ``loop.add_reader`` on its descriptor.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np
import serial

from companion.plugins import register_backend
from companion.schema import meta
from drivers import scip
from drivers.base import Backend, CorruptFrame, DeviceLost
from companion.messages import Scan
from drivers.serial_fd import SerialFd
from drivers.scip import Reply, ScipError, ScipProtocolError, SensorParams

log = logging.getLogger("companion.drivers.hokuyo")

REPLY_LIMIT = 1 << 16  # bytes; a UTM-30LX scan is about 3.4 kB
TERMINATOR = b"\n\n"
TIME_SYNC_SAMPLES = 5  # TM1 round trips; the shortest one is used
MIN_WAIT_S = 0.01  # never wait for a reply with less than this


@dataclass
class HokuyoSettings:
    """``settings`` of a ``kind: lidar, backend: real`` sensor."""

    port: str | None = field(default=None, metadata=meta(
        "Serial device (or pyserial URL) of a USB/RS-232 scanner, e.g. /dev/ttyACM0; null for Ethernet."))
    host: str | None = field(default=None, metadata=meta(
        "Address of an Ethernet scanner (factory default 192.168.0.10); null for USB/serial."))
    tcp_port: int = field(default=10940, metadata=meta("TCP port of an Ethernet scanner.", (1, 65535)))
    baud: int = field(default=115200, metadata=meta(
        "Serial bit rate (USB CDC-ACM scanners ignore it).", (1200, 1_000_000)))
    model: str | None = field(default=None, metadata=meta(
        "Expected model, checked against the PP reply (e.g. UTM-30LX, URG-04LX); null = any."))
    start_step: int | None = field(default=None, metadata=meta(
        "First step to measure (Hokuyo steps); null = AMIN from PP.", (0, 9999)))
    end_step: int | None = field(default=None, metadata=meta(
        "Last step to measure (Hokuyo steps); null = AMAX from PP.", (0, 9999)))
    cluster: int = field(default=1, metadata=meta(
        "Neighbouring steps merged into one beam by the scanner (it reports the shortest).", (1, 99)))
    min_range_m: float | None = field(default=None, metadata=meta(
        "Ranges below this are invalid, metres; null = DMIN from PP.", (0.0, 100.0)))
    timeout_s: float = field(default=1.0, metadata=meta(
        "A reply or scan later than this means the scanner is lost, seconds.", (0.05, 30.0)))

    def validate(self) -> tuple[str, str] | None:
        """Exactly one link; a step range that is not reversed."""
        if (self.port is None) == (self.host is None):
            return "port", "give exactly one of port (USB/serial) and host (Ethernet)"
        if self.start_step is not None and self.end_step is not None and self.start_step > self.end_step:
            return "end_step", f"end_step {self.end_step} is before start_step {self.start_step}"
        return None


class StartupError(OSError):
    """The scanner answered, but the start-up sequence failed (error status, wrong model,
    steps outside its range, no SCIP 2.0). An OSError, so the frontend retries with backoff."""


# --- time -------------------------------------------------------------------------------

class SensorClock:
    """Maps the sensor's 24-bit millisecond timestamps to the host clock (seconds).

    It starts from one TM1 reading ``sensor_ms`` taken at host time ``host_s``: host time =
    offset + sensor time. Timestamps are unwrapped across the 2^24 ms wrap (4.66 h) by the
    signed difference to the previous one. After that, arrival times keep the offset honest,
    since a scan can never arrive before its step 0 plus the transfer delay:

    - the first ``LEARN_S`` trust the TM offset and learn that delay's floor, the minimum of
      arrival - mapped time (long enough that a busy host does not inflate every sample);
    - each later ``WINDOW_S`` moves the offset by the change of that minimum, slew-limited to
      ``MAX_SLEW`` (1000 ppm: far above a crystal's drift, far below a stalled host's delay,
      which only ever adds delay);
    - a scan mapped later than its arrival allows (more than ``TOLERANCE_S`` below the floor)
      pulls the offset down at once: the sensor clock runs fast;
    - a sensor time that goes backwards, or jumps further ahead than the host time between
      two scans plus ``JUMP_S``, re-anchors the offset: the sensor clock restarted (RS, a
      power glitch).
    """

    LEARN_S = 2.0
    WINDOW_S = 1.0
    MAX_SLEW = 1e-3
    TOLERANCE_S = 1e-3
    JUMP_S = 0.5

    def __init__(self, sensor_ms: int, host_s: float) -> None:
        self._raw = sensor_ms
        self._ms = sensor_ms  # unwrapped
        self._offset = host_s - sensor_ms / 1000.0
        self._floor: float | None = None  # learnt minimum delay from step 0 to arrival, s
        self._previous: tuple[float, float] | None = None  # (sensor s, arrival s) of the last scan
        self._window_start: float | None = None
        self._window_min = math.inf

    def unwrap(self, raw_ms: int) -> int:
        """The 24-bit timestamp ``raw_ms`` as a continuous millisecond count."""
        diff = (raw_ms - self._raw) % scip.TIMESTAMP_MODULUS_MS
        if diff >= scip.TIMESTAMP_MODULUS_MS // 2:
            diff -= scip.TIMESTAMP_MODULUS_MS
        self._raw = raw_ms
        self._ms += diff
        return self._ms

    def host_time(self, raw_ms: int, arrival_s: float) -> float:
        """Host time of sensor timestamp ``raw_ms``, for a reply that arrived at ``arrival_s``."""
        s = self.unwrap(raw_ms) / 1000.0
        floor = self._floor or 0.0
        lag = arrival_s - (self._offset + s)
        if self._jumped(s, arrival_s) or lag < floor - self.TOLERANCE_S:
            self._offset = arrival_s - s - floor
            lag = floor
        self._previous = (s, arrival_s)
        self._track(lag, arrival_s)
        return self._offset + s

    def _jumped(self, s: float, arrival_s: float) -> bool:
        if self._previous is None:
            return False
        ds, dh = s - self._previous[0], arrival_s - self._previous[1]
        return ds < 0 or ds > dh + self.JUMP_S

    def _track(self, lag: float, arrival_s: float) -> None:
        if self._window_start is None:
            self._window_start = arrival_s
        self._window_min = min(self._window_min, lag)
        span = arrival_s - self._window_start
        if span < (self.LEARN_S if self._floor is None else self.WINDOW_S):
            return
        if self._floor is None:
            self._floor = self._window_min
        else:
            step = self.MAX_SLEW * span
            self._offset += min(max(self._window_min - self._floor, -step), step)
        self._window_start, self._window_min = arrival_s, math.inf


# --- links ------------------------------------------------------------------------------

class _Link(ABC):
    """A byte stream to the scanner: replies arrive in ``reader``."""

    reader: asyncio.StreamReader

    @abstractmethod
    def write(self, data: bytes) -> None:
        """Send a request; DeviceLost if the link is gone."""

    @abstractmethod
    def close(self) -> None:
        """Release the link."""


class _TcpLink(_Link):
    """Ethernet scanners: one TCP connection."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader = reader
        self._writer = writer

    @classmethod
    async def connect(cls, host: str, port: int, timeout_s: float) -> _TcpLink:
        try:
            reader, writer = await asyncio.wait_for(
                asyncio.open_connection(host, port, limit=REPLY_LIMIT), timeout_s)
        except TimeoutError as exc:
            raise DeviceLost(f"no TCP connection to {host}:{port} within {timeout_s:.1f} s") from exc
        return cls(reader, writer)

    def write(self, data: bytes) -> None:
        if self._writer.is_closing():
            raise DeviceLost("TCP connection closed")
        self._writer.write(data)

    def close(self) -> None:
        self._writer.close()


class _SerialLink(_Link):
    """USB CDC-ACM or RS-232 scanners: pyserial configures the port, the loop reads its fd."""

    def __init__(self, port: serial.SerialBase) -> None:
        self.reader = asyncio.StreamReader(limit=REPLY_LIMIT)
        self._serial = SerialFd(port, "scanner", self.reader.feed_data, self.reader.set_exception, REPLY_LIMIT)

    @classmethod
    async def open(cls, url: str, baud: int) -> _SerialLink:
        port = await SerialFd.open_port(url, baud)
        try:
            return cls(port)
        except (AttributeError, ValueError) as exc:  # io.UnsupportedOperation is a ValueError
            port.close()
            raise StartupError(f"{url} has no file descriptor; use a device path, or host for Ethernet") from exc
        except BaseException:
            port.close()
            raise

    def write(self, data: bytes) -> None:
        self._serial.write(data)

    def close(self) -> None:
        self._serial.close()


# --- the backend --------------------------------------------------------------------------

class HokuyoScip(Backend[Scan]):
    """A Hokuyo scanner speaking SCIP 2.0; scans go out as :class:`~companion.messages.Scan`."""

    def __init__(self, settings: HokuyoSettings, sensor_id: str = "lidar") -> None:
        self.settings = settings
        self.sensor_id = sensor_id
        where = settings.port if settings.port is not None else f"{settings.host}:{settings.tcp_port}"
        self.description = f"Hokuyo scanner on {where}"
        self.params: SensorParams | None = None  # from PP, set by open()
        self.version: dict[str, str] = {}  # VV fields, set by open()
        self.clock: SensorClock | None = None
        self._link: _Link | None = None
        self._md = b""  # the MD request being streamed
        self._angles = np.empty(0)
        self._first_beam_s = 0.0  # step 0 to the first beam, s
        self._sweep_s = 0.0  # first to last beam, s
        self._min_mm = 0
        self._last: tuple[int, float] | None = None  # (sequence, t_capture) of the last scan

    # --- Backend ----------------------------------------------------------------

    async def open(self) -> None:
        await self.close()
        self._link = await self._connect()
        try:
            await self._start_scip2()
            self.version = scip.parse_info(await self._command(scip.VV))
            self.params = SensorParams.from_pp(scip.parse_info(await self._command(scip.PP)))
            start, end = self._plan(self.params)
            self.clock = await self._sync_clock()
            await self._command(scip.BM, ok=("00", "02"))
            self._md = scip.md_request(start, end, self.settings.cluster)
            await self._command(self._md)
        except BaseException as exc:
            await self.close()
            if isinstance(exc, (ScipProtocolError, CorruptFrame)):
                raise StartupError(f"start-up failed: {exc}") from exc
            raise
        p = self.params
        log.info("%s: %s (serial %s, firmware %s): steps %d..%d / %d, cluster %d, %.1f Hz",
                 self.description, p.model, self.version.get("SERI", "?"), self.version.get("FIRM", "?"),
                 start, end, p.ares, self.settings.cluster, 1.0 / p.scan_period_s)

    async def read(self) -> Scan:
        if self._link is None or self.params is None:
            raise DeviceLost("not open")
        while True:
            raw = await self._read_reply(self.settings.timeout_s, "the next scan")
            arrival = asyncio.get_running_loop().time()
            try:
                reply = scip.split_reply(raw)
                if reply.echo != self._md[:-1]:
                    raise ScipProtocolError(f"unexpected reply {reply.echo[:20]!r} while streaming")
                if reply.status == "00":
                    continue  # the acknowledgement of a restarted MD
                if reply.status != "99":
                    self._stream_status(reply.status)
                data = scip.parse_distance_data(reply)
            except ScipProtocolError as exc:
                raise CorruptFrame(str(exc)) from exc
            return self._scan(data, arrival)

    async def close(self) -> None:
        link, self._link = self._link, None
        if link is None:
            return
        with contextlib.suppress(Exception):
            link.write(scip.QT)  # stop streaming, laser off
        with contextlib.suppress(Exception):
            link.close()

    # --- start-up -------------------------------------------------------------------

    async def _connect(self) -> _Link:
        s = self.settings
        if s.port is not None:
            return await _SerialLink.open(s.port, s.baud)
        assert s.host is not None
        return await _TcpLink.connect(s.host, s.tcp_port, s.timeout_s)

    async def _start_scip2(self) -> None:
        """QT until the answer is SCIP 2.0's "00", recovering like urg_library."""
        for _ in range(3):
            reply = await self._command(scip.QT, ok=None)
            if reply.status == "00":
                return
            if reply.status == "E":  # SCIP 1.1
                log.info("%s: switching from SCIP 1.1 to SCIP 2.0", self.description)
                await self._command(scip.SCIP20, ok=("0", "00"))
            elif reply.status == "0E":  # left in time-adjust mode
                log.info("%s: leaving time-adjust mode", self.description)
                await self._command(scip.tm_request(2), ok=("00", "03"))
            else:
                reply.raise_for_status()
        raise StartupError("no SCIP 2.0 after recovery")

    def _plan(self, params: SensorParams) -> tuple[int, int]:
        """Check model and steps against PP; precompute beam angles and times."""
        s = self.settings
        if s.model is not None and s.model not in params.model:
            raise StartupError(f"expected a {s.model}, found {params.model}")
        start = params.amin if s.start_step is None else s.start_step
        end = params.amax if s.end_step is None else s.end_step
        if not params.amin <= start <= end <= params.amax:
            raise StartupError(f"steps {start}..{end} outside the scanner's "
                               f"{params.amin}..{params.amax}")
        centres = params.beam_steps(start, end, s.cluster)
        self._angles = np.asarray(params.angle_rad(centres))
        self._angles.setflags(write=False)
        self._first_beam_s = centres[0] * params.step_time_s
        self._sweep_s = (centres[-1] - centres[0]) * params.step_time_s
        min_mm = params.dmin_mm if s.min_range_m is None else max(params.dmin_mm, s.min_range_m * 1000.0)
        self._min_mm = math.ceil(min_mm)
        return start, end

    async def _sync_clock(self) -> SensorClock:
        """TM0, TM1 x TIME_SYNC_SAMPLES (keep the shortest round trip), TM2."""
        loop = asyncio.get_running_loop()
        await self._command(scip.tm_request(0), ok=("00", "02"))
        best: tuple[float, float, int] | None = None  # (round trip, host midpoint, sensor ms)
        for _ in range(TIME_SYNC_SAMPLES):
            t0 = loop.time()
            reply = await self._command(scip.tm_request(1))
            t1 = loop.time()
            sample = (t1 - t0, (t0 + t1) / 2, scip.parse_timestamp_reply(reply))
            best = sample if best is None or sample[0] < best[0] else best
        await self._command(scip.tm_request(2), ok=("00", "03"))
        assert best is not None
        log.debug("%s: clock synchronised (round trip %.2f ms)", self.description, best[0] * 1e3)
        return SensorClock(best[2], best[1])

    async def _command(self, request: bytes, ok: tuple[str, ...] | None = ("00",)) -> Reply:
        """Send ``request`` and return its reply (checked against ``ok`` unless None),
        skipping anything else that arrives first (e.g. scans a previous session left on)."""
        assert self._link is not None
        loop = asyncio.get_running_loop()
        self._link.write(request)
        deadline = loop.time() + self.settings.timeout_s
        echo = request[:-1] + scip.LF
        while True:
            raw = await self._read_reply(max(deadline - loop.time(), MIN_WAIT_S), repr(request))
            if raw.startswith(echo):
                break
            log.debug("%s: skipped %d bytes waiting for %r", self.description, len(raw), request)
        reply = scip.split_reply(raw)
        if ok is not None:
            reply.raise_for_status(ok)
        return reply

    async def _read_reply(self, timeout_s: float, awaited: str) -> bytes:
        """The next reply, up to and including its empty line (``awaited`` names it in errors)."""
        assert self._link is not None
        reader = self._link.reader
        try:
            async with asyncio.timeout(timeout_s):  # no task per reply, unlike wait_for
                return await reader.readuntil(TERMINATOR)
        except TimeoutError as exc:
            raise DeviceLost(f"no reply from the scanner within {timeout_s:.2f} s (waiting for {awaited})") from exc
        except asyncio.IncompleteReadError as exc:
            raise DeviceLost("the scanner closed the connection") from exc
        except asyncio.LimitOverrunError as exc:
            await reader.readexactly(exc.consumed)
            raise CorruptFrame(f"no reply end within {REPLY_LIMIT} bytes") from exc

    # --- streaming ------------------------------------------------------------------

    def _stream_status(self, status: str) -> None:
        """React to a non-data status while streaming (always raises)."""
        assert self._link is not None
        error = ScipError("MD", status)
        code = int(status) if status.isdigit() else -1
        if 21 <= code <= 49:
            self._link.write(self._md)
            raise CorruptFrame(f"{error}; streaming restarted")
        if 50 <= code <= 97:
            raise DeviceLost(str(error))
        raise error

    def _scan(self, data: scip.DistanceData, arrival_s: float) -> Scan:
        assert self.params is not None and self.clock is not None
        ranges = data.ranges_mm
        valid = (ranges >= self._min_mm) & (ranges <= self.params.dmax_mm)
        t_capture = self.clock.host_time(data.timestamp_ms, arrival_s) + self._first_beam_s
        return Scan(self.sensor_id, t_capture, self._angles, ranges / 1000.0, valid,
                    self._sweep_s, self._sequence(t_capture))

    def _sequence(self, t_capture: float) -> int:
        """Scan counter that skips the scans lost in between (by capture time)."""
        assert self.params is not None
        if self._last is None:
            sequence = 0
        else:
            elapsed = t_capture - self._last[1]
            sequence = self._last[0] + max(1, round(elapsed / self.params.scan_period_s))
        self._last = (sequence, t_capture)
        return sequence


@register_backend("lidar", "real", HokuyoSettings)
def _hokuyo(name: str, settings: HokuyoSettings, ctx: object) -> HokuyoScip:
    """A Hokuyo on a serial port or TCP (SCIP 2.0)."""
    return HokuyoScip(settings, sensor_id=name)
