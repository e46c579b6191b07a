"""``mazebot replay FILE.mcap``: a recorded run through the same SLAM again.

Example::

    mazebot replay run.mcap --out /tmp/replay          # as fast as the CPU allows
    mazebot replay run.mcap --speed 1 --out /tmp/replay  # paced as recorded

writes ``map.pgm`` + ``map.yaml`` (ROS map_server), ``map.png``, ``trajectory.txt``
(``time_s x_m y_m theta_rad`` per scan), ``graph.g2o`` and ``summary.json`` into
``--out`` (default: ``FILE.replay/`` next to the recording), and prints the summary.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from mazebot.errors import EXIT_OK, UsageError


def _cmd_replay(args: argparse.Namespace) -> int:
    from mazebot.record.reader import Recording
    from mazebot.record.replay import replay, write_outputs

    if args.speed is not None and args.speed <= 0:
        raise UsageError(f"--speed must be positive, got {args.speed}")
    recording = Recording.open(args.file)
    result = replay(recording, speed=None if args.fast else args.speed)
    out = Path(args.out) if args.out else recording.path.with_suffix(".replay")
    write_outputs(result, out)
    print(json.dumps({**result.stats, "out": str(out)}))
    return EXIT_OK


def register(sub: argparse._SubParsersAction) -> None:
    rep = sub.add_parser("replay", help="run a recording (MCAP) through SLAM again; writes map and trajectory")
    rep.add_argument("file", help="a recording made with `mazebot run --record FILE.mcap`")
    pace = rep.add_mutually_exclusive_group()
    pace.add_argument("--speed", type=float, default=None, help="pace: 1 = as recorded, 2 = twice as fast")
    pace.add_argument("--fast", action="store_true", help="as fast as possible (the default)")
    rep.add_argument("--out", default=None, help="output folder (default FILE.replay/)")
    rep.set_defaults(func=_cmd_replay)
