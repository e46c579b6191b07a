"""``mazebot replay FILE.mcap``: a recorded run through the same SLAM again.

Example::

    mazebot replay run.mcap --out /tmp/replay          # as fast as the CPU allows
    mazebot replay run.mcap --speed 1 --out /tmp/replay  # paced as recorded
    mazebot replay run.mcap --serve --port 8080        # watch it again on the phone page

writes ``map.pgm`` + ``map.yaml`` (ROS map_server), ``map.png``, ``trajectory.txt``
(``time_s x_m y_m theta_rad`` per scan), ``graph.g2o`` and ``summary.json`` into
``--out`` (default: ``FILE.replay/`` next to the recording), and prints the summary.
With ``--serve`` the replay (paced as recorded unless ``--speed``/``--fast`` say
otherwise) is shown on the phone page at ``--host``:``--port`` (default ``[web]``), the
outputs are written when it ends, and the page stays up until Ctrl-C.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import math
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from mazebot.errors import EXIT_OK, UsageError

if TYPE_CHECKING:
    from mazebot.record.reader import Recording

log = logging.getLogger(__name__)


def _cmd_replay(args: argparse.Namespace) -> int:
    from mazebot.record.reader import Recording
    from mazebot.record.replay import replay, write_outputs

    if args.speed is not None and not (math.isfinite(args.speed) and args.speed > 0):
        raise UsageError(f"--speed must be a positive number, got {args.speed}")
    if not args.serve and (args.host is not None or args.port is not None):
        raise UsageError("--host and --port need --serve (the replay's web page)")
    recording = Recording.open(args.file)
    out = Path(args.out) if args.out else recording.path.with_suffix(".replay")
    if args.serve:
        speed = None if args.fast else (1.0 if args.speed is None else args.speed)
        return asyncio.run(_serve(args, recording, speed, out))
    result = replay(recording, speed=None if args.fast else args.speed)
    write_outputs(result, out)
    print(json.dumps({**result.stats, "out": str(out)}))
    return EXIT_OK


async def _serve(args: argparse.Namespace, recording: Recording, speed: float | None, out: Path) -> int:
    """Serve the page, feed the replay, write the outputs, keep serving until a signal."""
    from concurrent.futures import ThreadPoolExecutor

    from mazebot.config import load_config
    from mazebot.logs import setup_logging
    from mazebot.record import replay_server
    from mazebot.record.replay import write_outputs
    from mazebot.state import SharedState

    config = load_config(args.config)
    setup_logging(args.log_level or config.daemon.log_level)
    host = args.host if args.host is not None else config.web.host
    port = args.port if args.port is not None else config.web.port
    progress = replay_server.ReplayProgress.of(recording, speed)
    state = SharedState()
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    runner = await replay_server.start_server(state, progress, replay_server.replay_settings(config.web), host, port)
    executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mazebot-replay")
    log.info("replaying %s %s on http://%s:%d/ (Ctrl-C stops)", progress.file, replay_server.speed_text(speed),
             host, port)
    feeding = asyncio.create_task(replay_server.feed(recording, state, progress, executor))
    stopping = asyncio.create_task(stop.wait())
    try:
        await asyncio.wait({feeding, stopping}, return_when=asyncio.FIRST_COMPLETED)
        if feeding.done():
            result = feeding.result()  # a damaged file: its one line, after the page is closed
            write_outputs(result, out)
            print(json.dumps({**result.stats, "out": str(out)}), flush=True)
            log.info("replay finished; the page shows the final map until Ctrl-C")
            await stopping
        else:
            share = progress.fed / max(progress.messages, 1)
            log.info("replay stopped at %.0f %% of %s; no outputs written", 100 * share, progress.file)
    finally:
        for task in (feeding, stopping):
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        executor.shutdown(wait=False, cancel_futures=True)
        await runner.cleanup()
        sys.stdout.flush()
    return EXIT_OK


def _cmd_export_bag(args: argparse.Namespace) -> int:
    from mazebot.record.rosbag_export import export_bag

    summary = export_bag(args.file, args.out, odometry_only=args.odometry_only)
    print(json.dumps({"out": summary.out, "messages": summary.messages}))
    return EXIT_OK


def register(sub: argparse._SubParsersAction) -> None:
    bag = sub.add_parser("export-bag", help="write a recording (MCAP) as a ROS 2 bag (rosbag2, CDR)",
                         description="Write a recording as a ROS 2 bag (rosbag2, MCAP storage, CDR): /scan, "
                                     "/odom, /tf, /tf_static and /map, for rviz2, slam_toolbox and Nav2. "
                                     "Needs the optional rosbags package (pip install 'mazebot[ros]').")
    bag.add_argument("file", help="a recording made with `mazebot run --record FILE.mcap`")
    bag.add_argument("out", help="the bag's folder, which must not exist yet")
    bag.add_argument("--odometry-only", action="store_true",
                     help="leave out map -> odom and /map (for slam_toolbox to map the bag itself)")
    bag.set_defaults(func=_cmd_export_bag)
    rep = sub.add_parser("replay", help="run a recording (MCAP) through SLAM again; writes map and trajectory",
                         description="Run a recording (MCAP) through SLAM again and write the map, trajectory "
                                     "and pose graph; --serve shows it on the phone page as it runs.")
    rep.add_argument("file", help="a recording made with `mazebot run --record FILE.mcap`")
    pace = rep.add_mutually_exclusive_group()
    pace.add_argument("--speed", type=float, default=None,
                      help="pace: 1 = as recorded, 2 = twice as fast (default: --fast, or 1 with --serve)")
    pace.add_argument("--fast", action="store_true", help="as fast as possible (the default without --serve)")
    rep.add_argument("--out", default=None, help="output folder (default FILE.replay/)")
    rep.add_argument("--serve", action="store_true", help="show the replay on the phone page while it runs")
    rep.add_argument("--host", default=None, help="with --serve: web server interface (overrides [web] host)")
    rep.add_argument("--port", type=int, default=None, help="with --serve: web server port (overrides [web] port)")
    rep.add_argument("--config", default=None, help="with --serve: config file for [web] (default as `mazebot run`)")
    rep.add_argument("--log-level", default=None, choices=["debug", "info", "warning", "error"],
                     help="log threshold on stderr (default: [daemon] log_level of the config)")
    rep.set_defaults(func=_cmd_replay)
