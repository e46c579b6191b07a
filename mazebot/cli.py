"""The ``mazebot`` command line: one entry point, one subcommand per job.

Every subcommand sets ``args.func(args) -> int``. Errors the user can act on
(``MazebotError``) become one line on stderr and the error's exit code; argparse's own
usage errors exit 2. Nothing here prints a traceback for a user mistake.

Start-up cost is paid per subcommand: the top-level parser is built from the table
:data:`COMMANDS` (name, module, one-line help) without importing any command's module,
and only the module of the subcommand being run is imported, to add its options and
run it (pip does the same: ``pip/_internal/commands/__init__.py``). So ``mazebot motors
stop``, which systemd runs after every exit of the daemon, never imports numpy, scipy or
the SLAM, and ``mazebot config check`` works whatever optional part is missing.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import warnings
from collections.abc import Sequence
from typing import Any, NamedTuple

from mazebot.errors import EXIT_OK, MazebotError


class Command(NamedTuple):
    """One top-level subcommand: its name, the module whose ``register(subparsers)`` adds
    its parser, and the help line ``mazebot --help`` shows without importing that module."""

    name: str
    module: str
    help: str


#: Every top-level subcommand, in the order ``mazebot --help`` lists them. A module may
#: register several (``mazebot.persist.cli``: ``runs`` and ``export-map``); the help lines
#: here must equal the ones the modules register (a test keeps them equal).
COMMANDS: tuple[Command, ...] = (
    Command("config", "mazebot.config_cli", "check or print the configuration"),
    Command("run", "mazebot.run_cli", "run the robot (or, with --sim, the simulated robot)"),
    Command("lidar", "mazebot.io.lidar_cli", "talk to the RPLidar or decode its byte stream"),
    Command("motors", "mazebot.io.motors_cli", "direct motor HAT commands"),
    Command("doctor", "mazebot.doctor_cli", "check every part of the robot, one line each"),
    Command("sim", "mazebot.sim.cli", "parts of the simulator on their own"),
    Command("posegraph", "mazebot.slam.posegraph_cli", "2D pose graphs in g2o format"),
    Command("slam", "mazebot.slam.slam_cli", "run the SLAM offline on recorded data"),
    Command("calibrate", "mazebot.calibration_cli",
            "measure wiring, wheel sizes, track width and lidar yaw with the lidar as the ruler"),
    Command("bench", "mazebot.bench.cli", "measure whole simulated runs against ground truth"),
    Command("export-bag", "mazebot.record.cli", "write a recording (MCAP) as a ROS 2 bag (rosbag2, CDR)"),
    Command("replay", "mazebot.record.cli",
            "run a recording (MCAP) through SLAM again; writes map and trajectory"),
    Command("runs", "mazebot.persist.cli", "list the saved runs (STATE_DIR/runs)"),
    Command("export-map", "mazebot.persist.cli",
            "export a saved run's map: PNG, ROS PGM+YAML, SVG or the cell graph"),
    Command("watch", "mazebot.fleet.cli", "show every robot on the Zenoh network on one page (needs mazebot[zenoh])"),
    Command("completion", "mazebot.completion_cli", "print a shell completion script (bash or zsh)"),
)

#: ``build_parser(ALL)`` imports every command's module: the whole tree, for shell
#: completion and for the tests.
ALL = "*"


class _VersionAction(argparse.Action):
    """``--version``: the installed distribution's version, read from its metadata only when asked."""

    def __init__(self, option_strings: Sequence[str], dest: str = argparse.SUPPRESS, **kwargs: object) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS,
                         help="print the installed version and exit")

    def __call__(self, parser: argparse.ArgumentParser, *args: object) -> None:
        from mazebot import __version__

        sys.stdout.write(f"mazebot {__version__}\n")
        parser.exit()


def command_name(argv: Sequence[str]) -> str | None:
    """The subcommand ``argv`` asks for: its first word that is not an option (the top-level
    parser has only flags without values), or None."""
    return next((word for word in argv if not word.startswith("-")), None)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``mazebot`` parser with the full options of ``command`` (or of all, with :data:`ALL`).

    The other subcommands are only their name and help line, which is all ``mazebot
    --help`` shows; their modules are not imported.
    """
    parser = argparse.ArgumentParser(
        prog="mazebot", description="A robot that maps an unknown maze and shows it on a phone."
    )
    parser.add_argument("--version", action=_VersionAction)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    wanted = {e.module for e in COMMANDS if command in (ALL, e.name)}
    registered: set[str] = set()
    for entry in COMMANDS:
        if entry.module not in wanted:
            sub.add_parser(entry.name, help=entry.help, add_help=False)
        elif entry.module not in registered:  # a module registers all of its commands at once
            importlib.import_module(entry.module).register(sub)
            registered.add(entry.module)
    return parser


def _warning_line(
    message: Warning | str, category: type[Warning], filename: str, lineno: int, file: Any = None, line: Any = None
) -> None:
    """A warning meant for the user (``FutureWarning``: a config key renamed) as one line, like the errors."""
    if issubclass(category, FutureWarning):
        print(f"mazebot: warning: {message}", file=sys.stderr)
    else:
        _show_warning(message, category, filename, lineno, file, line)


_show_warning = warnings.showwarning


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(command_name(argv))
    args = parser.parse_args(argv)
    args.argv = argv
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _warning_line
            return int(args.func(args))
    except MazebotError as exc:
        from mazebot.logs import error_line

        print(error_line(f"mazebot: {exc}"), file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # the reader of our output went away (`mazebot lidar decode cap.bin | head`):
        # not an error; keep Python from complaining again while flushing at exit
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_OK
