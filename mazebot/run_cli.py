"""``mazebot run [--sim]``: the daemon on the robot's devices or on the simulated robot.

The one place that chooses between the two hardware builders, so the daemon itself
(:mod:`mazebot.main`) never imports the simulator: this module sits above both in the
import layers (``docs/design.md``, "Layers").
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
from pathlib import Path

from pydantic import ValidationError

from mazebot.config import default_config_path, load_config
from mazebot.errors import EXIT_OK, UsageError
from mazebot.logs import setup_logging
from mazebot.main import open_robot_hardware, run_daemon


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UsageError(f"--size expects WxH like 6x6, got {text!r}") from None
    if not (2 <= w <= 32 and 2 <= h <= 32):
        raise UsageError(f"--size {text}: each side must be between 2 and 32 cells")
    return w, h


def _cmd_run(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    for flag, key, value in (("--host", "host", args.host), ("--port", "port", args.port)):
        if value is None:
            continue
        try:
            setattr(config.web, key, value)  # validated like the [web] key it overrides
        except ValidationError as exc:
            raise UsageError(f"{flag} {value}: {exc.errors()[0]['msg']}") from None
    setup_logging(args.log_level or config.daemon.log_level)
    if config.zenoh.enabled:  # before any device is opened: a missing extra is one line, exit 69
        from mazebot.fleet.session import import_zenoh

        import_zenoh("[zenoh] enabled")
    if args.sim:
        from mazebot.sim.backend import sim_hardware_builder

        if args.room:
            config.sim.world = "room"
        builder = sim_hardware_builder(
            maze_path=args.maze,
            seed=args.seed,
            size=parse_size(args.size) if args.size else None,
        )
    else:
        if args.maze or args.seed is not None or args.size or args.room:
            raise UsageError("--maze, --room, --seed and --size only make sense with --sim")
        builder = open_robot_hardware
    from mazebot.run_session import RunSession

    session = RunSession.from_options(config, record=args.record, resume=args.resume)
    config_path = Path(args.config) if args.config else default_config_path()  # a confirmed calibration replaces it
    with contextlib.suppress(KeyboardInterrupt):
        return asyncio.run(run_daemon(config, builder, session=session, config_path=config_path))
    return EXIT_OK


def register(sub: argparse._SubParsersAction) -> None:
    run = sub.add_parser(
        "run",
        help="run the robot (or, with --sim, the simulated robot)",
        description="Run the robot: lidar, encoders, SLAM, planner, motors and the phone page in one process, "
        "until SIGINT/SIGTERM (exit 0). Without --sim it needs the motor HAT, GPIO and the lidar "
        "(exit 69 naming a missing one); --sim drives a simulated robot in a generated 6x6 maze "
        "(or --maze, --seed, --size, --room) through the same drivers.",
    )
    run.add_argument("--config", default=None, help="config file (default: the one `mazebot config path` prints)")
    run.add_argument("--sim", action="store_true", help="drive a simulated robot instead of the hardware")
    run.add_argument("--maze", default=None, help="maze file in micromouse text format (with --sim)")
    run.add_argument("--room", action="store_true", help="the room with cylinders instead of a maze (with --sim)")
    run.add_argument("--seed", type=int, default=None, help="generate a maze from this seed (with --sim)")
    run.add_argument("--size", default=None, help="size of a generated maze, WxH cells (with --sim)")
    run.add_argument("--host", default=None, help="web server interface (overrides [web] host)")
    run.add_argument("--port", type=int, default=None, help="web server port (overrides [web] port)")
    run.add_argument("--log-level", default=None, choices=["debug", "info", "warning", "error"],
                     help="log threshold on stderr (default: [daemon] log_level of the config)")
    run.add_argument("--record", default=None, metavar="FILE.mcap", help="record every sensor stream to MCAP")
    run.add_argument("--resume", default=None, metavar="RUN", help="continue a saved run (a name from `mazebot runs`)")
    run.set_defaults(func=_cmd_run)
