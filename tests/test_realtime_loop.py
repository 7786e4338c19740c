"""The daemon's real-time event loop waits in select(2) (microsecond timeouts) and keeps every
descriptor the process can open inside select's range."""

import subprocess
import sys
import textwrap

PROBE = textwrap.dedent("""
    import asyncio, resource, selectors
    from companion.clock import FD_SETSIZE, realtime_event_loop

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (hard if hard != resource.RLIM_INFINITY else 4 * FD_SETSIZE, hard))
    raised = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    loop = realtime_event_loop()
    lowered = resource.getrlimit(resource.RLIMIT_NOFILE)[0]

    async def ticks():
        return await asyncio.gather(*(asyncio.sleep(0.001 * k, k) for k in range(3)))

    ticks = loop.run_until_complete(ticks())
    print(type(loop._selector).__name__, raised, lowered, "".join(str(ticks).split()))
""")


def test_realtime_loop_selects_and_lowers_a_descriptor_limit_above_fd_setsize() -> None:
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=60, check=True).stdout
    selector, raised, lowered, ticks = out.split(maxsplit=3)
    assert selector == "SelectSelector"
    assert int(lowered) == min(int(raised), 1024)
    assert ticks.strip() == "[0,1,2]"


def test_the_bench_measures_a_wake_up_of_the_loop_asleep_between_timers() -> None:
    # companion bench's per-wake-up CPU: a loop that spun instead of sleeping in select would cost
    # its whole period (5 ms at 200 Hz) per wake-up; one that never woke would report nothing.
    probe = "from companion.bench import wakeup_cpu_us; print(wakeup_cpu_us(200.0, 0.5))"
    cost_us = float(subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60,
                                   check=True).stdout)
    assert 0.0 < cost_us < 2500.0
