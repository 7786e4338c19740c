"""The daemon's clock: real monotonic time, or simulation time in lockstep with the SITL vehicle.

All daemon code reads time from ``asyncio.get_running_loop().time()`` (seconds, monotonic) and
waits with ``asyncio.sleep``. In real operation that is CLOCK_MONOTONIC. In lockstep the
daemon runs on :class:`LockstepEventLoop`, whose ``time()`` is the simulation time: nothing in
the daemon needs a lockstep branch, and a run is deterministic for a given seed.

Lockstep protocol (the vehicle side is sitl/vehicle.py):

1. The vehicle sends TIMESYNC(tc1=0, ts1=t ns) after stepping its physics to ``t``.
2. The daemon dispatches everything received since the previous tick in one go, in order
   (so no task runs between two messages of one tick, however the datagrams trickle in),
   stops reading the link and lets everything those messages woke finish at its current
   time; once idle it advances its clock to ``t``, runs every timer due by ``t`` and
   everything those wake, and, once idle again, answers TIMESYNC(tc1=its time, ts1=t).
   Everything the daemon sent for time ``t`` precedes the answer on the link.
3. The vehicle waits for the answer, then sends the data sampled at ``t`` (which the daemon
   reads with its clock at ``t``) and steps on.
"""

from __future__ import annotations

import asyncio
import resource
import selectors
import time
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")

# select(2) takes file descriptors below FD_SETSIZE (1024 on Linux) only.
FD_SETSIZE = 1024


class _IdleAwareSelector(selectors.BaseSelector):
    """Wraps a selector; tells the loop when it is about to block, i.e. has nothing to run.

    asyncio's ``_run_once`` passes timeout 0 whenever callbacks are ready or a timer is due,
    so a non-zero (or None) timeout means the loop is idle at the current clock reading.
    """

    def __init__(self, inner: selectors.BaseSelector, on_idle: Callable[[], bool]) -> None:
        self._inner = inner
        self._on_idle = on_idle
        self.released = False

    def register(self, fileobj, events, data=None):  # type: ignore[no-untyped-def]
        return self._inner.register(fileobj, events, data)

    def unregister(self, fileobj):  # type: ignore[no-untyped-def]
        return self._inner.unregister(fileobj)

    def modify(self, fileobj, events, data=None):  # type: ignore[no-untyped-def]
        return self._inner.modify(fileobj, events, data)

    def select(self, timeout: float | None = None):  # type: ignore[no-untyped-def]
        if not self.released and (timeout is None or timeout > 0):
            if self._on_idle():
                # Idle callbacks may have scheduled work: poll without blocking.
                return self._inner.select(0)
            # Simulation time does not pass while we block: wait for I/O only.
            return self._inner.select(None)
        return self._inner.select(timeout)

    def close(self) -> None:
        self._inner.close()

    def get_key(self, fileobj):  # type: ignore[no-untyped-def]
        return self._inner.get_key(fileobj)

    def get_map(self):  # type: ignore[no-untyped-def]
        return self._inner.get_map()


class LockstepEventLoop(asyncio.SelectorEventLoop):
    """An asyncio loop whose ``time()`` is simulation time, advanced only by :meth:`advance`."""

    def __init__(self) -> None:
        self._sim_time = 0.0
        self._real_offset: float | None = None  # set by release()
        self._idle_callbacks: list[Callable[[], None]] = []
        self._lockstep_selector = _IdleAwareSelector(selectors.DefaultSelector(), self._run_idle_callbacks)
        super().__init__(self._lockstep_selector)

    def time(self) -> float:
        if self._real_offset is not None:
            return time.monotonic() - self._real_offset
        return self._sim_time

    def release(self) -> None:
        """Leave lockstep: from now on the clock runs in real time from the current reading.

        Used at shutdown, when the simulator has stopped ticking but timeouts must still expire.
        """
        if self._real_offset is None:
            self._real_offset = time.monotonic() - self._sim_time
            self._lockstep_selector.released = True

    def advance(self, t: float) -> None:
        """Move the clock forward to ``t`` seconds (never backwards; ignored once released)."""
        if self._real_offset is None and t > self._sim_time:
            self._sim_time = t

    def call_when_idle(self, callback: Callable[[], None]) -> None:
        """Run ``callback`` once, the next time the loop has nothing left to do at this time."""
        self._idle_callbacks.append(callback)

    def _run_idle_callbacks(self) -> bool:
        if not self._idle_callbacks:
            return False
        callbacks, self._idle_callbacks = self._idle_callbacks, []
        for callback in callbacks:
            try:
                callback()
            except Exception as exc:  # never let a callback break the selector
                self.call_exception_handler({"message": "lockstep idle callback failed", "exception": exc})
        return True


def realtime_event_loop() -> asyncio.AbstractEventLoop:
    """The daemon's real-time loop, waiting in select(2) rather than epoll(7).

    The 50 Hz nav cycle waits for its tick in the loop's selector. epoll's timeout counts whole
    milliseconds (Python rounds it up), so every tick woke 0-1 ms late (median 0.8 ms, p99 1.4 ms
    on the 2-core test machine, before any work); select's counts microseconds (median 0.33 ms,
    p99 0.5-0.7 ms there). The daemon watches a handful of descriptors, where select costs
    nothing more. select takes descriptors below FD_SETSIZE only: the process's soft
    RLIMIT_NOFILE is lowered to FD_SETSIZE if it is higher (systemd's default for a service is
    that already), so no descriptor it opens can be out of select's range.
    """
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY or soft > FD_SETSIZE:
        resource.setrlimit(resource.RLIMIT_NOFILE, (FD_SETSIZE, hard))
    return asyncio.SelectorEventLoop(selectors.SelectSelector())


def is_lockstep() -> bool:
    """True when the running loop is driven by the simulator's clock."""
    return isinstance(asyncio.get_running_loop(), LockstepEventLoop)


def now() -> float:
    """The daemon's monotonic time in seconds (simulation time in lockstep)."""
    return asyncio.get_running_loop().time()


async def sleep_until(due: float) -> None:
    """Wait until daemon time ``due`` (s); at once if it has passed."""
    await asyncio.sleep(max(0.0, due - now()))


async def compute(fn: Callable[..., T], *args: object) -> T:
    """``fn(*args)`` for CPU work that can take long (e.g. planning a trajectory, ~0.2 s).

    In real time it runs on a worker thread, so the nav loop and the setpoint stream keep their
    rates meanwhile. In lockstep it runs inline: computing costs no simulation time there (as
    every other computation of the daemon does), which keeps a seeded run deterministic.
    """
    if is_lockstep():
        return fn(*args)
    return await asyncio.to_thread(fn, *args)
