"""Periodic work waits for the nav cycle (NavLoop.after_cycle): it runs right after the cycle of
its tick, never at a tick, and still runs if the nav loop stops."""

from __future__ import annotations

import asyncio

from companion import clock
from companion.clock import LockstepEventLoop
from companion.navloop import NavLoop, NavOutputs
from companion.sdnotify import WatchdogGate

RATE_HZ = 50.0


def nav_loop(events: list[tuple[str, float]]) -> NavLoop:
    outputs = NavOutputs(pose=print, range=print, attitude=print, publish=lambda stream, payload: None)
    nav = NavLoop([], None, outputs, WatchdogGate(1.0, clock=clock.now), RATE_HZ, clock.now)
    nav.on_cycle = lambda now, made, chosen: events.append(("cycle", round(now, 6)))
    return nav


def run_in_simulation_time(main, until_s: float) -> None:  # type: ignore[no-untyped-def]
    """Run ``main()`` on the lockstep loop, its clock advanced in 1 ms steps to ``until_s``."""
    loop = LockstepEventLoop()

    async def simulator() -> None:
        task = asyncio.create_task(main())
        for _ in range(3):  # main and the tasks it starts begin at time 0
            await asyncio.sleep(0)
        for k in range(1, round(until_s * 1000) + 1):
            idle = asyncio.Event()
            loop.advance(k / 1000)
            loop.call_when_idle(idle.set)
            await idle.wait()
        task.cancel()

    loop.run_until_complete(simulator())
    loop.close()


def test_a_step_due_between_ticks_runs_right_after_the_next_cycle_and_one_due_on_a_tick_after_its_cycle() -> None:
    events: list[tuple[str, float]] = []
    nav = nav_loop(events)

    async def control() -> None:
        for due in (0.013, 0.035, 0.0595, 0.080):  # ticks at 0, 0.02, 0.04, ...
            await nav.after_cycle(due)
            events.append(("control", round(clock.now(), 6)))

    async def main() -> None:
        ticking = asyncio.create_task(nav.run())
        await control()
        ticking.cancel()

    run_in_simulation_time(main, 0.1)
    controls = [i for i, e in enumerate(events) if e[0] == "control"]
    assert [events[i] for i in controls] == [("control", 0.02), ("control", 0.04), ("control", 0.06), ("control", 0.08)]
    assert all(events[i - 1] == ("cycle", events[i][1]) for i in controls)  # the cycle of that tick, just before


def test_without_a_running_nav_loop_a_step_still_runs_two_periods_late() -> None:
    events: list[tuple[str, float]] = []
    nav = nav_loop(events)

    async def main() -> None:
        await nav.after_cycle(0.010)
        events.append(("control", round(clock.now(), 6)))

    run_in_simulation_time(main, 0.1)
    assert events == [("control", 0.05)]
