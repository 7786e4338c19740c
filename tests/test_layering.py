"""The shape the design promises, checked on the source: the service never imports the simulator,
pipelines import no transport, messages import nothing of the service.

Every import statement counts, including the lazy ones inside functions.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tests.conftest import REPO

SERVICE_PACKAGES = ("companion", "drivers")
MAY_IMPORT_SIMULATOR = {"companion/cli.py"}  # the entry point of `companion sitl`; and bench*.py tools
PIPELINE_FORBIDDEN = ("companion.mavlink", "companion.telemetry", "zenoh", "sitl", "pymavlink")


def imported_modules(path: Path) -> set[str]:
    """Every module an import statement in ``path`` names (absolute imports)."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def _under(name: str, package: str) -> bool:
    return name == package or name.startswith(package + ".")


def service_files() -> list[Path]:
    return sorted(p for pkg in SERVICE_PACKAGES for p in (REPO / pkg).rglob("*.py"))


def test_the_service_never_imports_the_simulator() -> None:
    offenders = {}
    for path in service_files():
        rel = path.relative_to(REPO).as_posix()
        if rel in MAY_IMPORT_SIMULATOR or path.name.startswith("bench"):
            continue
        sim = sorted(n for n in imported_modules(path) if _under(n, "sitl"))
        if sim:
            offenders[rel] = sim
    assert offenders == {}


@pytest.mark.parametrize("path", sorted(p for p in (REPO / "companion" / "nav").glob("*.py")
                                        if not p.name.startswith("bench")), ids=lambda p: p.name)
def test_a_pipeline_module_imports_no_transport_and_no_simulator(path: Path) -> None:
    bad = sorted(n for n in imported_modules(path) if any(_under(n, f) for f in PIPELINE_FORBIDDEN))
    assert bad == []


def test_messages_import_nothing_of_the_service() -> None:
    names = imported_modules(REPO / "companion" / "messages.py")
    assert {n.split(".")[0] for n in names} <= {"__future__", "dataclasses", "typing", "numpy"}


def test_the_checker_sees_lazy_imports(tmp_path: Path) -> None:
    probe = tmp_path / "probe.py"
    probe.write_text("def f():\n    from sitl.world import World\n    import companion.mavlink.link\n")
    assert {"sitl.world", "companion.mavlink.link"} <= imported_modules(probe)
