"""The lockstep event loop: time moves only when advanced; timers due run before the idle ack."""

import asyncio

from companion.clock import LockstepEventLoop


def test_timers_fire_on_simulation_time_and_before_the_idle_callback() -> None:
    loop = LockstepEventLoop()
    events: list[tuple[str, float]] = []

    async def ticker() -> None:
        while True:
            await asyncio.sleep(0.02)
            events.append(("timer", round(loop.time(), 6)))

    async def simulator() -> None:
        for k in range(1, 11):
            acked = asyncio.Event()
            loop.advance(k * 0.01)
            loop.call_when_idle(acked.set)
            await acked.wait()
            events.append(("ack", round(loop.time(), 6)))

    async def main() -> None:
        task = asyncio.create_task(ticker())
        await asyncio.sleep(0)  # let the ticker arm its first timer at t = 0
        await simulator()
        task.cancel()

    try:
        loop.run_until_complete(main())
    finally:
        loop.close()
    timers = [t for kind, t in events if kind == "timer"]
    assert timers == [0.02, 0.04, 0.06, 0.08, 0.1]
    for t in timers:  # a timer due at t runs before tick t is acknowledged
        assert events.index(("timer", t)) < events.index(("ack", t))


def test_release_makes_timeouts_expire_in_real_time() -> None:
    loop = LockstepEventLoop()

    async def main() -> bool:
        loop.release()
        try:
            await asyncio.wait_for(asyncio.Event().wait(), 0.05)
        except TimeoutError:
            return True
        return False

    try:
        assert loop.run_until_complete(main())
    finally:
        loop.close()
