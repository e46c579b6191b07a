"""``mazebot watch``: every robot on the Zenoh network on one page (and, with --record, in MCAP files)."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import signal
from pathlib import Path

from mazebot.errors import EXIT_OK, HardwareUnavailable
from mazebot.logs import setup_logging

log = logging.getLogger("mazebot")


async def watch(args: argparse.Namespace) -> int:
    from aiohttp import web

    from mazebot.fleet.recorder import FleetRecorder
    from mazebot.fleet.session import open_session
    from mazebot.fleet.watch_app import create_watch_app
    from mazebot.fleet.watcher import Fleet

    session = open_session("mazebot watch", args.mode, args.connect, args.listen, not args.no_multicast)
    fleet = Fleet(session)
    fleet.start()
    recorder = None
    if args.record:
        recorder = FleetRecorder(Path(args.record), frozenset(args.only or ()))
        fleet.listeners.append(recorder)
    runner = web.AppRunner(create_watch_app(fleet), handle_signals=False, access_log=None, shutdown_timeout=2.0)
    await runner.setup()
    try:
        await web.TCPSite(runner, args.host, args.port).start()
    except OSError as exc:
        await runner.cleanup()
        fleet.close()
        raise HardwareUnavailable(f"mazebot watch cannot listen on {args.host}:{args.port} "
                                  f"({exc.strerror or exc}); choose another --port") from None
    log.info("watching the fleet on http://%s:%d/%s", args.host, args.port,
             f" (recording to {args.record})" if args.record else "")
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        await stop.wait()
    finally:
        await runner.cleanup()
        fleet.close()
        if recorder is not None:
            recorder.close()
    return EXIT_OK


def _cmd_watch(args: argparse.Namespace) -> int:
    setup_logging(args.log_level)
    with contextlib.suppress(KeyboardInterrupt):
        return asyncio.run(watch(args))
    return EXIT_OK


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "watch",
        help="show every robot on the Zenoh network on one page (needs mazebot[zenoh])",
        description="Find every robot publishing on Zenoh ([zenoh] enabled on the robot) and serve one page "
        "listing them; /robot/NAME/ is that robot's phone page, start/stop forwarded with its PIN. "
        "Peers on the local network are found by multicast; --connect reaches a zenohd router or a robot "
        "elsewhere (docs/fleet.md).",
    )
    p.add_argument("--host", default="127.0.0.1", help="interface of the page (0.0.0.0: every interface)")
    p.add_argument("--port", type=int, default=8090, help="port of the page")
    p.add_argument("--mode", default="peer", choices=["peer", "client"], help="Zenoh mode (client: via a router)")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="a Zenoh endpoint to connect to, e.g. tcp/192.168.1.10:7447 (repeatable)")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="a Zenoh endpoint to listen on (repeatable)")
    p.add_argument("--no-multicast", action="store_true", help="do not scout for peers by UDP multicast")
    p.add_argument("--record", default=None, metavar="DIR", help="record each robot to DIR/NAME.mcap")
    p.add_argument("--only", action="append", default=None, metavar="NAME",
                   help="with --record: record only this robot (repeatable)")
    p.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"],
                   help="log threshold on stderr")
    p.set_defaults(func=_cmd_watch)
