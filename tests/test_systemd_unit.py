"""The systemd unit (checked by systemd-analyze itself) and the install script's dry run."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
UNIT = REPO / "systemd" / "companion.service"
INSTALL = REPO / "systemd" / "install.sh"
SYSTEMD_ANALYZE = shutil.which("systemd-analyze")

needs_systemd_analyze = pytest.mark.skipif(
    SYSTEMD_ANALYZE is None, reason="systemd-analyze not installed (apt install systemd)"
)


def parse_unit(text: str) -> dict[str, list[tuple[str, str]]]:
    """Sections of a unit file as lists of (key, value), in order, repeats kept."""
    sections: dict[str, list[tuple[str, str]]] = {}
    current: list[tuple[str, str]] | None = None
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1], [])
            continue
        assert current is not None, f"assignment outside a section: {raw!r}"
        key, sep, value = line.partition("=")
        assert sep, f"not an assignment: {raw!r}"
        current.append((key.strip(), value.strip()))
    return sections


def values(sections: dict[str, list[tuple[str, str]]], section: str, key: str) -> list[str]:
    return [v for k, v in sections.get(section, []) if k == key]


UNIT_TEXT = UNIT.read_text(encoding="utf-8")
SECTIONS = parse_unit(UNIT_TEXT)


# --- systemd-analyze verify ---------------------------------------------------------------


def verifiable(text: str) -> str:
    """The unit made checkable on a machine where it is not installed.

    ExecStart= must name an existing executable (verify checks it) and the service user may
    not exist, so point ExecStart= at /bin/true (same arguments) and run as root. Nothing
    else changes, so every other key and value is still checked.
    """
    out = []
    for line in text.splitlines():
        if line.startswith(("User=", "Group=")):
            continue
        if line.startswith("ExecStart="):
            line = re.sub(r"^ExecStart=\S+", "ExecStart=/bin/true", line)
        out.append(line)
    return "\n".join(out) + "\n"


def verify(text: str) -> tuple[int, list[str]]:
    """Run systemd-analyze verify on ``text``; return its exit code and complaint lines.

    verify exits 0 after merely warning about an unknown key or an unparsable value, so
    every output line counts as a complaint, except lines about *other* unit files (a
    broken unit installed on the test machine is not ours to fix).
    """
    assert SYSTEMD_ANALYZE is not None
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp).resolve() / "companion.service"
        path.write_text(text, encoding="utf-8")
        proc = subprocess.run(
            [SYSTEMD_ANALYZE, "verify", str(path)],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, "SYSTEMD_COLORS": "0", "SYSTEMD_PAGER": ""},
            timeout=60,
            check=False,
        )
    complaints = []
    for line in proc.stdout.splitlines():
        other = re.match(r"(/\S+?\.[a-z]+):\d+:", line.strip())
        if line.strip() and not (other and other.group(1) != str(path)):
            complaints.append(line)
    return proc.returncode, complaints


@needs_systemd_analyze
def test_unit_verifies_without_any_complaint() -> None:
    returncode, complaints = verify(verifiable(UNIT_TEXT))
    assert complaints == []
    assert returncode == 0


def _inject(text: str, section: str, line: str) -> str:
    header = f"[{section}]\n"
    assert header in text
    return text.replace(header, header + line + "\n", 1)


@needs_systemd_analyze
@pytest.mark.parametrize(
    ("section", "line", "mentioned"),
    [
        ("Service", "WatchdogSecc=5s", "WatchdogSecc"),  # misspelled key
        ("Service", "Restart=sometimes", "sometimes"),  # bad value
        ("Service", "ProtectSystem=strickt", "strickt"),  # bad value, no "Invalid" in text
        ("Service", "StartLimitIntervalSec=60s", "StartLimitIntervalSec"),  # wrong section
        ("Unit", "Wantz=network-online.target", "Wantz"),
    ],
)
def test_verify_catches_mistakes(section: str, line: str, mentioned: str) -> None:
    """Proof that the check above fails on a broken unit although verify exits 0."""
    returncode, complaints = verify(_inject(verifiable(UNIT_TEXT), section, line))
    assert complaints, f"systemd-analyze said nothing about {line!r}"
    assert any(mentioned in c for c in complaints)
    assert returncode == 0  # why the output, not the exit code, must be checked


# --- required directives ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("section", "key", "value"),
    [
        ("Unit", "After", "network-online.target"),
        ("Unit", "Wants", "network-online.target"),
        ("Service", "Type", "notify"),
        ("Service", "NotifyAccess", "main"),
        (
            "Service",
            "ExecStart",
            "/opt/companion/venv/bin/companion run -c /etc/companion/companion.yaml",
        ),
        ("Service", "WatchdogSec", "5s"),
        ("Service", "Restart", "on-failure"),
        ("Service", "RestartSec", "2s"),
        ("Service", "TimeoutStopSec", "5s"),
        ("Service", "User", "companion"),
        ("Service", "Group", "companion"),
        ("Service", "Environment", "PYTHONUNBUFFERED=1"),
        ("Service", "Nice", "-10"),
        ("Service", "CPUWeight", "1000"),
        ("Service", "StateDirectory", "companion"),
        ("Service", "ReadWritePaths", "/var/lib/companion"),
        ("Service", "NoNewPrivileges", "yes"),
        ("Service", "ProtectSystem", "strict"),
        ("Service", "ProtectHome", "yes"),
        ("Service", "PrivateTmp", "yes"),
        ("Service", "ProtectKernelTunables", "yes"),
        ("Service", "ProtectKernelModules", "yes"),
        ("Service", "ProtectKernelLogs", "yes"),
        ("Service", "ProtectControlGroups", "yes"),
        ("Service", "RestrictRealtime", "no"),
        ("Service", "LimitRTPRIO", "10"),
        ("Service", "RestrictAddressFamilies", "AF_UNIX AF_INET AF_INET6 AF_NETLINK"),
        ("Install", "WantedBy", "multi-user.target"),
    ],
)
def test_required_directive(section: str, key: str, value: str) -> None:
    assert values(SECTIONS, section, key) == [value]


def test_start_limits_are_in_unit_section() -> None:
    for key in ("StartLimitIntervalSec", "StartLimitBurst"):
        assert len(values(SECTIONS, "Unit", key)) == 1, key
        assert values(SECTIONS, "Service", key) == [], key


def test_serial_ports_and_cameras_stay_reachable() -> None:
    groups = " ".join(values(SECTIONS, "Service", "SupplementaryGroups")).split()
    assert {"dialout", "video"} <= set(groups)
    # Each of these hides /dev/ttyACM0 and /dev/video0 (ProtectClock= implies a DeviceAllow=
    # list on systemd 252, which closes every other device).
    for key in ("PrivateDevices", "DevicePolicy", "DeviceAllow", "ProtectClock"):
        assert all(k != key for k, _ in SECTIONS["Service"]), key


def test_no_inline_comments() -> None:
    """systemd has no end-of-line comments: '# ...' after a value becomes part of it."""
    for section in SECTIONS.values():
        for key, value in section:
            assert "#" not in value, f"{key}={value}"


# --- install.sh ---------------------------------------------------------------------------


@pytest.fixture
def source_tree() -> Iterator[Path]:
    """A minimal project tree holding a copy of install.sh and the unit."""
    with tempfile.TemporaryDirectory(prefix="companion-src") as tmp:
        root = Path(tmp)
        (root / "systemd").mkdir()
        (root / "config").mkdir()
        shutil.copy2(INSTALL, root / "systemd" / "install.sh")
        shutil.copy2(UNIT, root / "systemd" / "companion.service")
        (root / "pyproject.toml").write_text('[project]\nname = "x"\n', encoding="utf-8")
        (root / "config" / "example-ardupilot-hokuyo.yaml").write_text("{}\n", encoding="utf-8")
        yield root


SYSTEM_PATHS = [
    Path("/opt/companion"),
    Path("/etc/companion"),
    Path("/etc/systemd/system/companion.service"),
    Path("/var/lib/companion"),
]


def system_state() -> tuple[object, ...]:
    """What an install would change: the paths above and the service user."""
    user = subprocess.run(["getent", "passwd", "companion"], capture_output=True, check=False)
    return (*(p.exists() for p in SYSTEM_PATHS), user.stdout)


def tree_state(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def run_install(script: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["bash", str(script), *args],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        cwd="/",
    )


def test_install_dry_run_prints_every_step_and_changes_nothing(source_tree: Path) -> None:
    before, files = system_state(), tree_state(source_tree)
    proc = run_install(source_tree / "systemd" / "install.sh", "--dry-run")
    assert proc.returncode == 0, proc.stderr
    commands = [line[2:] for line in proc.stdout.splitlines() if line.startswith("+ ")]
    text = "\n".join(commands)
    src = str(source_tree)  # default source: the tree holding the script

    assert re.search(
        r"^(useradd --system .*--groups dialout,video .*companion"
        r"|usermod --append --groups dialout,video companion)$",
        text,
        re.M,
    )
    if not Path("/opt/companion/venv/bin/python").exists():
        assert "python3 -m venv /opt/companion/venv" in commands
    assert f"/opt/companion/venv/bin/python -m pip install --upgrade {src}" in commands
    if not Path("/etc/companion/companion.yaml").exists():
        assert (
            f"install -m 0640 -o root -g companion {src}/config/example-ardupilot-hokuyo.yaml"
            " /etc/companion/companion.yaml"
        ) in commands
    assert (
        f"install -m 0644 {src}/systemd/companion.service /etc/systemd/system/companion.service"
    ) in commands
    assert "systemctl daemon-reload" in commands
    assert any(c.startswith("systemctl enable") for c in commands)
    # The unit is installed before systemd is told to reload and start it.
    unit_step = next(i for i, c in enumerate(commands) if "/etc/systemd/system/" in c)
    assert unit_step < commands.index("systemctl daemon-reload")

    assert system_state() == before
    assert tree_state(source_tree) == files


def test_install_source_option(source_tree: Path) -> None:
    proc = run_install(INSTALL, "--dry-run", "--source", str(source_tree))
    assert proc.returncode == 0, proc.stderr
    assert f"+ /opt/companion/venv/bin/python -m pip install --upgrade {source_tree}\n" in (
        proc.stdout
    )


def test_install_rejects_a_tree_without_the_project(source_tree: Path) -> None:
    (source_tree / "config" / "example-ardupilot-hokuyo.yaml").unlink()
    proc = run_install(source_tree / "systemd" / "install.sh", "--dry-run")
    assert proc.returncode != 0
    assert "example-ardupilot-hokuyo.yaml not found" in proc.stderr


def test_install_rejects_unknown_arguments() -> None:
    proc = run_install(INSTALL, "--dry-run", "--frobnicate")
    assert proc.returncode != 0
    assert "unknown argument: --frobnicate" in proc.stderr
    assert "+ " not in proc.stdout


def test_install_refuses_to_run_without_root() -> None:
    """Run for real (no --dry-run) as an unprivileged user: it must stop at once."""
    with tempfile.TemporaryDirectory() as tmp:
        os.chmod(tmp, 0o755)  # readable by the unprivileged user below
        script = Path(tmp) / "install.sh"
        shutil.copy2(INSTALL, script)
        script.chmod(0o755)
        command = ["bash", str(script)]
        if os.geteuid() == 0:
            setpriv = shutil.which("setpriv")
            if setpriv is None:
                pytest.skip("running as root and setpriv (util-linux) is missing")
            command = [setpriv, "--reuid=65534", "--regid=65534", "--clear-groups", *command]
        before = system_state()
        proc = subprocess.run(
            command, capture_output=True, text=True, timeout=60, check=False, cwd=tmp
        )
    assert proc.returncode != 0
    assert "must be run as root" in proc.stderr
    assert proc.stdout == ""
    assert system_state() == before


def test_install_script_passes_shellcheck() -> None:
    shellcheck = shutil.which("shellcheck")
    if shellcheck is None:
        pytest.skip("shellcheck not installed (apt install shellcheck)")
    proc = subprocess.run(
        [shellcheck, "--severity=style", str(INSTALL)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 0, proc.stdout


def test_the_fault_suite_runs_the_daemon_at_the_units_priority() -> None:
    from sitl.rig import SERVICE_NICE

    assert values(SECTIONS, "Service", "Nice") == [str(SERVICE_NICE)]


def test_the_installed_config_asks_for_no_higher_realtime_priority_than_the_unit_grants() -> None:
    from companion.config import load_config

    cfg = load_config(REPO / "config" / "example-ardupilot-hokuyo.yaml")
    granted = int(values(SECTIONS, "Service", "LimitRTPRIO")[0])
    assert 0 < cfg.scheduling.realtime_priority <= granted
