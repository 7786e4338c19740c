"""The daemon's sensors: one :class:`~drivers.base.SensorDriver` per configured sensor, each
around the backend its (kind, backend) names in the registry (companion/plugins.py). No code
here knows a particular sensor.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from companion import plugins
from companion.config import Config, SensorConfig, typed
from companion.health import Health
from drivers.base import SensorDriver
from drivers.checks import sensor_driver


@dataclass
class SensorContext:
    """What a backend factory may use besides its settings.

    ``link`` and ``autopilot`` are the daemon's MAVLink link and autopilot state (for sensors the
    autopilot carries: its IMU, its GNSS; and the simulator's ground truth). ``shared`` holds one
    object per key that several backends use (e.g. the simulator's truth source), made once.
    """

    config: Config
    health: Health
    link: Any = None
    autopilot: Any = None
    shared: dict[str, Any] = field(default_factory=dict)

    @property
    def base_dir(self) -> Path:
        """The config file's directory: relative paths in settings are resolved against it."""
        return self.config.base_dir

    def once(self, key: str, make: Any) -> Any:
        """``shared[key]``, made by ``make()`` the first time."""
        if key not in self.shared:
            self.shared[key] = make()
        return self.shared[key]


def check_sensor_files(cfg: Config) -> None:
    """Load the files every sensor's settings name (ConfigError at the key of the first bad one)."""
    for name, sensor in cfg.sensors.items():
        entry = plugins.backend(sensor.kind, sensor.backend)
        if entry is not None and entry.check_files is not None:
            entry.check_files(cfg, name)


def build_driver(name: str, sensor: SensorConfig, ctx: SensorContext) -> SensorDriver:
    """The frontend around the configured backend of sensor ``name`` (the config is validated, so
    the backend exists and its settings are valid)."""
    entry = plugins.backend(sensor.kind, sensor.backend)
    assert entry is not None, f"{sensor.kind}/{sensor.backend}: the config was not validated"
    return sensor_driver(sensor.kind, name, entry.build(name, typed(sensor.settings, entry.settings), ctx), ctx.health)
