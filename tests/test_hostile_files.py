"""Hostile or broken config, mission, world and key files: `companion check-config` and `companion run`
exit 2 within seconds with `file:line: key: message`, never hang, never print a traceback."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from companion.config import Config
from companion.mission.steps import Mission
from companion.schema import MAX_VALUES, TOO_DEEP, YAML_MAX_BYTES, SchemaError, load_text, read_regular_file
from tests.conftest import REPO, free_port

TIMEOUT_S = 15  # both commands end in about a second; a hang fails the test here instead of stalling CI
COMMANDS = ["check-config", "run"]
ELF_HEADER = b"\x7fELF\x02\x01\x01\x00" + bytes(8) + b"\x02\x00\x3e\x00\x01\x00\x00\x00\xc0\x10\x40\x00"  # 0xc0: not UTF-8
BAD_MISSION = "name: broken\nsteps:\n  - hold: {seconds: -1}\n"


def companion(command: str, config: Path | str) -> subprocess.CompletedProcess[str]:
    """`companion check-config CONFIG` or `companion run -c CONFIG`, killed (TimeoutExpired) after TIMEOUT_S."""
    args = ["check-config", str(config)] if command == "check-config" else ["run", "-c", str(config)]
    return subprocess.run([sys.executable, "-m", "companion.cli", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=TIMEOUT_S)


def assert_config_error(proc: subprocess.CompletedProcess[str], expected: str) -> None:
    """Exit 2, ``expected`` in stderr, no traceback."""
    assert proc.returncode == 2, proc.stderr
    assert expected in proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr


def replace_once(text: str, old: str, new: str) -> str:
    assert text.count(old) == 1, f"config/sitl.yaml no longer has {old!r} once"
    return text.replace(old, new)


def line_of(path: Path, needle: str) -> int:
    """The 1-based number of the first line of ``path`` that contains ``needle``."""
    return next(n for n, line in enumerate(path.read_text().splitlines(), start=1) if needle in line)


@pytest.fixture
def project(tmp_path: Path) -> Path:
    """config/sitl.yaml copied into tmp_path with its world and mission, runnable by `companion run` here:
    the autopilot link on a free loopback udpin port (nobody there), no telemetry."""
    text = (REPO / "config" / "sitl.yaml").read_text()
    text = replace_once(text, "url: udpout:127.0.0.1:14555", f"url: udpin:127.0.0.1:{free_port()}")
    text = replace_once(text, "\ntelemetry:\n", "\ntelemetry:\n  enabled: false\n")
    for name in ("worlds/arena.yaml", "missions/hover.yaml"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_text((REPO / "config" / name).read_text())
    config = tmp_path / "c.yaml"
    config.write_text(text)
    return config


def with_signing_key(config: Path, key_file: str) -> None:
    config.write_text(replace_once(config.read_text(), "\nmavlink:\n", f"\nmavlink:\n  signing_key_file: {key_file}\n"))


# -- the config file itself ---------------------------------------------------------------------------


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("kind", ["a character device", "a FIFO (named pipe)", "a directory"])
def test_a_config_that_is_not_a_regular_file_is_refused_without_reading_it(tmp_path: Path, command: str,
                                                                            kind: str) -> None:
    path = {"a character device": Path("/dev/zero"), "a FIFO (named pipe)": tmp_path / "fifo",
            "a directory": tmp_path}[kind]
    if kind.startswith("a FIFO"):
        os.mkfifo(path)  # no writer: opening it for reading the usual way would block for ever
    assert_config_error(companion(command, path), f"{path}: cannot read file: not a regular file but {kind}")


@pytest.mark.parametrize("command", COMMANDS)
def test_an_empty_config_is_an_error_on_line_1(tmp_path: Path, command: str) -> None:
    path = tmp_path / "c.yaml"
    path.write_text("# nothing but a comment\n")
    assert_config_error(companion(command, path), f"{path}:1: empty document: expected a mapping of keys")


@pytest.mark.parametrize("command", COMMANDS)
def test_a_binary_config_is_an_error_at_its_first_byte_that_is_not_utf8(tmp_path: Path, command: str) -> None:
    path = tmp_path / "c.yaml"
    path.write_bytes(ELF_HEADER)
    assert_config_error(companion(command, path), f"{path}:1: not UTF-8 text: byte 0xc0 at column 25")


@pytest.mark.parametrize("command", COMMANDS)
def test_invalid_utf8_in_the_middle_of_line_3_is_reported_on_line_3(tmp_path: Path, command: str) -> None:
    path = tmp_path / "c.yaml"
    path.write_bytes(b"origin:\n  lat: 1.0\n  lon: 2\xff.0\n  alt: 3.0\n")
    assert_config_error(companion(command, path), f"{path}:3: not UTF-8 text: byte 0xff at column 9")


@pytest.mark.parametrize("command", COMMANDS)
def test_a_config_larger_than_the_cap_is_refused(tmp_path: Path, command: str) -> None:
    path = tmp_path / "c.yaml"
    path.write_text("origin: {lat: 1, lon: 2, alt: 3}\n" + "#" * YAML_MAX_BYTES)
    assert_config_error(companion(command, path), f"{path}: cannot read file: larger than {YAML_MAX_BYTES} bytes")


# -- files the config names ---------------------------------------------------------------------------


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("key, needle, missing", [
    ("mission.file", "  file: missions/hover.yaml", "missions/hover.yaml"),
    ("pipelines.lidar.map", "  map: worlds/arena.yaml", "worlds/arena.yaml"),
    ("mavlink.signing_key_file", "  signing_key_file:", "keys/companion.key"),
])
def test_a_missing_referenced_file_is_reported_at_the_config_key_that_names_it(
        project: Path, command: str, key: str, needle: str, missing: str) -> None:
    with_signing_key(project, "keys/companion.key")  # nowhere yet
    (project.parent / "keys").mkdir()
    (project.parent / "keys" / "companion.key").write_text(bytes(range(32)).hex() + "\n")
    (project.parent / missing).unlink()
    assert_config_error(companion(command, project),
                        f"{project}:{line_of(project, needle)}: {key}: {project.parent.resolve() / missing}: "
                        "cannot read file: No such file or directory")


@pytest.mark.parametrize("command", COMMANDS)
def test_a_schema_error_in_the_mission_names_the_config_key_and_the_mission_line(project: Path, command: str) -> None:
    mission = project.parent / "missions" / "hover.yaml"
    mission.write_text(BAD_MISSION)
    assert_config_error(companion(command, project),
                        f"{project}:{line_of(project, '  file: missions/hover.yaml')}: mission.file: "
                        f"{project.parent.resolve() / 'missions' / 'hover.yaml'}:3: steps[0].hold.seconds: "
                        "must be within [0, 3600], got -1.0")


@pytest.mark.parametrize("command", COMMANDS)
def test_dev_zero_as_the_mission_is_refused_at_the_config_key(project: Path, command: str) -> None:
    project.write_text(replace_once(project.read_text(), "file: missions/hover.yaml", "file: /dev/zero"))
    assert_config_error(companion(command, project),
                        f"{project}:{line_of(project, '  file: /dev/zero')}: mission.file: /dev/zero: "
                        "cannot read file: not a regular file but a character device")


@pytest.mark.parametrize("command", COMMANDS)
def test_a_fifo_as_the_signing_key_is_refused_without_blocking(project: Path, command: str) -> None:
    os.mkfifo(project.parent / "key.fifo")
    with_signing_key(project, "key.fifo")
    assert_config_error(companion(command, project),
                        f"{project}:{line_of(project, '  signing_key_file:')}: mavlink.signing_key_file: "
                        f"{project.parent.resolve() / 'key.fifo'}: cannot read file: not a regular file but a FIFO")


@pytest.mark.parametrize("command", COMMANDS)
def test_a_missing_replay_recording_is_reported_at_its_sensor_key(project: Path, command: str) -> None:
    text = replace_once(project.read_text(), "    backend: sim\n    mount: {position_m: [0.05",
                        "    backend: replay\n    mount: {position_m: [0.05")
    project.write_text(replace_once(text, "settings: {model: URG-04LX, seed: 2, whole_mm: true}", "settings: {file: scans.npz}"))
    assert_config_error(companion(command, project),
                        f"{project}:{line_of(project, 'settings: {file: scans.npz}')}: sensors.lidar_v.settings.file: "
                        f"{project.parent.resolve() / 'scans.npz'}: cannot read file: No such file or directory")


def test_a_camera_without_a_driver_and_a_dotted_sensor_name_are_config_errors_not_crashes(project: Path) -> None:
    project.write_text(replace_once(project.read_text(), "\nsensors:\n",
                                    "\nsensors:\n  cam.front:\n    kind: camera\n    backend: replay\n"))
    assert_config_error(companion("check-config", project),
                        "sensors.cam.front: a sensor name is letters, digits, '_' and '-'")


def test_check_config_accepts_the_unbroken_project(project: Path) -> None:
    proc = companion("check-config", project)
    assert proc.returncode == 0, proc.stderr


# -- the reader and the YAML loader -------------------------------------------------------------------


def test_the_reader_takes_a_file_of_exactly_the_cap_and_refuses_one_byte_more(tmp_path: Path) -> None:
    path = tmp_path / "f"
    path.write_bytes(b"x" * 100)
    assert read_regular_file(path, 100) == b"x" * 100
    with pytest.raises(OSError, match="larger than 99 bytes"):
        read_regular_file(path, 99)


def test_aliases_that_expand_without_end_stop_at_the_value_limit() -> None:
    """A "billion laughs": 1000 steps, each an alias of one step of 1000 waypoints."""
    waypoints = ", ".join(f"*w{i % 2}" for i in range(1000))
    text = ("name: laughs\nsteps:\n"
            f"  - &s {{fly: {{waypoints: [&w0 {{position: [0, 0, -1]}}, &w1 {{position: [1, 0, -1]}}, {waypoints}]}}}}\n"
            + "  - *s\n" * 1000)
    with pytest.raises(SchemaError, match=f"more than {MAX_VALUES} values"):
        load_text(text, Mission)


def test_lists_nested_too_deeply_are_an_error_not_a_crash() -> None:
    nested = "[" * 900 + "]" * 900  # libyaml's own limit is 1000 levels; building them recursed past Python's
    with pytest.raises(SchemaError, match=TOO_DEEP):
        load_text(f"origin: {{lat: 1, lon: 2, alt: 3}}\nsensors:\n  x:\n    kind: lidar\n    backend: sim\n"
                  f"    settings: {{deep: {nested}}}\n", Config)


def test_run_with_telemetry_on_stops_at_a_bad_mission_before_any_task_starts(project: Path) -> None:
    text = replace_once(project.read_text(), "\ntelemetry:\n  enabled: false\n", "\ntelemetry:\n")
    text = replace_once(text, "tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}")
    project.write_text(replace_once(text, "file: missions/hover.yaml", "file: missions/not-there.yaml"))
    assert_config_error(companion("run", project), f"{project}:{line_of(project, 'not-there.yaml')}: mission.file: ")


def test_a_control_character_after_multibyte_text_is_reported_on_its_own_line(tmp_path: Path) -> None:
    config = tmp_path / "c.yaml"
    config.write_text("a: 1\nb: 2\nc: 3\nd: \"" + "é" * 31 + "\"\ne: \"x\x01\"\n", encoding="utf-8")
    assert_config_error(companion("check-config", config), f"{config}:5: invalid YAML: character #x0001 is not allowed")
