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
import os
import select
import threading
import time
from multiprocessing.connection import Connection

from mazebot.sim.pipe_kit import PipeKitOpener as PipeKitOpener  # re-exported: the bench and tests open them here
from mazebot.sim.pipe_kit import PipeMotorKit as PipeMotorKit
from mazebot.sim.sim_pins import BoundedHistoryPin, SimPinFactory
from mazebot.sim.world_process import drive_edges

#: How often (ms) the GPIO edge thread looks whether it was asked to stop while no edge comes.
STOP_POLL_MS = 100


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
        # lgpio's thread blocks on its notification pipe; this one waits on the world's pipe with one
        # poll object made here: Connection.poll(timeout) builds a selector per call, ~40 µs a wake-up
        # of a cold thread (100 a second) that is the simulator's plumbing, not the robot's
        self._poller = select.poll()
        self._poller.register(edge_rx.fileno(), select.POLLIN)
        self.edges = 0  # edges driven onto the pins
        self.batches = 0  # messages received (one per world step with edges)

    @staticmethod
    def pin_factory() -> SimPinFactory:
        """The pin factory the daemon's encoders are opened on (the monotonic clock, as the world's)."""
        return SimPinFactory(pin_class=BoundedHistoryPin)

    def run(self) -> None:
        pins, drive = self._pins, self._factory.drive
        try:
            while not self._stopping.is_set():
                if not self._poller.poll(STOP_POLL_MS):
                    continue
                # each edge keeps the time the world made it (lgpio's edges carry the kernel's stamp)
                self.edges += drive_edges(self._rx.recv_bytes(), pins, drive)
                self.batches += 1
        except (EOFError, OSError):  # the world is gone
            return
        except (AssertionError, AttributeError):  # the pins were closed under us at shutdown
            return

    def cpu_s(self) -> float | None:
        """The CPU seconds this thread has used so far (its own clock, read from another thread); None
        before it started or after it ended.

        Its work is the simulator's stand-in for lgpio's callback thread: the quota benchmark
        puts the Pi's path per edge (:mod:`mazebot.sim.edge_cost`) in place of it.
        """
        ident = self.ident
        if ident is None or not self.is_alive():
            return None
        try:
            return time.clock_gettime(time.pthread_getcpuclockid(ident))
        except (OSError, AttributeError):  # no per-thread clock: the kernel's account, in clock ticks
            try:
                with open(f"/proc/self/task/{self.native_id}/stat") as f:
                    fields = f.read().rpartition(")")[2].split()
                return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
            except (OSError, IndexError, ValueError):
                return None

    def stop(self) -> None:
        """Stop driving pins (within 0.1 s); safe to call more than once."""
        self._stopping.set()
        with contextlib.suppress(RuntimeError):
            if self.is_alive() and threading.current_thread() is not self:
                self.join(1.0)
