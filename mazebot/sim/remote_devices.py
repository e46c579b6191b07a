"""The daemon's side of a world in another process: a motor kit and a GPIO thread.

Used by ``mazebot bench --cpu-quota`` (:mod:`mazebot.bench.quota_run`), where the world
runs in its own process (:mod:`mazebot.sim.world_process`) and the daemon opens its
devices exactly as on the robot (``main.robot_hardware_builder``), with two stand-ins:

- :class:`PipeMotorKit` for ``adafruit_motorkit.MotorKit``: the fake kit of the simulator
  (same attributes, same range check), whose every successful write also goes to the
  world's motors;
- :class:`GpioEdgeThread` for lgpio's callback thread: it receives the world's encoder
  edges and drives them onto gpiozero ``MockFactory`` pins, so the daemon's real encoder
  code (:mod:`mazebot.io.encoders`) counts them on a thread of the daemon's own process,
  inside its CPU quota, as lgpio's thread does on the Pi.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import threading
from multiprocessing.connection import Connection
from typing import Any

from mazebot.clock import Clock
from mazebot.io.motors import FakeMotorKit
from mazebot.sim.sim_pins import BoundedHistoryPin, SimPinFactory
from mazebot.sim.world_process import EDGES_TIME, encode_throttle


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


class GpioEdgeThread(threading.Thread):
    """Drives the world's encoder edges onto this process's mock pins, on a thread of its own.

    ``pins`` are the four encoder pin numbers in wire order (left A, left B, right A,
    right B; :func:`mazebot.sim.world_process.encoder_pins`). The thread ends when the
    world closes its end of ``edge_rx`` or :meth:`stop` is called.

    Example::

        factory = GpioEdgeThread.pin_factory()
        encoders = WheelEncoders.from_config(config.encoders, factory)
        thread = GpioEdgeThread(edge_rx, factory, (17, 18, 22, 23))
        thread.start()
    """

    def __init__(self, edge_rx: Connection, factory: SimPinFactory, pins: tuple[int, int, int, int]) -> None:
        super().__init__(name="mazebot-gpio-edges", daemon=True)
        self._rx = edge_rx
        self._factory = factory
        self._pins = [factory.pin(number) for number in pins]
        self._stopping = threading.Event()
        self.edges = 0  # edges driven onto the pins
        self.batches = 0  # messages received (one per world step with edges)

    @staticmethod
    def pin_factory() -> SimPinFactory:
        """The pin factory the daemon's encoders are opened on (the monotonic clock, as the world's)."""
        return SimPinFactory(pin_class=BoundedHistoryPin)

    def run(self) -> None:
        pins, drive = self._pins, self._factory.drive
        head = EDGES_TIME.size
        try:
            while not self._stopping.is_set():
                if not self._rx.poll(0.1):
                    continue
                data = self._rx.recv_bytes()
                # each edge keeps the time the world made it (lgpio's edges carry the kernel's stamp)
                (time_s,) = EDGES_TIME.unpack_from(data)
                for byte in data[head:]:
                    drive(pins[byte >> 1], byte & 1, time_s)
                self.edges += len(data) - head
                self.batches += 1
        except (EOFError, OSError):  # the world is gone
            return
        except (AssertionError, AttributeError):  # the pins were closed under us at shutdown
            return

    def stop(self) -> None:
        """Stop driving pins (within 0.1 s); safe to call more than once."""
        self._stopping.set()
        with contextlib.suppress(RuntimeError):
            if self.is_alive() and threading.current_thread() is not self:
                self.join(1.0)
