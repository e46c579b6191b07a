"""Logging to stderr, with syslog priorities when stderr is systemd's journal.

journald files every line a service writes under the priority of its ``<N>`` prefix
(``SyslogLevelPrefix=``, on by default: systemd.exec(5)); without one every line is
"info" and ``journalctl -u mazebot -p warning`` shows no fault. systemd tells a service
that its stderr is the journal with ``$JOURNAL_STREAM`` = ``DEVICE:INODE`` of that
stream (systemd.exec(5), "Environment variables in spawned processes"); the prefix is
only written when stderr is that very stream, so a child whose stderr was redirected
to a file or a pipe writes plain lines. The numbers are sd-daemon(3)'s ``SD_ERR``,
``SD_WARNING``, ... No timestamps: journald adds its own.

Example::

    setup_logging("info")      # under systemd: "<4>WARNING mazebot.web.server: control PIN ..."
    print(journal_line(3, "mazebot: motor HAT not found ..."), file=sys.stderr)
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Mapping
from typing import IO

#: Python's levels and their syslog priorities (sd-daemon(3): SD_CRIT 2, SD_ERR 3,
#: SD_WARNING 4, SD_INFO 6, SD_DEBUG 7); a level between two takes the lower one's.
SYSLOG_PRIORITY = ((logging.CRITICAL, 2), (logging.ERROR, 3), (logging.WARNING, 4), (logging.INFO, 6))
DEBUG_PRIORITY = 7
#: The priority of the one-line error the command line ends with.
ERROR_PRIORITY = 3

LOG_FORMAT = "%(levelname)s %(name)s: %(message)s"


def syslog_priority(levelno: int) -> int:
    """The syslog priority (0 emergency ... 7 debug) of a Python log level."""
    return next((priority for level, priority in SYSLOG_PRIORITY if levelno >= level), DEBUG_PRIORITY)


def stream_is_journal(stream: IO[str], environ: Mapping[str, str] | None = None) -> bool:
    """Whether ``stream`` is the journal stream systemd named in ``$JOURNAL_STREAM``."""
    value = (os.environ if environ is None else environ).get("JOURNAL_STREAM", "")
    device, _, inode = value.partition(":")
    try:
        stat = os.fstat(stream.fileno())
        return (stat.st_dev, stat.st_ino) == (int(device), int(inode))
    except (ValueError, OSError, AttributeError):  # unset or malformed, or a stream without a descriptor
        return False


def journal_line(priority: int, text: str) -> str:
    """``text`` with ``<priority>`` in front of each of its lines (journald reads every line alone)."""
    return "\n".join(f"<{priority}>{line}" for line in text.split("\n"))


class JournalFormatter(logging.Formatter):
    """A formatter whose every output line starts with the record's syslog priority."""

    def format(self, record: logging.LogRecord) -> str:
        return journal_line(syslog_priority(record.levelno), super().format(record))


def setup_logging(level: str, stream: IO[str] | None = None) -> None:
    """Log mazebot's records at ``level`` and above to ``stream`` (stderr), prefixed for journald under systemd."""
    stream = sys.stderr if stream is None else stream
    handler = logging.StreamHandler(stream)
    journal = stream_is_journal(stream)
    handler.setFormatter(JournalFormatter(LOG_FORMAT) if journal else logging.Formatter(LOG_FORMAT))
    logging.basicConfig(level=getattr(logging, level.upper()), handlers=[handler], force=True)


def error_line(text: str, stream: IO[str] | None = None) -> str:
    """The command line's closing error as written to ``stream`` (stderr): prefixed for the journal there."""
    stream = sys.stderr if stream is None else stream
    return journal_line(ERROR_PRIORITY, text) if stream_is_journal(stream) else text
