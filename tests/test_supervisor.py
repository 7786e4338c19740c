"""A supervised task that raises is logged, counted, reported and restarted."""

import asyncio

from companion.health import Health, State
from companion.supervisor import Supervisor


def test_crashing_task_is_restarted_and_reported(monkeypatch) -> None:
    monkeypatch.setattr("companion.supervisor.MIN_BACKOFF_S", 0.01)
    runs: list[int] = []

    async def main() -> tuple[int, Health, dict]:
        health = Health(asyncio.get_running_loop().time)
        sup = Supervisor(health)

        async def flaky() -> None:
            runs.append(1)
            if len(runs) < 3:
                raise RuntimeError("sensor exploded")
            await asyncio.Event().wait()

        sup.spawn("driver", flaky)
        for _ in range(200):
            await asyncio.sleep(0.01)
            if len(runs) >= 3:
                break
        snap = sup.snapshot()
        await sup.stop()
        return len(runs), health, snap

    count, health, snap = asyncio.run(main())
    assert count == 3
    assert snap["driver"]["restarts"] == 2
    assert "RuntimeError: sensor exploded" in snap["driver"]["last_error"]
    component = health.get("task:driver")
    assert component is not None and component.state == State.DEGRADED


def test_a_restarted_task_that_keeps_running_is_reported_ok_again(monkeypatch) -> None:
    monkeypatch.setattr("companion.supervisor.MIN_BACKOFF_S", 0.01)
    monkeypatch.setattr("companion.supervisor.RECOVERED_AFTER_S", 0.05)
    runs: list[int] = []

    async def main() -> Health:
        health = Health(asyncio.get_running_loop().time)
        sup = Supervisor(health)

        async def crashes_once() -> None:
            runs.append(1)
            if len(runs) == 1:
                raise RuntimeError("transient")
            await asyncio.Event().wait()

        sup.spawn("pipeline", crashes_once)
        await asyncio.sleep(0.3)
        await sup.stop()
        return health

    component = asyncio.run(main()).get("task:pipeline")
    assert component is not None and component.state == State.OK
    assert "after 1 restarts" in component.reason
