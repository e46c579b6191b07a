"""``mazebot config check|defaults|path``: the configuration file, checked, written out or located."""

from __future__ import annotations

import argparse
import sys

from mazebot.errors import EXIT_OK, MazebotError


def _config_check(args: argparse.Namespace) -> int:
    from mazebot.config import load_config
    from mazebot.logs import error_line

    try:
        load_config(args.path)
    except MazebotError as exc:
        problems = getattr(exc, "problems", [str(exc)])
        for line in problems:
            print(error_line(line), file=sys.stderr)
        return exc.exit_code
    print("ok")
    return EXIT_OK


def _config_defaults(args: argparse.Namespace) -> int:
    from mazebot.config import render_toml

    sys.stdout.write(render_toml())
    return EXIT_OK


def _config_path(args: argparse.Namespace) -> int:
    from mazebot.config import config_search_path, default_config_path

    path = default_config_path()
    if path is None:
        searched = ", ".join(str(p) for p in config_search_path())
        print(f"built-in defaults (no file at {searched})")
    else:
        print(path.absolute())
    return EXIT_OK


def register(sub: argparse._SubParsersAction) -> None:
    config = sub.add_parser("config", help="check or print the configuration",
                            description="Check, print or locate mazebot's configuration file (config.toml).")
    csub = config.add_subparsers(dest="config_command", required=True, metavar="{check,defaults,path}")
    check = csub.add_parser("check", help="validate a config file: prints ok or one line per problem",
                            description="Validate a config file: prints ok (exit 0) or one line per problem "
                                        "naming the key (exit 78).")
    check.add_argument("path", nargs="?", default=None,
                       help="config file (default: the one `mazebot config path` prints)")
    check.set_defaults(func=_config_check)
    defaults = csub.add_parser("defaults", help="print a complete default config file",
                               description="Print a complete, commented config file with every default.")
    defaults.set_defaults(func=_config_defaults)
    path = csub.add_parser("path", help="print which config file is used without --config",
                           description="Print the config file mazebot uses when no --config is given: "
                                       "$MAZEBOT_CONFIG, else ./config.toml, else "
                                       "$XDG_CONFIG_HOME/mazebot/config.toml (~/.config), else "
                                       "/etc/mazebot/config.toml, else the built-in defaults.")
    path.set_defaults(func=_config_path)
