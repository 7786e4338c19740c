"""ArduPilot SITL as a process of the harness: ports, start, restart, faults, and its internal errors.

``ArduPilotSitl`` runs one ArduPilot SITL binary (e.g. ../shared/ardupilot/arducopter) in its own
working directory (its eeprom.bin and logs live there), on a free *instance*: ArduPilot adds
10 x instance to every port, so several runs (or tests) never share one. Facts it relies on,
checked against ArduCopter 4.0 SITL:

- SERIAL0 is TCP ``5760 + 10 I``, SERIAL1 ``5762 + 10 I``, SERIAL2 ``5763 + 10 I``; each takes one
  client at a time. SERIAL0 normally waits for a client before booting; the harness passes
  ``--uartA tcp:0`` so the autopilot boots first, as it would on a vehicle. ArduPilot listens on
  every interface (its choice); the harness only ever connects on 127.0.0.1.
- ``-w`` wipes the parameters (first start only); a MAVLink reboot re-executes the binary in
  place without it, closing every connection.
- An internal error ("panic") makes SITL spin forever at 100 % CPU; with ``SITL_PANIC_EXIT=1``
  it prints the reason and exits 1 instead, which is how :meth:`internal_errors` finds it.
- It does not always exit on SIGTERM after an internal error: :meth:`stop` kills it on timeout.
"""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

from sitl.frame_shift import moved_origin

BASE_PORT = 5760
SERIAL_OFFSETS = (0, 2, 3)  # SERIAL0, SERIAL1, SERIAL2 (uartA, uartC, uartD) from the base port
UDP_PORTS = (5501, 9005)  # RC input and IRLock, which SITL binds (also + 10 x instance)
MAX_INSTANCE = 60
STOP_TIMEOUT_S = 5.0
# SITL dumps its stack after every panic and fatal signal (AP_HAL::dump_stack_trace); the line
# before says why (e.g. "Should not be called on invalid location", "Short write on UART: 0 < 10").
STACK_DUMP = "Running: sh dumpstack"


@dataclass(frozen=True)
class SitlOptions:
    """How to start the binary: model (frame), parameter defaults file, home, speed-up."""

    binary: Path
    model: str = "+"
    defaults: Path | None = None  # ArduPilot's default parameter file for this model
    home: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)  # lat deg, lon deg, alt m AMSL, heading deg
    speedup: float = 1.0


def serial_port(instance: int, serial: int) -> int:
    """TCP port of SERIAL``serial`` (0, 1 or 2) of SITL instance ``instance``."""
    return BASE_PORT + SERIAL_OFFSETS[serial] + 10 * instance


def default_defaults(binary: Path) -> Path | None:
    """The default parameter file shipped beside the binary (copter.parm for arducopter, ...)."""
    stem = Path(binary).name.replace("ardu", "")
    candidate = Path(binary).parent / f"{stem}.parm"
    return candidate if candidate.exists() else None


def _bindable(kind: socket.SocketKind, port: int) -> bool:
    with socket.socket(socket.AF_INET, kind) as sock:
        if kind == socket.SOCK_STREAM:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(("0.0.0.0", port))
        except OSError:
            return False
    return True


def free_instance(start: int = 0) -> int:
    """The first SITL instance number whose ports are all free."""
    for instance in range(start, MAX_INSTANCE):
        tcp = [serial_port(instance, serial) for serial in range(len(SERIAL_OFFSETS))]
        udp = [port + 10 * instance for port in UDP_PORTS]
        if all(_bindable(socket.SOCK_STREAM, p) for p in tcp) and all(_bindable(socket.SOCK_DGRAM, p) for p in udp):
            return instance
    raise RuntimeError(f"no free ArduPilot SITL instance below {MAX_INSTANCE} (ports {BASE_PORT} + 10 x instance)")


