"""``mazebot run --sim``: the daemon's real drivers, opened on a simulated robot.

The motor driver writes into the simulator's fake MotorKit, the encoder driver counts
edges on the simulator's gpiozero mock pins, and the lidar driver talks to the RPLidar
emulator over an in-memory byte stream. Nothing in the daemon knows it is simulated.

The world is brought up to the present (:meth:`SimulatedRobot.catch_up`) whenever a driver
reads a sensor or writes a throttle, not only at the simulator's own ticks: a real lidar
streams and real encoders count while the daemon's loop is busy elsewhere.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import threading
from collections.abc import Callable
from contextlib import AsyncExitStack
from typing import Any

from mazebot.clock import Clock
from mazebot.config import Config
from mazebot.hardware import Hardware, HardwareBuilder
from mazebot.io.encoders import WheelEncoders
from mazebot.io.motors import DifferentialMotors
from mazebot.io.rplidar import RPLidar
from mazebot.io.serial_link import ByteLink, memory_link_pair
from mazebot.sim.lidar_emulator import RPLidarEmulator
from mazebot.sim.robot import SimulatedRobot
from mazebot.sim.world_source import make_world

log = logging.getLogger(__name__)


class SimLidarLine:
    """The serial line between the daemon's lidar driver and the emulator.

    Each ``connect()`` is a fresh line (like replugging the USB cable): the emulator
    serves the device end until the driver closes its end.
    """

    def __init__(self, emulator: RPLidarEmulator, catch_up: Callable[[], None] | None = None) -> None:
        self.emulator = emulator
        self.catch_up = catch_up  # brings the world (and so the lidar's stream) up to now
        self._served: set[asyncio.Task[None]] = set()
        self._device_writers: list[asyncio.StreamWriter] = []
        self.plugged = True
        self.connects = 0  # lines opened (the first one and every reconnect)
        self._silent_ends: list[object] = []  # device ends of lines opened at a wrong speed

    def unplug(self) -> None:
        """Pull the USB cable: the open line ends (the driver reads end of file) and the port is gone."""
        self.plugged = False
        for writer in self._device_writers:
            writer.close()
        self._device_writers.clear()

    def replug(self) -> None:
        """Put the cable back: the port can be opened again (the device powers up, motor stopped)."""
        self.plugged = True
        self.emulator.motor_on = False
        self.emulator.mode = None

    async def connect(self) -> ByteLink:
        if not self.plugged:
            # what opening /dev/ttyUSB0 gives once the adapter is gone
            raise FileNotFoundError(errno.ENOENT, "No such file or directory: the lidar's USB adapter is unplugged")
        self.connects += 1
        # The driver turns the motor on by clearing DTR, as on the A1's USB adapter.
        link, (device_reader, device_writer) = memory_link_pair(on_motor=lambda on: self.emulator.set_dtr(not on))
        self._device_writers = [w for w in self._device_writers if not w.is_closing()] + [device_writer]
        task = asyncio.create_task(self.emulator.serve(device_reader, device_writer), name="sim-lidar-device")
        self._served.add(task)
        task.add_done_callback(self._served.discard)
        return link if self.catch_up is None else _StreamingLink(link, self.catch_up)

    async def connect_at(self, baudrate: int) -> ByteLink:
        """A line opened at ``baudrate``: at the unit's own speed the device answers;
        at any other it hears only noise and its answers are noise, so nothing comes."""
        if baudrate == self.emulator.model.baudrate:
            return await self.connect()
        if not self.plugged:
            raise FileNotFoundError(errno.ENOENT, "No such file or directory: the lidar's USB adapter is unplugged")
        self.connects += 1
        link, device_end = memory_link_pair(on_motor=lambda on: None)
        self._silent_ends.append(device_end)  # nobody serves it, but it stays open
        return link

    async def close(self) -> None:
        for task in list(self._served):
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task


class _StreamingLink:
    """The host end of the lidar's line, as if the device streamed without pause.

    The emulator sends on the simulator's ticks; a reader that comes later (its loop was
    busy) would get only what was sent by the last tick and stamp it with the later time
    of the read. A real A1 keeps sending meanwhile, so the newest byte a read returns is
    always just arrived: each read first brings the world up to now.
    """

    def __init__(self, link: Any, catch_up: Callable[[], None]) -> None:
        self._link = link
        self._catch_up = catch_up

    async def read(self, max_bytes: int = 4096) -> bytes:
        self._catch_up()
        data = await self._link.read(max_bytes)
        # woken up later than the bytes came: what the device sent since is on the line too
        self._catch_up()
        if len(data) < max_bytes and self._link.pending_bytes():
            data += await self._link.read(max_bytes - len(data))
        return data

    def __getattr__(self, name: str) -> Any:
        return getattr(self._link, name)


def sim_hardware_builder(
    maze_path: str | None = None, seed: int | None = None, size: tuple[int, int] | None = None
) -> HardwareBuilder:
    """A hardware builder for ``run_daemon`` that opens the drivers on a simulated robot."""

    async def build(config: Config, clock: Clock, stack: AsyncExitStack) -> Hardware:
        world = make_world(config, maze_path, seed, size)
        robot = SimulatedRobot(world, config, seed=config.sim.seed if seed is None else seed, clock=clock)
        stack.callback(robot.close)
        robot.step(clock.now_s())

        emulator: RPLidarEmulator | None = None
        loop_thread = threading.get_ident()

        def catch_up() -> None:
            if threading.get_ident() != loop_thread:  # the motors' hang guard braking: the world is the loop's
                return
            robot.catch_up(clock.now_s())
            if emulator is not None and emulator.self_paced:  # a paced one was pumped by catch_up
                emulator.pump()

        robot.kit.before_write = catch_up
        motors = DifferentialMotors.from_config(config.motors, robot.kit, clock)
        stack.callback(motors.close)
        encoders = WheelEncoders.from_config(config.encoders, robot.pin_factory)
        stack.callback(encoders.close)
        encoders.before_read = catch_up  # a reading shows the wheels as they are at the clock's time
        robot.encoders = encoders

        emulator = robot.make_lidar(clock)
        line = SimLidarLine(emulator, catch_up)
        stack.push_async_callback(line.close)
        lidar = RPLidar.from_config(
            config.lidar, clock, link_factory=lambda: line.connect_at(config.lidar.baudrate),
            probe_factory=line.connect_at,
        )
        await stack.enter_async_context(lidar)
        robot.lidar_line = line  # the fault injector pulls its cable (mazebot.sim.faults)
        return Hardware(
            lidar=lidar,
            encoders=encoders,
            motors=motors,
            description=f"simulated robot in {world.name} ({len(world.segments)} wall segments)",
            extra_tasks=[("simulator", lambda: robot.run(clock))],
            sim=robot,
        )

    return build


def simulated_robot(hardware: Hardware) -> SimulatedRobot:
    """The simulated robot behind ``hardware``: the harness's ground truth (the pose, the world, the kit)."""
    if not isinstance(hardware.sim, SimulatedRobot):
        raise TypeError(f"{hardware.description}: not a simulated robot, so no ground truth to measure against")
    return hardware.sim
