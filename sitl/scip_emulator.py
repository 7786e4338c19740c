"""A Hokuyo SCIP 2.0 device emulator over TCP (Ethernet models) and a pseudo-terminal (USB).

It answers like a real URG-04LX / UTM-30LX: QT, SCIP2.0, VV, PP, II, BM, TM0/1/2, MD/MS,
GD/GS and RS, with echoes, statuses, sum bytes, 64-character data blocks and the empty-line
terminators of :mod:`drivers.scip`. MD/MS stream at the scan period: scan ``k`` has step 0
at host time ``T0 + k * period`` (its timestamp is the emulated 24-bit sensor clock then)
and is sent once the mirror has passed the last requested step, as a sensor does.

Device state survives connections (like a sensor): SCIP 1.1 or 2.0 mode, time-adjust mode,
laser, clock. Start-up quirks (``start_mode``): ``"scip1"`` (answers SCIP 1.1 until it gets
``SCIP2.0``), ``"tm"`` (stuck in time-adjust mode: everything but TM gets status 0E),
``"streaming"`` (the first client finds an MD stream already running).

Faults for tests: :meth:`ScipEmulator.corrupt_scans` (a wrong sum byte in a data line),
:meth:`ScipEmulator.truncate_scans` (a scan cut short in the middle of a block, with valid
sums), :meth:`ScipEmulator.send_status` (a status-only reply instead of the next scan;
21-49 stop the stream as on a sensor), :meth:`ScipEmulator.disconnect` (unplug, optionally
power-cycle, and plug back in).

CLI (a constant synthetic room)::

    python -m sitl.scip_emulator --model UTM-30LX --tcp 127.0.0.1:10940
    python -m sitl.scip_emulator --model URG-04LX --pty      # prints the device path
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import os
import shutil
import tempfile
import tty
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from drivers import scip
from drivers.lidar_models import MODELS as LIDAR_MODELS
from drivers.scip import SensorParams

# PP replies of the real sensors, from the one model table (drivers/lidar_models.py).
MODELS: dict[str, SensorParams] = {name: model.pp for name, model in LIDAR_MODELS.items()}

StartMode = Literal["scip2", "scip1", "tm", "streaming"]
# One scan: (sensor timestamp in ms or None for the emulator's clock, ranges in mm for
# steps AMIN..AMAX). A callable is asked once per scan; an iterable ends the stream when spent.
ScanSource = Callable[[], tuple[int | None, np.ndarray]] | Iterable[tuple[int | None, np.ndarray]]


@dataclass(frozen=True)
class SentScan:
    """What the emulator sent for one scan (for tests to compare against)."""

    timestamp_ms: int  # 24-bit sensor clock in the reply
    t_step0: float  # host (event loop) time of the scan's step 0, s
    ranges_mm: np.ndarray  # steps AMIN..AMAX as the source gave them
    fault: str | None  # "corrupt", "truncate", "status NN" or None


class _Session:
    """One client connection (a TCP socket, or the pty while it is plugged in)."""

    def __init__(self, writer: asyncio.StreamWriter) -> None:
        self.writer = writer
        self.task = asyncio.current_task()  # the one serving this connection
        self.stream: asyncio.Task[None] | None = None

    def send(self, data: bytes) -> None:
        if not self.writer.is_closing():
            self.writer.write(data)

    def stop_stream(self) -> None:
        if self.stream is not None:
            self.stream.cancel()
            self.stream = None


class ScipEmulator:
    """A SCIP 2.0 sensor with ``params`` (see :data:`MODELS`) measuring ``scan_source``."""

    def __init__(self, params: SensorParams, scan_source: ScanSource, *, start_mode: StartMode = "scip2",
                 clock_start_ms: int = 0, period_s: float | None = None, history: int = 1000) -> None:
        """``clock_start_ms``: sensor clock at start-up (e.g. near 2^24 to test the wrap);
        ``period_s``: scan period overriding PP's SCAN (e.g. to replay a file quickly)."""
        self.params = params
        self._source = scan_source if callable(scan_source) else iter(scan_source).__next__
        self.period_s = period_s if period_s is not None else params.scan_period_s
        self._scip1 = start_mode == "scip1"
        self._adjust_mode = start_mode == "tm"
        self._stream_on_connect = start_mode == "streaming"
        self.laser_on = False
        self._clock_origin = 0.0
        self._clock_start_ms = clock_start_ms
        self._faults: deque[str] = deque()
        self._noise = np.random.default_rng(0)  # the bytes of garbage_scans()
        self._sessions: set[_Session] = set()
        self._server: asyncio.Server | None = None
        self._tcp_address: tuple[str, int] | None = None
        self._pty_dir: Path | None = None
        self._pty: tuple[int, asyncio.BaseTransport, asyncio.StreamWriter, asyncio.Task[None]] | None = None
        self.commands: list[str] = []  # every request line received, for tests
        self.sent: deque[SentScan] = deque(maxlen=history)  # the latest scans, for tests

    # --- plugging in -----------------------------------------------------------------

    async def start_tcp(self, host: str = "127.0.0.1", port: int = 0) -> int:
        """Serve on ``host:port`` (0 = any free port); returns the port."""
        self._reset_clock()
        self._server = await asyncio.start_server(self._serve, host, port)
        self._tcp_address = (host, self._server.sockets[0].getsockname()[1])
        return self._tcp_address[1]

    async def start_pty(self) -> str:
        """Serve on a pseudo-terminal; returns a stable device path (a symlink to the pty
        slave, re-pointed on every re-plug like a udev symlink) to open like /dev/ttyACM0."""
        self._reset_clock()
        self._pty_dir = Path(tempfile.mkdtemp(prefix="scip-emulator-"))
        await self._plug_pty()
        return str(self._pty_dir / "ttyACM0")

    async def close(self) -> None:
        """Stop serving and release the port or pty."""
        await self._unplug()
        if self._pty_dir is not None:
            shutil.rmtree(self._pty_dir, ignore_errors=True)
            self._pty_dir = None

    async def disconnect(self, down_s: float = 0.3, *, power_cycle: bool = False) -> None:
        """Unplug (every connection drops), wait ``down_s``, plug back in.

        ``power_cycle`` also resets the device like a bus-powered sensor: laser off, clock
        restarting at 0, no stream.
        """
        await self._unplug()
        if power_cycle:
            self.laser_on = False
            self._clock_start_ms = 0
            self._reset_clock()
        await asyncio.sleep(down_s)
        if self._tcp_address is not None:
            self._server = await asyncio.start_server(self._serve, *self._tcp_address)
        elif self._pty_dir is not None:
            await self._plug_pty()

    async def _plug_pty(self) -> None:
        assert self._pty_dir is not None
        loop = asyncio.get_running_loop()
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo or line editing before the client configures the port
        link = self._pty_dir / "ttyACM0"
        tmp = self._pty_dir / "ttyACM0.new"
        os.symlink(os.ttyname(slave), tmp)
        os.replace(tmp, link)
        reader = asyncio.StreamReader()
        read_transport, _ = await loop.connect_read_pipe(
            lambda: asyncio.StreamReaderProtocol(reader), os.fdopen(master, "rb", buffering=0))
        write_transport, protocol = await loop.connect_write_pipe(
            asyncio.streams.FlowControlMixin, os.fdopen(os.dup(master), "wb", buffering=0))
        writer = asyncio.StreamWriter(write_transport, protocol, reader, loop)
        self._pty = (slave, read_transport, writer, asyncio.create_task(self._serve(reader, writer)))

    async def _unplug(self) -> None:
        if self._server is not None:
            self._server.close()
            self._server = None
        if self._pty is not None:
            slave, read_transport, writer, task = self._pty
            self._pty = None
            writer.transport.abort()
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
            read_transport.close()
            os.close(slave)
            with contextlib.suppress(FileNotFoundError):
                (self._pty_dir / "ttyACM0").unlink()  # type: ignore[operator]
        sessions = list(self._sessions)  # TCP clients
        for session in sessions:
            session.stop_stream()
            if not session.writer.is_closing():
                session.writer.transport.abort()
        if sessions:  # let them see the connection drop and finish
            await asyncio.wait([s.task for s in sessions if s.task is not None], timeout=1.0)

    # --- faults ------------------------------------------------------------------------

    def corrupt_scans(self, n: int = 1) -> None:
        """The next ``n`` streamed scans carry a wrong sum byte in one data line."""
        self._faults.extend(["corrupt"] * n)

    def truncate_scans(self, n: int = 1) -> None:
        """The next ``n`` streamed scans stop in the middle of a data block (sums valid)."""
        self._faults.extend(["truncate"] * n)

    def garbage_scans(self, n: int = 1) -> None:
        """The next ``n`` streamed scans are replaced by line noise (random bytes, then LF LF)."""
        self._faults.extend(["garbage"] * n)

    def delay_scans(self, n: int, delay_s: float) -> None:
        """The next ``n`` streamed scans leave ``delay_s`` late (a slow or congested scanner)."""
        self._faults.extend([f"delay {delay_s}"] * n)

    def send_status(self, status: str) -> None:
        """Answer the next streamed scan with ``status`` only (21-49 then stop streaming)."""
        self._faults.append(f"status {status}")

    # --- clock -------------------------------------------------------------------------

    def _reset_clock(self) -> None:
        self._clock_origin = asyncio.get_running_loop().time()

    def clock_ms(self, host_t: float | None = None) -> int:
        """The 24-bit sensor clock (ms) at host time ``host_t`` (default: now)."""
        t = asyncio.get_running_loop().time() if host_t is None else host_t
        return (self._clock_start_ms + math.floor((t - self._clock_origin) * 1000.0)) % scip.TIMESTAMP_MODULUS_MS

    # --- requests ----------------------------------------------------------------------

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        session = _Session(writer)
        self._sessions.add(session)
        if self._stream_on_connect:  # a previous client left MD on: join in mid-reply
            self._stream_on_connect = False
            p = self.params
            session.send(scip.format_data_lines(np.full(64, p.dmin_mm), 3)[-70:] + scip.LF)
            self._start_stream(session, scip.md_request(p.amin, p.amax)[:-1], at_once=True)
        try:
            while True:
                line = (await reader.readuntil(b"\n"))[:-1]
                self.commands.append(line.decode("ascii", "replace"))
                session.send(self._answer(session, line))
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, ConnectionError):
            pass
        finally:
            session.stop_stream()
            self._sessions.discard(session)
            writer.close()

    def _answer(self, session: _Session, line: bytes) -> bytes:
        if self._scip1:
            if line == b"SCIP2.0":
                self._scip1 = False
                return b"SCIP2.0\n0\n\n"
            return line + b"\nE\n\n"
        body, _, tag = line.partition(b";")
        if len(tag) > scip.MAX_TAG_CHARS:
            return scip.format_reply(line, "0G")
        if self._adjust_mode and not body.startswith(b"TM"):
            return scip.format_reply(line, "0E")
        if body == b"SCIP2.0":  # already in SCIP 2.0
            return scip.format_reply(line, "0E")
        handler = {b"QT": self._qt, b"RS": self._rs, b"BM": self._bm, b"VV": self._vv, b"PP": self._pp,
                   b"II": self._ii, b"TM": self._tm, b"MD": self._md, b"MS": self._md, b"GD": self._gd,
                   b"GS": self._gd}.get(body[:2])
        if handler is None:
            return scip.format_reply(line, "0D")
        return handler(session, line, body)

    def _qt(self, session: _Session, line: bytes, body: bytes) -> bytes:
        session.stop_stream()
        self.laser_on = False
        return scip.format_reply(line, "00")

    def _rs(self, session: _Session, line: bytes, body: bytes) -> bytes:
        session.stop_stream()
        self.laser_on = False
        self._clock_start_ms = 0
        self._reset_clock()
        return scip.format_reply(line, "00")

    def _bm(self, session: _Session, line: bytes, body: bytes) -> bytes:
        if self.laser_on:
            return scip.format_reply(line, "02")
        self.laser_on = True
        return scip.format_reply(line, "00")

    def _vv(self, session: _Session, line: bytes, body: bytes) -> bytes:
        name = self.params.model.split("(")[0]
        return self._info(line, {"VEND": "Hokuyo Automatic Co.,Ltd.", "PROD": f"SOKUIKI Sensor {name}",
                                 "FIRM": "emulator (sitl.scip_emulator)", "PROT": "SCIP 2.0", "SERI": "H0000001"})

    def _pp(self, session: _Session, line: bytes, body: bytes) -> bytes:
        return self._info(line, self.params.pp_fields())

    def _ii(self, session: _Session, line: bytes, body: bytes) -> bytes:
        return self._info(line, {
            "MODL": self.params.model, "LASR": "ON" if self.laser_on else "OFF",
            "SCSP": f"Initial({self.params.scan_rpm}[rpm])",
            "MESM": "Measuring by Normal Mode" if self.laser_on else "Idle",
            "SBPS": "USB only", "TIME": scip.encode(self.clock_ms(), 4).decode("ascii"),
            "STAT": "Sensor works well."})

    @staticmethod
    def _info(line: bytes, fields: dict[str, str]) -> bytes:
        return scip.format_reply(line, "00", b"".join(scip.format_info_line(k, v) for k, v in fields.items()))

    def _tm(self, session: _Session, line: bytes, body: bytes) -> bytes:
        code = body[2:]
        if code == b"0":
            status = "02" if self._adjust_mode else "00"
            session.stop_stream()
            self.laser_on = False
            self._adjust_mode = True
        elif code == b"1":
            if not self._adjust_mode:
                return scip.format_reply(line, "04")
            return scip.format_reply(line, "00", scip.format_line(scip.encode(self.clock_ms(), 4)))
        elif code == b"2":
            status = "00" if self._adjust_mode else "03"
            self._adjust_mode = False
        else:
            status = "01"
        return scip.format_reply(line, status)

    def _measure_status(self, body: bytes, continuous: bool) -> str | None:
        """Status for bad MD/MS/GD/GS parameters, None if they are fine."""
        if len(body) != (15 if continuous else 12):
            return "0C"
        fields = [(body[2:6], "01"), (body[6:10], "02"), (body[10:12], "03")]
        if continuous:
            fields += [(body[12:13], "06"), (body[13:15], "07")]
        for text, status in fields:
            if not text.isdigit():
                return status
        start, end = int(body[2:6]), int(body[6:10])
        if start < self.params.amin or end > self.params.amax:
            return "04"
        if end < start:
            return "05"
        return None

    def _md(self, session: _Session, line: bytes, body: bytes) -> bytes:
        status = self._measure_status(body, continuous=True)
        if status is not None:
            return scip.format_reply(line, status)
        self._start_stream(session, line)
        return scip.format_reply(line, "00")

    def _gd(self, session: _Session, line: bytes, body: bytes) -> bytes:
        status = self._measure_status(body, continuous=False)
        if status is not None or not self.laser_on:
            return scip.format_reply(line, status or "10")
        t = asyncio.get_running_loop().time()
        stamp, values, _ = self._measure(scip.parse_distance_echo(body), t)
        return scip.format_reply(line, "00", scip.format_line(scip.encode(stamp, 4)) + values)

    # --- measuring ---------------------------------------------------------------------

    def _start_stream(self, session: _Session, line: bytes, at_once: bool = False) -> None:
        session.stop_stream()
        self.laser_on = True
        session.stream = asyncio.create_task(self._stream(session, line, at_once))

    async def _stream(self, session: _Session, line: bytes, at_once: bool) -> None:
        """Send scans at the scan period until cancelled, the count is done or a 21-49 status;
        ``at_once``: the first scan is already measured (sent without waiting)."""
        loop = asyncio.get_running_loop()
        body, sep, tag = line.partition(b";")
        request = scip.parse_distance_echo(body)
        period = self.period_s * (request.interval + 1)
        sweep = (request.end + 1) * self.period_s / self.params.ares  # step 0 to the last step
        t_step0 = loop.time() - (sweep if at_once else 0.0)
        remaining = request.scans  # 0: until QT
        while True:
            await asyncio.sleep(max(0.0, t_step0 + sweep - loop.time()))
            if self._faults and self._faults[0].startswith("delay "):
                await asyncio.sleep(float(self._faults.popleft().split()[1]))
            remaining = max(remaining - 1, 0)
            echo = body[:13] + b"%02d" % remaining + sep + tag
            try:
                reply, stop = self._scan_reply(request, echo, t_step0)
            except StopIteration:
                return  # the recording is over: the sensor goes quiet
            session.send(reply)
            await session.writer.drain()
            if stop or (request.scans and not remaining):
                return
            t_step0 += period
            while t_step0 + sweep < loop.time() - period:  # fell behind (slow reader): drop scans
                t_step0 += period

    def _scan_reply(self, request: scip.DistanceEcho, echo: bytes, t_step0: float) -> tuple[bytes, bool]:
        """One streamed reply (with any pending fault) and whether the stream stops after it."""
        fault = self._faults.popleft() if self._faults else None
        if fault is not None and fault.startswith("status "):
            status = fault.split()[1]
            self.sent.append(SentScan(self.clock_ms(t_step0), t_step0, np.empty(0, np.int64), fault))
            return scip.format_reply(echo, status), 21 <= int(status) <= 49
        if fault == "garbage":
            self.sent.append(SentScan(self.clock_ms(t_step0), t_step0, np.empty(0, np.int64), fault))
            return self._noise.integers(0, 256, 200, dtype=np.uint8).tobytes() + scip.LF + scip.LF, False
        stamp, data, full = self._measure(request, t_step0)
        if fault == "corrupt":
            data = _corrupt_sum(data)
        elif fault == "truncate":
            data = _truncate(data)
        self.sent.append(SentScan(stamp, t_step0, full, fault))
        return scip.format_reply(echo, "99", scip.format_line(scip.encode(stamp, 4)) + data), False

    def _measure(self, request: scip.DistanceEcho, t_step0: float) -> tuple[int, bytes, np.ndarray]:
        """(timestamp ms, formatted data lines, the source's full scan) for one scan."""
        stamp, full = self._source()
        full = np.asarray(full, dtype=np.int64)
        if full.shape != (self.params.steps,):
            raise ValueError(f"scan source gave {full.shape} ranges, expected ({self.params.steps},)")
        stamp = self.clock_ms(t_step0) if stamp is None else stamp % scip.TIMESTAMP_MODULUS_MS
        values = cluster_ranges(full[request.start - self.params.amin:request.end - self.params.amin + 1],
                                request.cluster, self.params.dmin_mm)
        if request.width == 2:
            values = np.minimum(values, (1 << 12) - 1)
        return stamp, scip.format_data_lines(values, request.width), full


