"""``mazebot run --sim``: the daemon's real drivers, opened on a simulated robot.

The motor driver writes into the simulator's fake MotorKit, the encoder driver counts
edges on the simulator's gpiozero mock pins, and the lidar driver talks to the RPLidar
emulator over an in-memory byte stream. Nothing in the daemon knows it is simulated.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from contextlib import AsyncExitStack
from pathlib import Path

from mazebot.clock import Clock
from mazebot.config import Config
from mazebot.errors import UsageError
from mazebot.io.encoders import WheelEncoders
from mazebot.io.motors import DifferentialMotors
from mazebot.io.rplidar import RPLidar
from mazebot.io.serial_link import ByteLink, memory_link_pair
from mazebot.main import Hardware, HardwareBuilder
from mazebot.sim.lidar_emulator import RPLidarEmulator
from mazebot.sim.maze_file import load_maze
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.robot import SimulatedRobot
from mazebot.sim.world import World, world_from_layout

log = logging.getLogger(__name__)


def make_world(config: Config, maze_path: str | None, seed: int | None, size: tuple[int, int] | None) -> World:
    """The world a sim run uses: a maze file, or a maze generated from a seed and size."""
    sim = config.sim
    path = maze_path or (sim.maze or None)
    if path is not None:
        if seed is not None or size is not None:
            raise UsageError("give either --maze or --seed/--size, not both")
        if not Path(path).is_file():
            raise UsageError(f"maze file {path} not found")
        return load_maze(path, cell_size_m=sim.cell_size_m, wall_thickness_m=sim.wall_thickness_m)
    width, height = size or (sim.maze_width, sim.maze_height)
    maze_seed = sim.seed if seed is None else seed
    layout = generate_maze(width, height, maze_seed, kind=sim.maze_kind, cell_size_m=sim.cell_size_m)
    return world_from_layout(
        layout, wall_thickness_m=sim.wall_thickness_m, name=f"{sim.maze_kind}-{width}x{height}-seed{maze_seed}"
    )


class SimLidarLine:
    """The serial line between the daemon's lidar driver and the emulator.

    Each ``connect()`` is a fresh line (like replugging the USB cable): the emulator
    serves the device end until the driver closes its end.
    """

    def __init__(self, emulator: RPLidarEmulator) -> None:
        self.emulator = emulator
        self._served: set[asyncio.Task[None]] = set()

    async def connect(self) -> ByteLink:
        link, device_reader, device_writer = memory_link_pair(on_dtr=self.emulator.set_dtr)
        task = asyncio.create_task(self.emulator.serve(device_reader, device_writer), name="sim-lidar-device")
        self._served.add(task)
        task.add_done_callback(self._served.discard)
        return link

    async def close(self) -> None:
        for task in list(self._served):
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task


def sim_hardware_builder(
    maze_path: str | None = None, seed: int | None = None, size: tuple[int, int] | None = None
) -> HardwareBuilder:
    """A hardware builder for ``run_daemon`` that opens the drivers on a simulated robot."""

    async def build(config: Config, clock: Clock, stack: AsyncExitStack) -> Hardware:
        world = make_world(config, maze_path, seed, size)
        robot = SimulatedRobot(world, config, seed=config.sim.seed if seed is None else seed)
        stack.callback(robot.close)
        robot.step(clock.now_s())

        motors = DifferentialMotors.from_config(config.motors, robot.kit, clock)
        stack.callback(motors.close)
        encoders = WheelEncoders.from_config(config.encoders, robot.pin_factory)
        stack.callback(encoders.close)

        emulator = RPLidarEmulator(robot.lidar_head, robot.poses, clock)
        line = SimLidarLine(emulator)
        stack.push_async_callback(line.close)
        lidar = RPLidar.from_config(config.lidar, clock, link_factory=line.connect)
        await stack.enter_async_context(lidar)
        return Hardware(
            lidar=lidar,
            encoders=encoders,
            motors=motors,
            description=f"simulated robot in {world.name} ({len(world.segments)} wall segments)",
            extra_tasks=[("simulator", lambda: robot.run(clock))],
            sim=robot,
        )

    return build
