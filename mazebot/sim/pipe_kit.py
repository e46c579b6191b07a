"""The simulated motor HAT of the quota benchmark: throttle writes sent to the world process.

Kept apart from :mod:`mazebot.sim.remote_devices` (gpiozero's mock pins, the world's wire
format) because the daemon's control process opens its motors with it: a forked process
that imports only this and :mod:`mazebot.io.motors` stays as small as on the robot, where it
opens the HAT's driver.
"""

from __future__ import annotations

import math
import multiprocessing
import struct
import threading
from multiprocessing.connection import Connection
from typing import Any

from mazebot.clock import Clock
from mazebot.io.motors import FakeMotorKit

#: One throttle message: the motor channel, and the throttle (NaN: coasting, ``None``).
THROTTLE = struct.Struct("<Bd")


def encode_throttle(channel: int, throttle: float | None) -> bytes:
    """A throttle write as it crosses from the daemon to the world."""
    return THROTTLE.pack(channel, math.nan if throttle is None else throttle)


def decode_throttle(data: bytes) -> tuple[int, float | None]:
    """``(channel, throttle)`` of :func:`encode_throttle`'s bytes."""
    channel, value = THROTTLE.unpack(data)
    return channel, None if math.isnan(value) else value


class PipeMotorKit(FakeMotorKit):
    """A fake MotorKit whose throttle writes are sent to the world process on ``motor_tx``.

    Example::

        kit = PipeMotorKit(motor_tx)
        kit.motor1.throttle = 0.5      # the world's left wheel (channel 1) speeds up
    """

    def __init__(self, motor_tx: Connection, clock: Clock | None = None, shared_count: Any = None) -> None:
        super().__init__(clock)
        self._tx = motor_tx
        self._tx_lock = threading.Lock()  # control and the supervisor's emergency stop may both write
        self.writes_sent = 0  # throttle writes that reached the world
        # a shared-memory counter (multiprocessing RawValue) the opening process reads too; this kit its one writer
        self._shared_count = shared_count

    def _write(self, channel: int, throttle: float | None) -> None:
        super()._write(channel, throttle)  # the range check and the command log
        try:
            with self._tx_lock:
                self._tx.send_bytes(encode_throttle(channel, throttle))
                self.writes_sent += 1
                if self._shared_count is not None:
                    self._shared_count.value += 1
        except (OSError, ValueError) as exc:  # the world is gone: as an I2C bus that stopped answering
            raise OSError(f"motor{channel}: the simulated motor HAT is gone ({exc})") from exc


class PipeKitOpener:
    """Opens a :class:`PipeMotorKit` on ``motor_tx`` in whichever process calls it (picklable).

    The control process (:mod:`mazebot.tasks.control_process`) gets the pipe's end this way
    and writes the world's motors itself; both processes may write: each throttle is one
    message of a few bytes, one ``write`` to the pipe, and pipe writes of up to ``PIPE_BUF``
    bytes are never interleaved (POSIX ``write(2)``).
    """

    def __init__(self, motor_tx: Connection) -> None:
        self.motor_tx = motor_tx
        # the writes of the kit it opens in the other process, counted where this process can read
        # them (the benchmark checks every throttle written reached the world)
        self.writes = multiprocessing.get_context("forkserver").RawValue("q", 0)

    @property
    def writes_sent(self) -> int:
        """Throttle writes the kits opened by this opener (in any process) sent to the world."""
        return int(self.writes.value)

    def __call__(self) -> PipeMotorKit:
        from mazebot.clock import RealClock

        return PipeMotorKit(self.motor_tx, RealClock(), shared_count=self.writes)
