"""companion/scheduling.py: the daemon's realtime priority, granted or refused without harm.

Each case runs in a child process, so the test process itself never turns realtime."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PROBE = (
    "import logging, os, resource, sys\n"
    "logging.basicConfig(level=logging.INFO, stream=sys.stderr)\n"
    "from companion.scheduling import apply_realtime_priority\n"
    "if sys.argv[2] == 'unprivileged':  # what a service without LimitRTPRIO= is: no capability, limit 0\n"
    "    resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))\n"
    "    os.setgid(65534); os.setuid(65534)  # root's capabilities go with its uid\n"
    "apply_realtime_priority(int(sys.argv[1]))\n"
    "print(os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK, os.sched_getparam(0).sched_priority)\n"
)


def _probe(priority: int, who: str = "as-is") -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", PROBE, str(priority), who], cwd=REPO,
                          capture_output=True, text=True, timeout=30, check=True)


def _may_set_realtime() -> bool:
    import resource
    soft, _ = resource.getrlimit(resource.RLIMIT_RTPRIO)
    return os.geteuid() == 0 or soft == resource.RLIM_INFINITY or soft >= 5


def test_priority_zero_leaves_the_scheduling_alone() -> None:
    proc = _probe(0)
    assert proc.stdout.split() == [str(os.SCHED_OTHER), "0"]
    assert "WARNING" not in proc.stderr


@pytest.mark.skipif(not _may_set_realtime() or (os.cpu_count() or 1) < 2,
                    reason="this user may not use realtime priorities, or a single CPU")
def test_a_permitted_priority_puts_the_daemon_under_fifo_and_says_so() -> None:
    proc = _probe(5)
    assert proc.stdout.split() == [str(os.SCHED_FIFO), "5"]
    assert "SCHED_FIFO priority 5" in proc.stderr


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to become an unprivileged user in the probe")
def test_a_refused_priority_is_a_warning_and_the_daemon_runs_on_at_normal_priority() -> None:
    proc = _probe(5, "unprivileged")
    assert proc.stdout.split() == [str(os.SCHED_OTHER), "0"]
    assert "WARNING" in proc.stderr and "refused" in proc.stderr and "RLIMIT_RTPRIO 0" in proc.stderr


BLAS_PROBE = (
    "import logging, os, sys\n"
    "logging.basicConfig(level=logging.INFO, stream=sys.stderr)\n"
    "from companion.scheduling import single_threaded_blas\n"
    "if sys.argv[1] == 'late':\n"
    "    import numpy\n"
    "single_threaded_blas()\n"
    "import numpy\n"
    "print(len(os.listdir('/proc/self/task')))\n"
)


def _threads_after_numpy(when: str, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    clean = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    return subprocess.run([sys.executable, "-c", BLAS_PROBE, when], cwd=REPO, env={**clean, **env},
                          capture_output=True, text=True, timeout=30, check=True)


@pytest.mark.skipif((os.cpu_count() or 1) < 2 or not Path("/proc/self/task").is_dir(),
                    reason="needs Linux and 2 CPUs: OpenBLAS starts no worker on one")
def test_numpy_starts_no_blas_worker_threads_when_made_single_threaded_before_its_import() -> None:
    assert _threads_after_numpy("early", {}).stdout.split() == ["1"]
    # The probe can tell: with the user's own setting kept, or called too late, the workers are there.
    assert int(_threads_after_numpy("early", {"OPENBLAS_NUM_THREADS": "2"}).stdout) == 2
    late = _threads_after_numpy("late", {})
    assert int(late.stdout) > 1
    assert "numpy is already imported" in late.stderr
