"""Errors that mazebot reports to its user, each with the process exit code it maps to.

Every error message is one line that says what was expected, what was found and,
where there is one, what to do about it. The CLI prints ``str(error)`` and exits with
``error.exit_code``; it never shows a traceback for these.
"""

from __future__ import annotations

import os

#: Exit codes, from BSD ``sysexits.h`` where one fits.
EXIT_OK = 0
EXIT_USAGE = 2
EXIT_SOFTWARE = 70  # a task crashed and the config asked the daemon to exit on faults
EXIT_UNAVAILABLE = 69  # a device is missing (EX_UNAVAILABLE)
EXIT_CONFIG = 78  # the configuration is invalid (EX_CONFIG)


class MazebotError(Exception):
    """Base class of every error mazebot reports to a user."""

    exit_code: int = EXIT_SOFTWARE


class ConfigError(MazebotError):
    """The configuration file is missing, unreadable or invalid.

    ``problems`` holds one line per invalid key, each naming the key path.
    """

    exit_code = EXIT_CONFIG

    def __init__(self, message: str, problems: list[str] | None = None) -> None:
        super().__init__(message)
        self.problems = problems if problems is not None else [message]


class HardwareUnavailable(MazebotError):
    """A device the run needs (lidar port, motor HAT, GPIO) cannot be reached."""

    exit_code = EXIT_UNAVAILABLE


class UsageError(MazebotError):
    """The command line asked for something that does not make sense."""

    exit_code = EXIT_USAGE


class ProtocolError(MazebotError):
    """A device answered something the protocol does not allow (e.g. a bad descriptor)."""


def serial_port_hint(port: str, error: BaseException) -> str:
    """One line explaining why ``port`` could not be opened and how to fix the usual causes."""
    reason = getattr(error, "strerror", None) or str(error) or type(error).__name__
    dialout = "add your user to the 'dialout' group (sudo usermod -aG dialout $USER, then log in again)"
    if os.path.exists(port):
        hint = dialout
    else:
        hint = f"check the USB cable and [lidar] port; once the device appears, {dialout} if it is refused"
    return f"lidar serial port {port} cannot be opened ({reason}); {hint}"
