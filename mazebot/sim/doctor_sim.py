"""``mazebot doctor --sim``: the doctor's parts on the simulated robot, with one part broken on request.

The drivers are the real ones: the lidar emulator is served on a pseudo-terminal that the
doctor opens as its serial port (:mod:`mazebot.sim.pty_lidar`), the encoders count edges
on gpiozero mock pins, the motors write into the simulator's motor HAT. A fault breaks
the world, never the doctor: a wiring fault is a robot built differently from its config
(the simulator's physics follows ``robot_config``, the drivers follow ``config``); what the
operating system would say (under-voltage, heat, a full disk, an unset clock, a port this
user may not open) is said by the :class:`~mazebot.doctor.SystemProbe`.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import errno
import tempfile
from collections import namedtuple
from collections.abc import AsyncIterator
from dataclasses import replace
from pathlib import Path
from typing import Any

from mazebot.clock import RealClock
from mazebot.config import Config
from mazebot.doctor import Parts, SystemProbe
from mazebot.sim.pty_lidar import pty_device
from mazebot.sim.robot import SimulatedRobot
from mazebot.sim.world_source import make_world

#: Each fault and the part whose line it must turn to FAIL (the tests check every one).
SIM_FAULTS: dict[str, str] = {
    "lidar-missing": "serial port",
    "serial-permission": "serial port",
    "lidar-silent": "lidar info",
    "lidar-health": "lidar health",
    "lidar-jammed": "lidar rotation",
    "lidar-blind": "lidar revolution",
    "hat-missing": "motor driver",
    "encoder-dead": "left encoder",
    "encoder-inverted": "left encoder",
    "motors-swapped": "motor channels",
    "undervoltage": "power",
    "hot": "CPU temperature",
    "disk-full": "free space",
    "clock-unset": "clock",
}

_Usage = namedtuple("_Usage", "total used free")


def _probe(fault: str | None) -> SystemProbe:
    """A Raspberry Pi in good health, unless the fault says otherwise (flag values: Raspberry Pi
    documentation, ``vcgencmd get_throttled``; the sysfs file's format: hexadecimal)."""
    throttled = {"undervoltage": "50005"}.get(fault or "", "0")
    temp = {"hot": "84500"}.get(fault or "", "47200")
    probe = SystemProbe(throttled=lambda: throttled, cpu_temp_text=lambda: temp, ntp_synchronized=lambda: True)
    if fault == "disk-full":
        probe.disk_usage = lambda path: _Usage(32 * 1024**3, 32 * 1024**3 - 20 * 1024**2, 20 * 1024**2)
    if fault == "clock-unset":
        probe.now = lambda: dt.datetime(1970, 1, 1, 0, 0, 12, tzinfo=dt.UTC)
    if fault == "serial-permission":
        def refuse(port: str) -> None:
            raise PermissionError(errno.EACCES, "Permission denied", port)

        probe.open_port = refuse
    return probe


def robot_config(config: Config, fault: str | None) -> Config:
    """The robot as it is really built: the config, but wired differently for a wiring fault."""
    robot = config.model_copy(deep=True)
    if fault == "encoder-inverted":
        robot.encoders.left_invert = not robot.encoders.left_invert
    if fault == "motors-swapped":
        robot.motors = robot.motors.model_copy(
            update={"left_channel": config.motors.right_channel, "right_channel": config.motors.left_channel})
    return robot


@contextlib.asynccontextmanager
async def sim_parts(config: Config, fault: str | None = None) -> AsyncIterator[Parts]:
    """The simulated robot's parts for one doctor run; the world runs until the block ends."""
    clock = RealClock()
    world = make_world(config, None, None, None)
    robot = SimulatedRobot(world, robot_config(config, fault), seed=config.sim.seed, clock=clock)
    robot.step(clock.now_s())
    robot.kit.before_write = lambda: robot.catch_up(clock.now_s())  # a throttle acts from its write on
    emulator = robot.make_lidar(clock)
    if fault == "lidar-silent":
        emulator.frozen = True
    elif fault == "lidar-health":
        emulator.protection_stop()
    elif fault == "lidar-jammed":
        emulator.motor_jammed = True
    elif fault == "lidar-blind":
        robot.lidar_head.params = replace(robot.lidar_head.params, dropout=0.97)
    if fault == "encoder-dead":
        robot.left_signal.dead = True
    if fault == "hat-missing":
        robot.kit.fail_writes()
    physics = asyncio.create_task(robot.run(clock), name="doctor-sim-world")
    try:
        with tempfile.TemporaryDirectory(prefix="mazebot-doctor-") as tmp:
            async with pty_device(emulator) as path:
                port = str(Path(tmp) / "ttyUSB0") if fault == "lidar-missing" else path
                # the emulated unit speaks at its model's speed; a pty has no DTR for the motor
                lidar = config.lidar.model_copy(update={"port": port, "baudrate": emulator.model.baudrate})

                def open_kit() -> Any:
                    return robot.kit

                yield Parts(
                    probe=_probe(fault), lidar=lidar, open_kit=open_kit,
                    kit_name="simulated motor HAT", open_pins=lambda: robot.pin_factory, clock=clock,
                    state_dir=Path(tmp) / "state", close_pins=False,
                )
    finally:
        physics.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await physics
        robot.close()
