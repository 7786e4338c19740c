"""Log format for the journal (``<N>`` priority prefix) and for a terminal."""

from __future__ import annotations

import io
import logging
import os
import re
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from companion.logsetup import setup_logging, syslog_priority


@pytest.fixture(autouse=True)
def restore_root_logger() -> Iterator[None]:
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield
    for handler in root.handlers[:]:
        if handler not in handlers:
            root.removeHandler(handler)
            handler.close()
    root.setLevel(level)


def capture_stderr(monkeypatch: pytest.MonkeyPatch) -> io.StringIO:
    """Point sys.stderr at a buffer (in the test body: pytest resets it after fixtures)."""
    buffer = io.StringIO()
    monkeypatch.setattr(sys, "stderr", buffer)
    monkeypatch.delenv("JOURNAL_STREAM", raising=False)
    return buffer


def test_journal_format_has_priority_and_no_timestamp(monkeypatch: pytest.MonkeyPatch) -> None:
    stderr = capture_stderr(monkeypatch)
    setup_logging("debug", journald=True)
    log = logging.getLogger("companion.test")
    log.debug("d")
    log.info("i")
    log.warning("w %d", 1)
    log.error("e")
    log.critical("c")
    assert stderr.getvalue().splitlines() == [
        "<7>companion.test: d",
        "<6>companion.test: i",
        "<4>companion.test: w 1",
        "<3>companion.test: e",
        "<2>companion.test: c",
    ]


def test_journal_format_prefixes_every_traceback_line(monkeypatch: pytest.MonkeyPatch) -> None:
    stderr = capture_stderr(monkeypatch)
    setup_logging("info", journald=True)
    try:
        raise RuntimeError("boom")
    except RuntimeError:
        logging.getLogger("companion.test").exception("failed")
    lines = stderr.getvalue().splitlines()
    assert lines[0] == "<3>companion.test: failed"
    assert lines[-1] == "<3>RuntimeError: boom"
    assert len(lines) > 2
    assert all(line.startswith("<3>") for line in lines)


def test_syslog_priority_of_custom_levels() -> None:
    assert syslog_priority(logging.INFO + 5) == 6
    assert syslog_priority(logging.DEBUG - 5) == 7
    assert syslog_priority(logging.CRITICAL + 10) == 2


def test_terminal_format(monkeypatch: pytest.MonkeyPatch) -> None:
    stderr = capture_stderr(monkeypatch)
    setup_logging("info", journald=False)
    log = logging.getLogger("companion.test")
    log.debug("hidden")
    log.warning("hello")
    assert re.fullmatch(
        r"\d\d:\d\d:\d\d\.\d{3} WARNING companion\.test: hello\n", stderr.getvalue()
    )


def test_level_names_are_case_insensitive(monkeypatch: pytest.MonkeyPatch) -> None:
    stderr = capture_stderr(monkeypatch)
    setup_logging("WARNING", journald=True)
    logging.getLogger("companion.test").info("hidden")
    logging.getLogger("companion.test").warning("shown")
    assert stderr.getvalue() == "<4>companion.test: shown\n"


@pytest.mark.parametrize("level", ["verbose", "", "critical", "warn"])
def test_invalid_level_names_the_valid_ones(level: str) -> None:
    with pytest.raises(ValueError) as excinfo:
        setup_logging(level)
    message = str(excinfo.value)
    assert repr(level) in message
    assert "debug, info, warning, error" in message


def test_calling_twice_does_not_duplicate_lines(monkeypatch: pytest.MonkeyPatch) -> None:
    stderr = capture_stderr(monkeypatch)
    root = logging.getLogger()
    others = len(root.handlers)
    setup_logging("info", journald=False)
    setup_logging("info", journald=True)
    assert len(root.handlers) == others + 1
    logging.getLogger("companion.test").info("once")
    assert stderr.getvalue() == "<6>companion.test: once\n"


def test_journal_detected_from_journal_stream(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """JOURNAL_STREAM counts only if it names the device and inode of stderr itself."""
    with open(tmp_path / "stderr", "w+", encoding="utf-8") as stream:
        monkeypatch.setattr(sys, "stderr", stream)
        st = os.fstat(stream.fileno())
        cases = {
            f"{st.st_dev}:{st.st_ino}": "<6>companion.test: a",
            f"{st.st_dev}:{st.st_ino + 1}": "companion.test: a",  # inherited, redirected
            "garbage": "companion.test: a",
            "": "companion.test: a",
        }
        for value, expected_end in cases.items():
            monkeypatch.setenv("JOURNAL_STREAM", value)
            stream.seek(0)
            stream.truncate()
            setup_logging("info")
            logging.getLogger("companion.test").info("a")
            stream.flush()
            line = (tmp_path / "stderr").read_text(encoding="utf-8").rstrip("\n")
            assert line.endswith(expected_end), value
            assert line.startswith("<6>") == expected_end.startswith("<6>"), value
