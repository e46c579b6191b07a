"""The ``mazebot`` command line: one entry point, one subcommand per job.

Every subcommand sets ``args.func(args) -> int``. Errors the user can act on
(``MazebotError``) become one line on stderr and the error's exit code; argparse's own
usage errors exit 2. Nothing here prints a traceback for a user mistake.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
from collections.abc import Sequence

from mazebot import __version__
from mazebot.config import load_config, render_toml
from mazebot.errors import EXIT_OK, MazebotError

log = logging.getLogger("mazebot")

#: Modules that add subcommands with ``register(subparsers)``; imported lazily so a
#: missing optional part never breaks ``config check``.
_COMMAND_MODULES = (
    "mazebot.main",
    "mazebot.io.lidar_cli",
    "mazebot.io.motors_cli",
    "mazebot.sim.cli",
    "mazebot.slam.posegraph_cli",
    "mazebot.slam.slam_cli",
    "mazebot.bench.cli",
    "mazebot.record.cli",
    "mazebot.persist.cli",
)


def _config_check(args: argparse.Namespace) -> int:
    try:
        load_config(args.path)
    except MazebotError as exc:
        problems = getattr(exc, "problems", [str(exc)])
        for line in problems:
            print(line, file=sys.stderr)
        return exc.exit_code
    print("ok")
    return EXIT_OK


def _config_defaults(args: argparse.Namespace) -> int:
    sys.stdout.write(render_toml())
    return EXIT_OK


def _register_config(sub: argparse._SubParsersAction) -> None:
    config = sub.add_parser("config", help="check or print the configuration")
    csub = config.add_subparsers(dest="config_command", required=True)
    check = csub.add_parser("check", help="validate a config file: prints ok or one line per problem")
    check.add_argument("path", nargs="?", default=None, help="config file (default: $MAZEBOT_CONFIG or ./config.toml)")
    check.set_defaults(func=_config_check)
    defaults = csub.add_parser("defaults", help="print a complete default config file")
    defaults.set_defaults(func=_config_defaults)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mazebot", description="A robot that maps an unknown maze and shows it on a phone."
    )
    parser.add_argument("--version", action="version", version=f"mazebot {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _register_config(sub)
    for name in _COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if not (exc.name and name.startswith(exc.name)):
                raise
            continue
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    args.argv = argv
    try:
        return int(args.func(args))
    except MazebotError as exc:
        print(f"mazebot: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # the reader of our output went away (`mazebot lidar decode cap.bin | head`):
        # not an error; keep Python from complaining again while flushing at exit
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_OK
