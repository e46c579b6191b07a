"""``mazebot completion bash|zsh``: a shell completion script for every command and option.

Generated from the full parser (every command's module is imported, once, here) by
shtab (https://docs.iterative.ai/shtab/). Install it once::

    mazebot completion bash | sudo tee /etc/bash_completion.d/mazebot >/dev/null
    mazebot completion zsh > "${fpath[1]}/_mazebot"
"""

from __future__ import annotations

import argparse
import sys

from mazebot.errors import EXIT_OK

SHELLS = ("bash", "zsh")


def _cmd_completion(args: argparse.Namespace) -> int:
    import shtab

    from mazebot.cli import ALL, build_parser

    sys.stdout.write(shtab.complete(build_parser(ALL), shell=args.shell))
    return EXIT_OK


def register(sub: argparse._SubParsersAction) -> None:
    completion = sub.add_parser(
        "completion", help="print a shell completion script (bash or zsh)",
        description="Print a completion script for every mazebot command and option. bash: "
                    "`mazebot completion bash | sudo tee /etc/bash_completion.d/mazebot`; zsh: "
                    "`mazebot completion zsh > \"${fpath[1]}/_mazebot\"`.",
    )
    completion.add_argument("shell", choices=SHELLS, help="the shell the script is for")
    completion.set_defaults(func=_cmd_completion)