class ArduPilotSitl:
    """One SITL process (see the module docstring)."""

    def __init__(self, options: SitlOptions, workdir: Path, instance: int | None = None) -> None:
        self.options = options
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.instance = free_instance() if instance is None else instance
        self.output = self.workdir / "sitl.out"
        self.proc: subprocess.Popen | None = None
        self.starts = 0

    def port(self, serial: int) -> int:
        """TCP port of SERIAL``serial`` (0, 1 or 2)."""
        return serial_port(self.instance, serial)

    def url(self, serial: int) -> str:
        return f"tcp:127.0.0.1:{self.port(serial)}"

    def command(self, wipe: bool) -> list[str]:
        o = self.options
        lat, lon, alt, heading = o.home
        cmd = [str(o.binary), "-S", "--model", o.model, "--speedup", f"{o.speedup:g}",
               "--home", f"{lat:.9f},{lon:.9f},{alt:.3f},{heading:.2f}", "-I", str(self.instance),
               "--uartA", "tcp:0"]
        if o.defaults is not None:
            cmd += ["--defaults", str(o.defaults)]
        if wipe:
            cmd.insert(1, "-w")
        return cmd

    def start(self, wipe: bool = False) -> None:
        """Start the process (``wipe``: with default parameters); its output goes to ``output``."""
        if self.running:
            raise RuntimeError("ArduPilot SITL is already running")
        with open(self.output, "a") as out:
            out.write(f"--- start {self.starts + 1}: {' '.join(self.command(wipe))}\n")
            out.flush()
            self.proc = subprocess.Popen(self.command(wipe), cwd=self.workdir, stdout=out, stderr=subprocess.STDOUT,
                                         stdin=subprocess.DEVNULL, env={**os.environ, "SITL_PANIC_EXIT": "1"})
        self.starts += 1

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    @property
    def returncode(self) -> int | None:
        return None if self.proc is None else self.proc.poll()

    def wait_listening(self, timeout_s: float = 15.0) -> bool:
        """Until SERIAL2 accepts connections (the autopilot booted), or it exits / the time is up."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if not self.running:
                return False
            with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
                probe.settimeout(0.2)
                if probe.connect_ex(("127.0.0.1", self.port(2))) == 0:
                    return True  # (SERIAL2: the port nobody else uses, so the probe steals no client slot)
            time.sleep(0.1)
        return False

    def pause(self) -> None:
        """SIGSTOP: the autopilot hangs (connections stay open, nothing is answered)."""
        if self.proc is not None:
            self.proc.send_signal(signal.SIGSTOP)

    def resume(self) -> None:
        if self.proc is not None:
            self.proc.send_signal(signal.SIGCONT)

    def kill(self) -> None:
        """SIGKILL, as a crash or a power cut would end it."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()

    def stop(self, timeout_s: float = STOP_TIMEOUT_S) -> int | None:
        """SIGTERM (after SIGCONT, in case it is paused), SIGKILL if it is still there after ``timeout_s``."""
        proc = self.proc
        if proc is None:
            return None
        if proc.poll() is None:
            proc.send_signal(signal.SIGCONT)
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        return proc.returncode

    def internal_errors(self) -> list[str]:
        """Why SITL stopped on an internal error, once per error, in order (from its output)."""
        if not self.output.exists():
            return []
        lines = [line.strip() for line in self.output.read_text(errors="replace").splitlines() if line.strip()]
        return [lines[i - 1] if i > 0 else line for i, line in enumerate(lines) if line.startswith(STACK_DUMP)]


def home_at(origin: tuple[float, float, float], start_ned_yaw: tuple[float, float, float]) -> tuple[float, float, float, float]:
    """SITL ``--home`` for a vehicle standing at ``start_ned_yaw`` (north m, east m, yaw deg) of the
    world whose origin (lat, lon, alt of the floor) is ``origin``."""
    north, east, yaw_deg = start_ned_yaw
    return (*moved_origin(origin, (north, east)), math.fmod(yaw_deg + 360.0, 360.0))
