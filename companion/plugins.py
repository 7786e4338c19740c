"""The registries the daemon builds from: sensor backends by (kind, backend), pipelines by name.

A backend module registers itself with :func:`register_backend`, a pipeline module with
:func:`register_pipeline`, at import. The daemon, ``check-config``, the harness and the report
walk these registries; none of them has code for a particular sensor or pipeline.

Where registrations come from (:func:`load`):

- every module of the ``drivers`` package and of ``companion.nav``, subpackages included (a new
  file there is found without editing any list; modules named ``bench*`` are skipped: they are tools, not parts);
- the modules a config lists under ``plugins`` (e.g. ``sitl.sim_backends``, which registers
  the simulated backends, or a user's own package). This is how the simulator plugs in: the
  service never imports ``sitl`` itself.

docs/extending.md walks through adding a backend and a pipeline.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

BUILTIN_PACKAGES = ("drivers", "companion.nav")


@dataclass(frozen=True)
class BackendEntry:
    """One sensor backend: how its ``settings`` mapping is typed and how it is built.

    ``build(name, settings, ctx)`` returns a :class:`drivers.base.Backend`; ``ctx`` is the
    daemon's :class:`companion.sensors.SensorContext` (the config, the autopilot link...).
    ``check_files(cfg, name)``, if given, loads the files the sensor's settings name (raising
    ConfigError at their key) so that ``check-config`` finds a bad one before a flight.
    """

    kind: str
    backend: str
    settings: type
    build: Callable[..., Any]
    check_files: Callable[[Any, str], None] | None = None
    module: str = ""


@dataclass(frozen=True)
class PipelineEntry:
    """One pipeline: its config section type (``pipelines.<name>``) and its factory
    ``build(section, ctx) -> Pipeline`` (ctx: :class:`companion.pipeline.PipelineContext`).
    ``check_files(cfg, section)``, if given, loads the files the section names. ``advise(cfg,
    section)``, if given, returns warnings about settings that load but may fail in flight (e.g. a
    camera too narrow for its beams): ``check-config`` prints them, the daemon logs them at start.
    ``poses``: the pipeline produces poses (False for one that only gives attitude or range estimates).
    ``heading``: the yaw of its poses is a heading measurement of its own (walls, floor markers);
    False for one that carries the autopilot's heading forward (the autopilot must then keep its
    compass: ``companion setup-autopilot`` turns it off only when every pose source measures heading).
    ``position_sigma_m``: the typical 1-sigma of its horizontal positions, m: ArduPilot 4.0's EKF2
    ignores the covariance sent with an estimate and takes ``EK2_POSNE_M_NSE`` instead, which
    ``setup-autopilot`` sets to the largest of the pose sources' (an EKF told 0.1 m about a
    GNSS-grade source was pulled about by its noise until its heading parted from its gyro)."""

    name: str
    config: type
    build: Callable[..., Any]
    check_files: Callable[[Any, Any], None] | None = None
    poses: bool = True  # it produces pose estimates (a candidate source for the autopilot)
    module: str = ""
    advise: Callable[[Any, Any], list[str]] | None = None
    heading: bool = True  # its poses' yaw is measured by the pipeline (not the autopilot's heading carried on)
    position_sigma_m: float = 0.1  # typical 1-sigma of its horizontal positions, m


_BACKENDS: dict[tuple[str, str], BackendEntry] = {}
_PIPELINES: dict[str, PipelineEntry] = {}
_LOADED: set[str] = set()


def register_backend(kind: str, backend: str, settings: type,
                     check_files: Callable[[Any, str], None] | None = None) -> Callable[[Any], Any]:
    """Class or function decorator: ``build(name, settings, ctx)`` makes a (kind, backend)."""
    def decorate(build: Any) -> Any:
        _add(_BACKENDS, (kind, backend), BackendEntry(kind, backend, settings, build, check_files, build.__module__))
        return build
    return decorate


def register_pipeline(name: str, config: type, check_files: Callable[[Any, Any], None] | None = None,
                      poses: bool = True, advise: Callable[[Any, Any], list[str]] | None = None,
                      heading: bool = True, position_sigma_m: float = 0.1) -> Callable[[Any], Any]:
    """Class or function decorator: ``build(section, ctx)`` makes the pipeline ``name`` (the
    arguments: :class:`PipelineEntry`)."""
    def decorate(build: Any) -> Any:
        _add(_PIPELINES, name, PipelineEntry(name, config, build, check_files, poses, build.__module__, advise,
                                             heading, position_sigma_m))
        return build
    return decorate


def _add(table: dict, key: Any, entry: Any) -> None:
    old = table.get(key)
    if old is not None and old.module != entry.module:
        raise ValueError(f"{key!r} is registered twice: by {old.module} and by {entry.module}")
    table[key] = entry


def load(plugins: Iterable[str] = ()) -> None:
    """Import the built-in packages' modules and the given plugin modules (once each).

    Raises ImportError naming the module that failed.
    """
    for package in BUILTIN_PACKAGES:
        if package in _LOADED:
            continue
        pkg = importlib.import_module(package)
        for info in pkgutil.walk_packages(pkg.__path__, prefix=f"{package}."):
            if not info.name.rpartition(".")[2].startswith("bench"):
                importlib.import_module(info.name)
        _LOADED.add(package)
    for name in plugins:
        if name not in _LOADED:
            importlib.import_module(name)
            _LOADED.add(name)


def backend(kind: str, name: str) -> BackendEntry | None:
    return _BACKENDS.get((kind, name))


def backends() -> list[BackendEntry]:
    return sorted(_BACKENDS.values(), key=lambda e: (e.kind, e.backend))


def pipeline(name: str) -> PipelineEntry | None:
    return _PIPELINES.get(name)


def pipelines() -> list[PipelineEntry]:
    return sorted(_PIPELINES.values(), key=lambda e: e.name)
