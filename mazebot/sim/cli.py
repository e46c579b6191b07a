"""``mazebot sim lidar``: only the emulated lidar, on a pseudo-terminal.

Prints the device path as the first line of stdout, then serves until interrupted, so
any RPLidar client program can open the path as if it were ``/dev/ttyUSB0``. The robot
stands still at ``--pose`` (default: the maze's start pose).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import signal
import sys

import numpy as np

from mazebot.clock import RealClock
from mazebot.config import load_config
from mazebot.errors import EXIT_OK, UsageError
from mazebot.io.rplidar_models import MODELS
from mazebot.sim.lidar_emulator import RPLidarEmulator
from mazebot.sim.lidar_samples import PoseHistory, SpinningLidar
from mazebot.sim.pty_lidar import pty_device
from mazebot.sim.robot import lidar_params


def _parse_pose(text: str) -> tuple[float, float, float]:
    try:
        x, y, theta = (float(v) for v in text.split(","))
    except ValueError:
        raise UsageError(f"--pose expects X,Y,THETA in metres and radians, got {text!r}") from None
    return x, y, theta


async def _serve_lidar(args: argparse.Namespace) -> int:
    from mazebot.sim.world_source import make_world

    config = load_config(args.config)
    if args.model:
        config.sim.lidar_model = args.model
    model = MODELS[config.sim.lidar_model]
    world = make_world(config, args.maze, args.seed, None)
    x, y, theta = _parse_pose(args.pose) if args.pose else world.start_pose
    clock = RealClock()
    poses = PoseHistory()
    poses.append(clock.now_s(), x, y, theta)
    head = SpinningLidar(world, lidar_params(config), np.random.default_rng(config.sim.seed))
    emulator = RPLidarEmulator(head, poses, clock, model=model)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    async with pty_device(emulator) as path:
        print(path, flush=True)
        print(f"emulated RPLidar {model.name} ({model.baudrate} baud) in {world.name} "
              f"at x={x:.3f} y={y:.3f} theta={theta:.3f}", file=sys.stderr)
        await stop.wait()
    return EXIT_OK


def _cmd_sim_lidar(args: argparse.Namespace) -> int:
    with contextlib.suppress(KeyboardInterrupt):
        return asyncio.run(_serve_lidar(args))
    return EXIT_OK


def register(sub: argparse._SubParsersAction) -> None:
    sim = sub.add_parser("sim", help="parts of the simulator on their own")
    ssub = sim.add_subparsers(dest="sim_command", required=True)
    lidar = ssub.add_parser("lidar", help="serve an emulated RPLidar on a pseudo-terminal",
                            description="Serve an emulated RPLidar (the model of --model) in a simulated maze on a "
                                        "pseudo-terminal; its path is the first line of stdout (any RPLidar client "
                                        "can open it).")
    src = lidar.add_mutually_exclusive_group()
    src.add_argument("--maze", default=None, help="maze file in micromouse text format")
    src.add_argument("--seed", type=int, default=None, help="generate a maze from this seed")
    lidar.add_argument("--pose", default=None, help="robot pose X,Y,THETA (m, m, rad); default: the start")
    lidar.add_argument("--config", default=None, help="config file (lidar mounting, [sim] noise)")
    lidar.add_argument("--model", choices=sorted(MODELS), default=None,
                       help="which RPLidar to be (default: [sim] lidar_model of the config)")
    lidar.set_defaults(func=_cmd_sim_lidar)
