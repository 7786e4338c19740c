"""Time and run loops of the simulated vehicle: sim time, real time, lockstep, stopping.

See the lockstep protocol in sitl/vehicle/__init__.py.
"""

from __future__ import annotations

import math
import select
import sys
import time

from pymavlink.dialects.v20 import ardupilotmega as mav

from sitl.plane import SimulatedPlane
from sitl.vehicle.link import next_due

LOG_SAMPLE_INTERVAL_US = 20_000  # truth / estimate in the flight log at 50 Hz
LOCKSTEP_WARN_S = 15.0
LOCKSTEP_FAIL_S = 60.0
EXIT_LOCKSTEP_TIMEOUT = 3


class _Shutdown(Exception):
    """Ends the run: the log is written and ``code`` becomes the exit status."""

    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


class RunLoopMixin:
    """Part of :class:`sitl.vehicle.core.Vehicle` (which sets the attributes): time and the run loops."""

    # ------------------------------------------------------------------ time

    @property
    def t_us(self) -> int:
        """Simulation time of the current tick, integer microseconds."""
        return self.n * self.tick_us

    @property
    def t(self) -> float:
        """Simulation time of the current tick (s)."""
        return self.t_us / 1e6

    def _now(self) -> float:
        """Simulation time (s) for a message received now: the tick in lockstep, the wall clock else."""
        if self.cfg.lockstep or self.t0 is None:
            return self.t
        return time.monotonic() - self.t0

    # ------------------------------------------------------------------ run loops

    def request_stop(self) -> None:
        """Ask the run to end (signal-safe: also wakes a waiting select())."""
        self._stop_requested = True
        try:
            self._wake_w.send(b"\0")
        except OSError:
            pass

    @property
    def wake_fd(self) -> int:
        """File descriptor for signal.set_wakeup_fd()."""
        return self._wake_w.fileno()

    def run(self) -> int:
        """Run until --seconds, a stop request or a lockstep failure; write the log; exit status."""
        code = 0
        self._observe()
        try:
            if self.cfg.lockstep:
                self._run_lockstep()
            else:
                self._run_realtime()
        except _Shutdown as stop:
            code = stop.code
        finally:
            self._write_log()
        return code

    def close(self) -> None:
        """Release the sockets (after the signal handlers that use the wake-up pipe are gone)."""
        for link in self.links:
            link.close()
        self._wake_r.close()
        self._wake_w.close()

    def _end_tick(self) -> float:
        """Number of ticks to run (inf without --seconds)."""
        if self.cfg.seconds is None:
            return math.inf
        return math.ceil(round(self.cfg.seconds * 1e6) / self.tick_us)

    def _run_realtime(self) -> None:
        self.t0 = time.monotonic()
        self._unix_at_zero_s = time.time()
        self.log.monotonic_at_sim_zero = self.t0
        end = self._end_tick()
        while self.n < end:
            if self._stop_requested:
                raise _Shutdown(0)
            self._send_due()
            self._step()
            self._wait_until(self.t0 + self.t)

    def _run_lockstep(self) -> None:
        self._await_companion()
        self._sync()
        end = self._end_tick()
        while self.n < end:
            self._send_due()
            self._step()
            self._sync()

    def _step(self) -> None:
        """Advance the copter one tick and record what changed."""
        if self.cfg.events:
            self._apply_events()
        self.copter.step(self.tick_us / 1e6)
        self.n += 1
        self.log.add_external_nav(self.t, bool(self.copter.estimate.ext_nav_in_use), self.tick_us / 1e6)
        self._observe()

    def _apply_events(self) -> None:
        """The ``--event`` disturbances active at the current time (summed where they overlap)."""
        active = [e for e in self.cfg.events if e[0] <= self.t < e[1]]
        if isinstance(self.copter, SimulatedPlane):
            self.copter.set_rudder(math.radians(sum(e[2] for e in active)))
        self.copter.set_tilt_fault(math.radians(sum(e[3] for e in active)), math.radians(sum(e[4] for e in active)))

    def _send_due(self) -> None:
        """Log sample and every stream due at the current tick, on every link."""
        if self.t_us >= self._next_sample_us:
            self._record_sample()
            self._next_sample_us = next_due(self._next_sample_us, LOG_SAMPLE_INTERVAL_US, self.t_us)
        built: dict[int, mav.MAVLink_message | None] = {}
        for link in self.links:
            for msgid in link.due(self.t_us):
                if msgid not in built:
                    built[msgid] = self._builders[msgid]()
                msg = built[msgid]
                if msg is None:
                    continue
                if msgid == mav.MAVLINK_MSG_ID_SIM_STATE:  # its position to the micrometre (sitl/truth.py)
                    mocap = mav.MAVLINK_MSG_ID_ATT_POS_MOCAP
                    if mocap not in built:
                        built[mocap] = self._truth_position()
                    link.send(built[mocap])
                link.send(msg)

    def _wait_until(self, wall_deadline: float) -> None:
        """Handle incoming traffic until time.monotonic() reaches ``wall_deadline`` (real time)."""
        while True:
            self._service_all()
            remaining = wall_deadline - time.monotonic()
            if remaining <= 0:
                return
            self._select(remaining)

    def _await_companion(self) -> None:
        """Lockstep start: wait for the companion's HEARTBEAT, sending ours at 1 Hz wall time."""
        next_heartbeat = time.monotonic()
        while True:
            if time.monotonic() >= next_heartbeat:
                heartbeat = self._heartbeat()
                for link in self.links:
                    link.send(heartbeat)
                next_heartbeat += 1.0
            self._service_all()
            if self._companion_heard:
                return
            self._select(next_heartbeat - time.monotonic())

    def _sync(self) -> None:
        """Lockstep: TIMESYNC(tc1=0, ts1=t ns) to the companion, then handle traffic until its reply.

        The reply is a TIMESYNC on the companion link with tc1 != 0 and the same ts1. Messages
        behind it on the companion link stay queued for the next tick, so what the companion
        sends between two replies is always handled at the same simulation time.
        """
        self._awaited_ts1 = self.t_us * 1000
        self.companion.send(mav.MAVLink_timesync_message(0, self._awaited_ts1))
        started = time.monotonic()
        warned = False
        while not self._service_all():
            waited = time.monotonic() - started
            if waited >= LOCKSTEP_FAIL_S:
                print(f"sitl.vehicle: lockstep: no TIMESYNC reply for tick {self.n} (t={self.t:.3f} s) "
                      f"within {LOCKSTEP_FAIL_S:.0f} s; giving up", file=sys.stderr, flush=True)
                raise _Shutdown(EXIT_LOCKSTEP_TIMEOUT)
            if waited >= LOCKSTEP_WARN_S and not warned:
                print(f"sitl.vehicle: lockstep: no TIMESYNC reply for tick {self.n} (t={self.t:.3f} s) "
                      f"within {LOCKSTEP_WARN_S:.0f} s; still waiting", file=sys.stderr, flush=True)
                warned = True
            self._select((LOCKSTEP_FAIL_S if warned else LOCKSTEP_WARN_S) - waited)
        self._awaited_ts1 = None

    def _select(self, timeout_s: float) -> None:
        """Block until a link or the stop pipe is readable, or ``timeout_s`` passes."""
        fds = [link.fileno() for link in self.links] + [self._wake_r.fileno()]  # tcpin's fd changes
        readable, _, _ = select.select(fds, [], [], max(0.0, timeout_s))
        if self._wake_r.fileno() in readable:
            try:
                while self._wake_r.recv(64):
                    pass
            except BlockingIOError:
                pass
        if self._stop_requested:
            raise _Shutdown(0)
