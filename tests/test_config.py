"""Config loading: every error names file, key path and line; the reference stays current."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from companion.config import ConfigError, load_config
from companion.config_reference import render
from companion.mission.steps import load_mission

REPO = Path(__file__).resolve().parent.parent
ORIGIN = "origin: {lat: 1.0, lon: 2.0, alt: 3.0}\n"


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "c.yaml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("name", ["sitl.yaml", "example-ardupilot-hokuyo.yaml"])
def test_shipped_configs_are_valid(name: str) -> None:
    cfg = load_config(REPO / "config" / name)
    if cfg.mission.file:
        load_mission(cfg.resolve(cfg.mission.file))


def test_the_example_vehicle_config_runs_the_lidar_pipeline_on_the_map_beside_it(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """What systemd/install.sh installs flies on the lidar pipeline; without the building's map
    beside it the config is refused (exit 2, the key and the missing file named), with it accepted."""
    from companion.cli import main

    config = tmp_path / "companion.yaml"
    shutil.copy(REPO / "config" / "example-ardupilot-hokuyo.yaml", config)
    assert "lidar" in load_config(config).pipelines.enabled
    assert main(["check-config", str(config)]) == 2
    err = capsys.readouterr().err
    assert "pipelines.lidar.map" in err and "building.yaml" in err
    shutil.copy(REPO / "config" / "worlds" / "arena.yaml", tmp_path / "building.yaml")
    assert main(["check-config", str(config)]) == 0


def test_defaults_fill_everything_but_the_origin(tmp_path: Path) -> None:
    cfg = load_config(write(tmp_path, ORIGIN))
    assert cfg.vehicle.compid == 197
    assert cfg.mavlink.estimate_rate_hz == 30.0
    assert cfg.origin.alt == 3.0


@pytest.mark.parametrize("text, line, path, words", [
    (ORIGIN + "mavlnk: {}\n", 2, "mavlnk", "unknown key"),
    (ORIGIN + "mavlink:\n  heartbeat_hz: fast\n", 3, "mavlink.heartbeat_hz", "expected a number"),
    (ORIGIN + "mavlink:\n  estimate_rate_hz: 500\n", 3, "mavlink.estimate_rate_hz", "within [4, 100]"),
    ("origin: {lat: 1.0, lon: 2.0}\n", 1, "origin.alt", "required key is missing"),
    (ORIGIN + "sensors:\n  lidar:\n    kind: sonar\n    backend: real\n", 4, "sensors.lidar.kind", "must be one of"),
    (ORIGIN + "vehicle:\n  sysid: true\n", 3, "vehicle.sysid", "expected an integer"),
    (ORIGIN + "telemetry:\n  listen: tcp/127.0.0.1:7447\n", 3, "telemetry.listen", "expected a list"),
    (ORIGIN + "mavlink: [\n", 3, "", "invalid YAML"),
    (ORIGIN + "mavlink:\n  url: a\n  url: b\n", 4, "mavlink.url", "duplicate key"),
    (ORIGIN + "origin: {lat: 1, lon: 2, alt: 3}\n", 2, "origin", "duplicate key"),
])
def test_errors_name_file_key_and_line(tmp_path: Path, text: str, line: int, path: str, words: str) -> None:
    file = write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        load_config(file)
    assert err.value.file == str(file)
    assert err.value.line == line
    assert err.value.key_path == path
    assert words in err.value.message
    assert str(err.value).startswith(f"{file}:{line}: ")


def test_nan_is_rejected_as_a_number(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="finite"):
        load_config(write(tmp_path, "origin: {lat: .nan, lon: 2, alt: 3}\n"))


def test_check_config_exits_2_with_the_location(tmp_path: Path) -> None:
    file = write(tmp_path, ORIGIN + "mavlink:\n  estimate_rate_hz: 500\n")
    proc = subprocess.run([sys.executable, "-m", "companion.cli", "check-config", str(file)],
                          capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 2
    assert f"{file}:3: mavlink.estimate_rate_hz" in proc.stderr


def test_mission_with_two_actions_in_one_step_is_rejected(tmp_path: Path) -> None:
    file = tmp_path / "m.yaml"
    file.write_text("name: x\nsteps:\n  - mode: GUIDED\n  - {hold: {seconds: 1}, land: {}}\n")
    with pytest.raises(ConfigError) as err:
        load_mission(file)
    assert err.value.line == 4
    assert "exactly one" in err.value.message


def test_config_reference_document_is_current() -> None:
    """docs/config.md is generated; regenerate with `companion config-reference > docs/config.md`."""
    assert (REPO / "docs" / "config.md").read_text() == render()
