"""What a navigation pipeline is to the daemon: the :class:`Pipeline` protocol, the config
section protocol, and the :class:`PipelineContext` its factory gets.

A pipeline module (``companion/nav/<name>.py`` or a plugin) defines a config dataclass (its
``pipelines.<name>`` section) with :meth:`PipelineSection.sensor_inputs`, a class following
:class:`Pipeline`, and registers a factory with :func:`companion.plugins.register_pipeline`.
The daemon subscribes the pipeline's handlers to the named sensors' drivers, calls
:meth:`Pipeline.step` every nav cycle, hands what it returns to the estimate-source selection,
and publishes :meth:`Pipeline.telemetry` streams; nothing in the daemon, CLI, harness or report
is written for one pipeline. Pipelines are plain numpy/OpenCV objects: no I/O, no asyncio, and
no import of ``companion.mavlink``, ``companion.telemetry``, zenoh or ``sitl`` (a test checks).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, TypeVar, runtime_checkable

from companion.health import Health
from companion.messages import Estimate, Guidance
from companion.timing import Timings

T = TypeVar("T")


class PipelineSection(Protocol):
    """A pipeline's config dataclass (a companion.schema dataclass)."""

    def sensor_inputs(self) -> dict[str, str]:
        """{key of this section that names a sensor: the kind that sensor must be}; the config
        check refuses a name that is not a sensor of that kind."""

    def moved(self, raw: dict[str, Any], offset: tuple[float, float], move_map: Callable[[str], str]) -> dict[str, Any]:
        """The section (``raw``, as written) for a local frame whose origin moved: ``offset``
        (north, east m) added to each of its positions (the harness passes minus the take-off
        point), its maps replaced by ``move_map(path)`` (a copy in the moved frame). The harness uses it to fly ArduPilot SITL, whose origin is its take-off point."""


class Pipeline(Protocol):
    """A navigation pipeline as the daemon sees it."""

    name: str
    timings: dict[str, Timings]  # per stage, milliseconds (published as system.stage_ms)
    telemetry_streams: tuple[str, ...]  # the telemetry streams :meth:`telemetry` may return

    def subscriptions(self) -> dict[str, Callable[[Any], None]]:
        """{sensor name: handler}: the daemon hands every message of that sensor to the handler
        (on the event loop, in order; a handler stores, the work is done in :meth:`step`)."""

    def step(self, now: float) -> list[Estimate]:
        """Advance to daemon time ``now`` (s); the estimates made this cycle (maybe none)."""

    def snapshot(self) -> dict[str, Any]:
        """Counters for telemetry (``system.pipelines.<name>``): plain numbers and dicts."""

    def telemetry(self, static_due: bool) -> dict[str, dict[str, Any]]:
        """{stream: payload} of what the pipeline computed since the previous call (nothing is
        computed again for it); with ``static_due``, also its static streams (e.g. a map) so a
        late listener gets them. Called at ``telemetry.scan_hz``."""

    def operating_area(self) -> tuple[tuple[float, float], tuple[float, float]] | None:
        """((north_min, east_min), (north_max, east_max)) m in LOCAL_NED that the pipeline can
        localize in (e.g. its map's bounds), the default companion geofence; None if unbounded."""


@runtime_checkable
class GuidanceSource(Protocol):
    """A pipeline that can fly the vehicle itself (optional; the daemon hands the first one it
    finds to the mission runner). While it is active the mission follows its :class:`Guidance`:
    the ``return_to_base`` mission step asks for it, and a pipeline may take over on its own (GNSS
    lost): the mission then drops its current step if ``failsafe.gnss_loss`` says so."""

    def guidance(self, now: float) -> Guidance | None:
        """What the pipeline wants the vehicle to do at daemon time ``now`` (s); None while it is
        not active."""

    def request_guidance(self, now: float, reason: str) -> str | None:
        """Start guiding (a mission step, a command); None if it did, else why it cannot."""


@dataclass
class PipelineContext:
    """What a pipeline factory may use besides its section: the whole config (sensor mounts,
    e.g. ``config.sensors[name].mount``), health to report into, and file loading."""

    config: Any  # companion.config.Config
    health: Health

    def load(self, key_path: str, value: str, loader: Callable[[Path], T]) -> T:
        """``loader(path)`` of the file a config key names (ConfigError at that key if bad)."""
        return self.config.load_referenced(key_path, value, loader)
