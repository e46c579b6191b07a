"""The hardware boundary: what the daemon's tasks call on the lidar, the encoders and the motors.

Three small :class:`typing.Protocol` classes name exactly the calls the tasks make, so the
real drivers (:class:`mazebot.io.rplidar.RPLidar`, :class:`mazebot.io.encoders.WheelEncoders`,
:class:`mazebot.io.motors.DifferentialMotors`), the simulator's devices (which are those same
drivers on simulated pins and an emulated serial line, :mod:`mazebot.sim.backend`), the
recording taps (:mod:`mazebot.tasks.record_task`) and the fakes of the tests are all
interchangeable, and mypy checks that each one still fits. A :class:`Hardware` is one run's
set of opened devices, built by a :data:`HardwareBuilder` (real: :func:`mazebot.main.
robot_hardware_builder`; simulated: :func:`mazebot.sim.backend.sim_hardware_builder`).

This module sits low in the import layers (``docs/design.md``, "Layers"): it imports the io
types only for the type checker, so the product and the harness can both depend on it.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Awaitable, Callable, Coroutine
from contextlib import AsyncExitStack
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from gpiozero import Factory

    from mazebot.clock import Clock
    from mazebot.config import Config
    from mazebot.io.encoders import EncoderReading
    from mazebot.io.motor_hat import MotorKitLike
    from mazebot.io.rplidar import LidarStats
    from mazebot.io.scan import Scan


class Lidar(Protocol):
    """A scanning lidar: one :class:`~mazebot.io.scan.Scan` per revolution, and its driver's counters."""

    @property
    def stats(self) -> LidarStats: ...

    def scans(self) -> AsyncIterator[Scan]: ...


class LidarActivity(Protocol):
    """What the health monitor reads to tell a silent lidar from one whose bytes make no revolution."""

    @property
    def stats(self) -> LidarStats: ...

    def bytes_waiting(self) -> int: ...


class Encoders(Protocol):
    """Both wheels' encoder totals, read in one consistent snapshot."""

    def read(self) -> EncoderReading: ...


class Motors(Protocol):
    """Two wheel motors: throttles in [-1, 1] for the left and right wheel, and a brake."""

    def set(self, left: float, right: float) -> None: ...

    def stop(self) -> None: ...


#: A coroutine the supervisor starts as a task (the same shape as :data:`mazebot.tasks.supervisor.TaskFactory`).
TaskFactory = Callable[[], Coroutine[Any, Any, None]]


@dataclass
class Hardware:
    """The devices one run drives, real or simulated, already opened.

    ``extra_tasks`` are tasks the backend itself needs (the simulator's physics);
    ``description`` is one line for the log and the status page. ``sim`` is the simulated
    robot when there is one (ground truth for the harness): the product never looks inside
    it, so here it is just an ``object``; the harness gets it back with its type from
    :func:`mazebot.sim.backend.simulated_robot` (naming the type here would import the simulator).
    """

    lidar: Lidar
    encoders: Encoders
    motors: Motors
    description: str
    extra_tasks: list[tuple[str, TaskFactory]] = field(default_factory=list)
    sim: object | None = None
    #: opens these motors' kit again in another process (picklable; the control process's
    #: driver), or None where only this process can drive them (the in-process simulator, GPIO lines)
    motor_kit_opener: Callable[[], MotorKitLike] | None = None


HardwareBuilder = Callable[["Config", "Clock", AsyncExitStack], Awaitable[Hardware]]


def lgpio_pin_factory() -> Factory:
    """gpiozero's pin factory for the Raspberry Pi 5's GPIO chip (lgpio), imported only when asked."""
    from gpiozero.pins.lgpio import LGPIOFactory

    return LGPIOFactory()
