"""Supervised asyncio tasks: a task that raises is logged, counted and restarted with backoff.

The daemon runs one supervised task per driver, pipeline and link. A crash never takes the
process down and never goes unnoticed: the exception is logged with its traceback, the
component's health turns degraded with the reason, and the task restarts after a backoff
that doubles from 0.5 s up to 30 s (and resets after a minute of clean running).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from companion.health import Health, State

log = logging.getLogger("companion.supervisor")

MIN_BACKOFF_S = 0.5
MAX_BACKOFF_S = 30.0
STABLE_AFTER_S = 60.0  # clean running that resets the backoff
RECOVERED_AFTER_S = 5.0  # clean running after a restart that turns the task's health back to ok


@dataclass
class TaskRecord:
    name: str
    restarts: int = 0
    last_error: str | None = None
    task: asyncio.Task | None = None


class Supervisor:
    """Owns the daemon's long-running tasks."""

    def __init__(self, health: Health) -> None:
        self.health = health
        self.tasks: dict[str, TaskRecord] = {}

    def spawn(self, name: str, factory: Callable[[], Awaitable[None]]) -> None:
        """Run ``factory()`` as task ``name``, restarting it whenever it raises or returns."""
        record = TaskRecord(name)
        record.task = asyncio.create_task(self._keep_running(record, factory), name=name)
        self.tasks[name] = record

    async def _keep_running(self, record: TaskRecord, factory: Callable[[], Awaitable[None]]) -> None:
        loop = asyncio.get_running_loop()
        backoff = MIN_BACKOFF_S
        while True:
            started = loop.time()
            recovered = loop.call_later(RECOVERED_AFTER_S, self._recovered, record) if record.restarts else None
            try:
                await factory()
                reason = "returned unexpectedly"
                log.error("task %s returned; restarting in %.1f s", record.name, backoff)
            except asyncio.CancelledError:
                raise
            except Exception as exc:
                reason = f"crashed: {type(exc).__name__}: {exc}"
                log.exception("task %s crashed; restarting in %.1f s", record.name, backoff)
            finally:
                if recovered is not None:
                    recovered.cancel()
            if loop.time() - started > STABLE_AFTER_S:
                backoff = MIN_BACKOFF_S
            record.restarts += 1
            record.last_error = reason
            self.health.report(f"task:{record.name}", State.DEGRADED, f"{reason} (restart {record.restarts})")
            await asyncio.sleep(backoff)
            backoff = min(backoff * 2, MAX_BACKOFF_S)

    def _recovered(self, record: TaskRecord) -> None:
        self.health.report(f"task:{record.name}", State.OK,
                           f"running again after {record.restarts} restarts (last: {record.last_error})")

    def snapshot(self) -> dict:
        """{name: {restarts, last_error}} for telemetry."""
        return {n: {"restarts": r.restarts, "last_error": r.last_error} for n, r in self.tasks.items()}

    async def cancel(self, name: str, timeout_s: float = 0.2) -> None:
        """Cancel task ``name`` (no restart) and wait (bounded) for it to finish; no-op if unknown."""
        record = self.tasks.get(name)
        if record is not None and record.task is not None:
            record.task.cancel()
            await asyncio.wait([record.task], timeout=timeout_s)

    async def stop(self, timeout_s: float = 1.0) -> None:
        """Cancel every task and wait (bounded) for them to finish."""
        tasks = [r.task for r in self.tasks.values() if r.task is not None]
        for task in tasks:
            task.cancel()
        if tasks:
            await asyncio.wait(tasks, timeout=timeout_s)
