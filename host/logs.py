"""Logging for the daemon and the CLI: the standard ``logging`` module, to stderr, with levels.

Every module logs through ``logging.getLogger(__name__)``; :func:`configure_logging` is called once by the
``phantom`` entry point. Under systemd (``$JOURNAL_STREAM`` names our stderr) each line starts with its syslog
priority, ``<3>`` for an error, which journald stores as the entry's priority: ``journalctl -u phantomd -p err``
then shows faults and failures only. Elsewhere the lines carry a time and the level's name.
"""

from __future__ import annotations

import logging
import os
import sys

#: Level names accepted by :func:`configure_logging` (and ``phantom --log-level``).
LEVELS: dict[str, int] = {"debug": logging.DEBUG, "info": logging.INFO, "warning": logging.WARNING,
                          "error": logging.ERROR}

#: syslog priorities (sd-daemon(3)) of the logging levels.
JOURNAL_PRIORITIES: tuple[tuple[int, int], ...] = (
    (logging.CRITICAL, 2), (logging.ERROR, 3), (logging.WARNING, 4), (logging.INFO, 6), (logging.DEBUG, 7))


def journal_priority(levelno: int) -> int:
    """The syslog priority of a logging level (a level between two takes the more severe's)."""
    for level, priority in JOURNAL_PRIORITIES:
        if levelno >= level:
            return priority
    return 7


class JournalFormatter(logging.Formatter):
    """Prefixes every line of a record (a traceback's too) with ``<priority>``, as journald reads stderr."""

    def format(self, record: logging.LogRecord) -> str:
        prefix = f"<{journal_priority(record.levelno)}>"
        return "\n".join(prefix + line for line in super().format(record).splitlines() or [""])


def stderr_is_journal() -> bool:
    """Whether stderr is the journal's stream: ``$JOURNAL_STREAM`` is ``device:inode`` of our stderr."""
    stream = os.environ.get("JOURNAL_STREAM", "")
    device, _, inode = stream.partition(":")
    if not (device.isdigit() and inode.isdigit()):
        return False
    try:
        status = os.fstat(sys.stderr.fileno())
    except (OSError, ValueError, AttributeError):
        return False
    return status.st_dev == int(device) and status.st_ino == int(inode)


def configure_logging(level: str = "info") -> None:
    """Send the ``phantom`` loggers' records at ``level`` and above to stderr (journald priorities under
    systemd); replaces an earlier configuration. Raises ValueError for an unknown level name."""
    name = level.lower()
    if name not in LEVELS:
        raise ValueError(f"unknown log level {level!r}; use one of {', '.join(LEVELS)}")
    handler = logging.StreamHandler(sys.stderr)
    if stderr_is_journal():
        handler.setFormatter(JournalFormatter("%(name)s: %(message)s"))
    else:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s",
                                               datefmt="%H:%M:%S"))
    logger = logging.getLogger("phantom")
    for old in list(logger.handlers):
        logger.removeHandler(old)
    logger.addHandler(handler)
    logger.setLevel(LEVELS[name])
    logger.propagate = False


def configured_level() -> str:
    """The level name :func:`configure_logging` set last (``info`` before it ran): a worker process started by
    this one logs like it."""
    level = logging.getLogger("phantom").level
    return next((name for name, value in LEVELS.items() if value == level), "info")
