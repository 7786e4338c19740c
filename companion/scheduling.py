"""The daemon's CPU scheduling: realtime priority for the nav loop, where the system grants it.

The 50 Hz nav cycle waits for its tick in select(2); on a loaded board the kernel may run another
process when the tick falls due, and the cycle wakes late by however long that process keeps
the core. Under ``SCHED_FIFO`` the daemon preempts every ordinary process the moment its timer
expires. Measured on the 2-core SITL machine (README "Nav-loop timing"): the real-driver hover's
tick lateness p99 1.22-2.41 ms at normal priority, 0.47-1.55 ms at FIFO priority 10, lower in each
of four alternating pairs.

:func:`apply_realtime_priority` is called once, first thing in ``companion run``, from the main
thread before any other thread exists, so every thread the daemon starts later (telemetry,
recorder, zenoh's) inherits the policy; child processes do not (``SCHED_RESET_ON_FORK``).

:func:`single_threaded_blas` is called before that, before numpy is imported: numpy's OpenBLAS
would otherwise start a worker thread per core at import. The daemon's algebra is 2x2 to 6x6
matrices and thousand-point vectors, which OpenBLAS runs on the calling thread anyway; its
workers only cost CPU time at start-up (0.2 s of the real-driver hover's 0.6 s on the 2-core
test machine) and, inheriting ``SCHED_FIFO``, would spin at realtime priority whenever an
operation did hand them work.

Guards against a runaway loop starving the board: a low priority (below the kernel's threaded
interrupts and ArduPilot's own threads on a Linux autopilot), never on a single-CPU machine,
and the kernel's realtime throttling (``/proc/sys/kernel/sched_rt_runtime_us``: by default 5 %
of every second stays for ordinary processes). systemd's watchdog (WatchdogSec=) still kills a
loop that stops beating.
"""

from __future__ import annotations

import logging
import os
import resource
import sys

log = logging.getLogger("companion.scheduling")


BLAS_THREADS_VARIABLE = "OPENBLAS_NUM_THREADS"


def single_threaded_blas() -> None:
    """Have numpy's OpenBLAS run on the calling thread only (``OPENBLAS_NUM_THREADS=1``), unless
    the environment already sets the variable (an explicit choice is kept). Effective only before
    numpy is first imported: called later, it logs a warning and changes nothing."""
    if "numpy" in sys.modules:
        log.warning("numpy is already imported: its BLAS keeps the threads it started")
        return
    os.environ.setdefault(BLAS_THREADS_VARIABLE, "1")


def apply_realtime_priority(priority: int) -> None:
    """Put this process's calling thread (and so every thread it creates later) under
    ``SCHED_FIFO`` at ``priority`` (1-99; 0: leave the scheduling as it is).

    Never raises: a refusal (no ``CAP_SYS_NICE`` and an ``RLIMIT_RTPRIO`` below ``priority``, a
    kernel with realtime group scheduling, a single CPU) is logged as a warning and the daemon
    runs at its ordinary priority.
    """
    if priority <= 0:
        return
    if not hasattr(os, "sched_setscheduler"):
        _refused(priority, "this platform has no sched_setscheduler")
    elif (os.cpu_count() or 1) < 2:
        _refused(priority, "a single CPU: a busy realtime loop would leave nothing for the rest")
    else:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(priority))
        except OSError as exc:
            _refused(priority, f"{exc.strerror or exc} (RLIMIT_RTPRIO {_rtprio_limit()}; the unit's LimitRTPRIO= grants it)")
        else:
            log.info("SCHED_FIFO priority %d for every thread of the daemon", priority)


def _refused(priority: int, why: str) -> None:
    log.warning("SCHED_FIFO priority %d refused, normal scheduling: %s", priority, why)


def _rtprio_limit() -> str:
    """This process's soft RLIMIT_RTPRIO (Linux, where sched_setscheduler exists)."""
    soft, _ = resource.getrlimit(resource.RLIMIT_RTPRIO)
    return "unlimited" if soft == resource.RLIM_INFINITY else str(soft)
