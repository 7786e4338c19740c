"""Shared test helpers: free loopback ports and small config files."""

from __future__ import annotations

import logging
import socket
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A currently free loopback port (UDP by default)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(autouse=True, scope="module")
def logging_left_as_found() -> Iterator[None]:
    """A test (or a module fixture) that runs a command through ``companion.cli.main`` configures
    logging as the command does (companion.logsetup: the root level and a handler); put it back
    after the module, so that the modules after it see the logging they would see alone."""
    root = logging.getLogger()
    level, handlers = root.level, list(root.handlers)
    yield
    root.setLevel(level)
    for handler in [h for h in root.handlers if h not in handlers and type(h).__name__ == "_CompanionHandler"]:
        root.removeHandler(handler)
        handler.close()


@pytest.fixture
def repo() -> Path:
    return REPO


@pytest.fixture
def procs(tmp_path: Path):  # noqa: ANN201 - a generator fixture
    """Subprocesses of the test (output in tmp_path/NAME.out); whatever still runs is killed after."""
    from tests.sitl_helpers import Processes  # the daemon's imports: only for the tests that use it

    p = Processes(tmp_path)
    try:
        yield p
    finally:
        p.close()