def cluster_ranges(ranges_mm: np.ndarray, cluster: int, dmin_mm: int) -> np.ndarray:
    """Group ``cluster`` neighbouring steps into one value, as a sensor does: the shortest
    real return of the group (values >= DMIN), or the group's first value if it has none."""
    c = max(cluster, 1)
    if c == 1:
        return ranges_mm
    pad = (-len(ranges_mm)) % c
    groups = np.concatenate((ranges_mm, np.zeros(pad, np.int64))).reshape(-1, c)
    real = np.where(groups >= dmin_mm, groups, np.iinfo(np.int64).max)
    shortest = real.min(axis=1)
    return np.where(shortest == np.iinfo(np.int64).max, groups[:, 0], shortest)


def _data_lines(data: bytes) -> list[bytes]:
    return data.split(scip.LF)[:-1]


def _corrupt_sum(data: bytes) -> bytes:
    """Replace the sum byte of the middle data line with a wrong one."""
    lines = _data_lines(data)
    i = len(lines) // 2
    bad = 0x30 + ((lines[i][-1] - 0x30 + 1) & 0x3F)
    lines[i] = lines[i][:-1] + bytes((bad,))
    return b"".join(line + scip.LF for line in lines)


def _truncate(data: bytes) -> bytes:
    """Keep the first half of the data lines and 20 characters of the next (sum recomputed)."""
    lines = _data_lines(data)
    keep = len(lines) // 2
    return b"".join(line + scip.LF for line in lines[:keep]) + scip.format_line(lines[keep][:20])


