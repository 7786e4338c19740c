"""Which backend implements which (kind, backend) and how its `settings` are validated.

Settings are plain YAML mappings in the config; each backend declares a settings dataclass
(companion.schema), so a misspelled or out-of-range setting is reported with the config's
file, key path and line like any other key. Kinds without a driver in this version (camera,
imu, gnss) are not validated here: the daemon reports such sensors lost at start.
"""

from __future__ import annotations

from typing import Any

import yaml

from companion.schema import SchemaError, load_text


def settings_types() -> dict[tuple[str, str], type]:
    """(kind, backend) -> settings dataclass, for every backend that exists."""
    from drivers.hokuyo import HokuyoSettings
    from drivers.lidar_replay import ReplayLidarSettings
    from drivers.lidar_sim import SimLidarSettings

    return {("lidar", "real"): HokuyoSettings, ("lidar", "sim"): SimLidarSettings,
            ("lidar", "replay"): ReplayLidarSettings}


def build_settings(kind: str, backend: str, raw: dict[str, Any]) -> Any:
    """The typed settings of a backend; SchemaError (key path relative to `settings`) if invalid."""
    schema = settings_types().get((kind, backend))
    if schema is None:
        raise SchemaError("", "", None, f"no {kind} driver with backend {backend!r} in this version")
    return load_text(yaml.safe_dump(raw), schema)


def check_settings(kind: str, backend: str, raw: dict[str, Any]) -> tuple[str, str] | None:
    """For SensorConfig.validate: (key path, message) of the first problem, or None."""
    if (kind, backend) not in settings_types():
        return None
    try:
        build_settings(kind, backend, raw)
    except SchemaError as exc:
        return (f"settings.{exc.key_path}" if exc.key_path else "settings"), exc.message
    return None
