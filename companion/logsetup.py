"""Logging to stderr in a format that suits both a terminal and the systemd journal.

Under systemd, stderr is a stream into journald, which timestamps every line itself and reads
an optional ``<N>`` syslog priority prefix (sd-daemon(3)) to set the entry's priority, so
``journalctl -p err`` and the colouring in ``journalctl`` work.  In a terminal the lines
carry a millisecond wall-clock time instead: ``12:34:56.789 INFO companion.nav: message``.
"""

from __future__ import annotations

import logging
import os
import sys
from typing import TextIO

__all__ = ["LEVELS", "setup_logging"]

LEVELS: dict[str, int] = {
    "debug": logging.DEBUG,
    "info": logging.INFO,
    "warning": logging.WARNING,
    "error": logging.ERROR,
}
"""Accepted level names (case-insensitive) and their ``logging`` levels."""

# sd-daemon(3) priorities: SD_CRIT 2, SD_ERR 3, SD_WARNING 4, SD_INFO 6, SD_DEBUG 7.
# Checked from the most severe down; custom levels in between take the next lower one.
_SYSLOG_PRIORITIES: tuple[tuple[int, int], ...] = (
    (logging.CRITICAL, 2),
    (logging.ERROR, 3),
    (logging.WARNING, 4),
    (logging.INFO, 6),
)
_SD_DEBUG = 7


def syslog_priority(levelno: int) -> int:
    """Map a ``logging`` level number to the sd-daemon(3) syslog priority."""
    for threshold, priority in _SYSLOG_PRIORITIES:
        if levelno >= threshold:
            return priority
    return _SD_DEBUG


class JournalFormatter(logging.Formatter):
    """``<N>logger: message``, with the prefix repeated on every line of the record.

    journald splits its input stream at newlines, so each line of a multi-line message or
    traceback needs its own prefix to keep the record's priority.
    """

    def __init__(self) -> None:
        """Create the formatter (no timestamp: journald adds its own)."""
        super().__init__("%(name)s: %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        """Format ``record`` and prefix each of its lines with ``<N>``."""
        prefix = f"<{syslog_priority(record.levelno)}>"
        return "\n".join(prefix + line for line in super().format(record).splitlines())


class _CompanionHandler(logging.StreamHandler[TextIO]):
    """The stderr handler installed by :func:`setup_logging` (marks it for replacement)."""


def _stderr_is_journal() -> bool:
    """True if stderr is the journal stream systemd connected (``JOURNAL_STREAM``).

    systemd.exec(5) sets ``JOURNAL_STREAM=DEVICE:INODE`` for the stream it connected; as it
    recommends, compare with stderr itself, so a child whose stderr was redirected elsewhere
    does not mistake the inherited variable for a journal connection.
    """
    value = os.environ.get("JOURNAL_STREAM", "")
    if not value:
        return False
    try:
        device, inode = (int(part) for part in value.split(":"))
        st = os.fstat(sys.stderr.fileno())
    except (ValueError, OSError, AttributeError):
        # Malformed variable, or stderr without a file descriptor (e.g. captured).
        return False
    return (st.st_dev, st.st_ino) == (device, inode)


def setup_logging(level: str, *, journald: bool | None = None) -> None:
    """Configure the root logger to write to stderr.

    Calling it again replaces the handler it installed before (no duplicate lines), so the
    level or format can be changed later, e.g. after the configuration file is read.

    Args:
        level: ``debug``, ``info``, ``warning`` or ``error`` (any case).
        journald: force the journal format (``True``) or the terminal format (``False``);
            ``None`` detects it from ``JOURNAL_STREAM``.

    Raises:
        ValueError: if ``level`` is not one of the names above.
    """
    levelno = LEVELS.get(level.lower())
    if levelno is None:
        raise ValueError(f"invalid log level {level!r}; valid levels: {', '.join(LEVELS)}")
    if journald is None:
        journald = _stderr_is_journal()

    handler = _CompanionHandler(sys.stderr)
    if journald:
        handler.setFormatter(JournalFormatter())
    else:
        handler.setFormatter(
            logging.Formatter(
                "%(asctime)s.%(msecs)03d %(levelname)s %(name)s: %(message)s",
                datefmt="%H:%M:%S",
            )
        )

    root = logging.getLogger()
    for old in [h for h in root.handlers if isinstance(h, _CompanionHandler)]:
        root.removeHandler(old)
        old.close()
    root.addHandler(handler)
    root.setLevel(levelno)