def synthetic_room(params: SensorParams, front_m: float = 4.0, back_m: float = 2.0,
                   left_m: float = 1.5, right_m: float = 2.5) -> np.ndarray:
    """Ranges (mm, steps AMIN..AMAX) in a rectangular room around the sensor: walls at the
    given distances ahead, behind, left and right of it (sensor frame of companion.messages)."""
    a = np.asarray(params.angle_rad(np.arange(params.amin, params.amax + 1)))
    c, s = np.cos(a), np.sin(a)
    with np.errstate(divide="ignore"):
        along_x = np.where(c > 0, front_m / c, back_m / -c)
        along_y = np.where(s > 0, right_m / s, left_m / -s)
    r_mm = np.rint(np.minimum(along_x, along_y) * 1000.0).astype(np.int64)
    return np.where(r_mm <= params.dmax_mm, r_mm, 0)


async def _serve_forever(args: argparse.Namespace) -> None:
    params = MODELS[args.model]
    room = synthetic_room(params)
    emulator = ScipEmulator(params, lambda: (None, room), start_mode=args.start_mode)
    if args.pty:
        print(f"{args.model} on {await emulator.start_pty()}", flush=True)
    else:
        host, _, port = args.tcp.rpartition(":")
        print(f"{args.model} on tcp {host}:{await emulator.start_tcp(host, int(port))}", flush=True)
    try:
        await asyncio.Event().wait()
    finally:
        await emulator.close()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Hokuyo SCIP 2.0 emulator serving a synthetic room.")
    parser.add_argument("--model", choices=sorted(MODELS), default="UTM-30LX")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--tcp", default="127.0.0.1:10940", help="HOST:PORT to listen on (default %(default)s)")
    where.add_argument("--pty", action="store_true", help="serve on a pseudo-terminal instead")
    parser.add_argument("--start-mode", choices=["scip2", "scip1", "tm", "streaming"], default="scip2")
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(_serve_forever(parser.parse_args(argv)))


if __name__ == "__main__":
    main()
