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
