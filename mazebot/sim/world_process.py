"""The simulated world in a process of its own, behind the robot's real hardware boundaries.

``mazebot bench --cpu-quota`` runs the daemon under a CPU quota; the world must not be
slowed by that quota (nor share the daemon's GIL), so it runs here, in a second process,
on the real clock, and meets the daemon only where the real robot meets the world:

- **lidar**: the RPLidar emulator serves a pseudo-terminal (:mod:`mazebot.sim.pty_lidar`);
  the daemon's serial driver opens its path with pyserial-asyncio, as it opens
  ``/dev/ttyUSB0`` on the robot;
- **motors**: the throttles the daemon writes into its motor kit arrive on ``motor_rx``
  (:func:`decode_throttle`) and are written into this world's fake MotorKit;
- **encoders**: every step's quadrature edges, recorded on this world's mock pins
  (:class:`EdgeRecordingFactory`), go to the daemon on ``edge_tx``, one byte an edge
  (:func:`edge_byte`) and each edge's own time (:func:`edges_message`), in the order they
  happened on both wheels, where a GPIO thread drives its own mock pins with them
  (:mod:`mazebot.sim.remote_devices`, :func:`drive_edges`);
- **ground truth** for the benchmark goes to the parent on ``report_tx``: ``("ready",
  pty_path)`` once the lidar is served, ``("truth", time_s, x_m, y_m, theta_rad,
  collisions)`` every :data:`TRUTH_PERIOD_S`, and ``("summary", dict)`` when told to stop
  (``"stop"`` on ``control_rx``, or the parent gone).

The process ignores SIGINT (Ctrl-C reaches every process of the terminal's group): the
parent stops the daemon first and then the world, so the daemon never loses its devices
while it is still driving. A SIGTERM stops it once the daemon has closed its motor line
(at most :data:`SIGTERM_GRACE_S` later).
"""

from __future__ import annotations

import asyncio
import contextlib
import signal
import struct
from array import array
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection
from typing import Any

from gpiozero.pins.mock import MockPin

from mazebot.sim.pipe_kit import decode_throttle
from mazebot.sim.pipe_kit import encode_throttle as encode_throttle  # re-exported: the wire's other end
from mazebot.sim.sim_pins import BoundedHistoryPin, SimPinFactory

#: How often the world reports the true pose to the parent (seconds of the real clock).
TRUTH_PERIOD_S = 0.2
#: After a SIGTERM, how long the world waits for the daemon to stop (and close its motor line) first.
#: A SIGTERM to the process group reaches the daemon while it may still be starting, and on a
#: loaded machine its start and its stop (the wheels braked through this world's motor line) took
#: longer than 5 s: the brake then met a world already gone. The bench's parent stops the world
#: once the daemon has ended, whenever that is; this only bounds a world whose parent is gone.
SIGTERM_GRACE_S = 60.0
#: The head of one message of edges: the clock time of its first edge (the monotonic clock both
#: processes read); then one :func:`edge_byte` per edge, in order; then each edge's time after the
#: first one's, seconds, float32 (``array("f")``, this machine's byte order: both ends are on it).
EDGES_TIME = struct.Struct("<d")


def edge_byte(index: int, level: int) -> int:
    """One edge on the wire: the encoder pin's index (0..3: left A, left B, right A, right B) and its new level."""
    return (index << 1) | (1 if level else 0)


def edges_message(codes: bytes, times_s: Sequence[float]) -> bytes:
    """The wire message of edges ``codes`` (:func:`edge_byte` each) that happened at ``times_s``, in order."""
    first_s = times_s[0]
    return EDGES_TIME.pack(first_s) + codes + array("f", [t - first_s for t in times_s]).tobytes()


def drive_edges(message: bytes, pins: Sequence[MockPin], drive: Callable[[MockPin, int, float], None]) -> int:
    """Drive each edge of ``message`` (:func:`edges_message`) onto ``pins`` (wire order) at its own
    time (``drive``: :meth:`mazebot.sim.sim_pins.SimPinFactory.drive`); returns how many."""
    (first_s,) = EDGES_TIME.unpack_from(message)
    count = (len(message) - EDGES_TIME.size) // 5  # a byte and a float32 an edge
    codes_end = EDGES_TIME.size + count
    offsets = array("f")
    offsets.frombytes(message[codes_end:])
    for byte, offset_s in zip(message[EDGES_TIME.size:codes_end], offsets, strict=True):
        drive(pins[byte >> 1], byte & 1, first_s + offset_s)
    return count


class EdgeRecordingPin(BoundedHistoryPin):
    """A simulator pin that also notes each edge it is driven through on its factory's ``edges``.

    Only edges driven with ``drive_high``/``drive_low`` are noted: a level that changes
    without an interrupt (a lost edge, :class:`mazebot.sim.encoder_signals.QuadratureSignal`)
    reaches the daemon as the impossible transition it is.
    """

    #: Index of this pin on the wire (:func:`edge_byte`); None: not an encoder pin.
    edge_index: int | None = None

    def drive_high(self) -> None:
        if not self._state and self.edge_index is not None:
            self._factory.note_edge(edge_byte(self.edge_index, 1))
        super().drive_high()

    def drive_low(self) -> None:
        if self._state and self.edge_index is not None:
            self._factory.note_edge(edge_byte(self.edge_index, 0))
        super().drive_low()


class EdgeRecordingFactory(SimPinFactory):
    """The simulator's pin factory whose encoder pins note their edges, with their times.

    Example::

        factory = EdgeRecordingFactory((17, 18, 22, 23))
        factory.drive(factory.pin(17), 0, time_s=12.5)
        factory.take_edges()     # b"\\x00": pin 0, level 0 (its time, 12.5, in take_message)
    """

    def __init__(self, encoder_pins: tuple[int, int, int, int]) -> None:
        super().__init__(pin_class=EdgeRecordingPin)
        self.edges = bytearray()
        self.edge_times_s: list[float] = []
        for index, number in enumerate(encoder_pins):
            self.pin(number).edge_index = index

    def note_edge(self, code: int) -> None:
        """An encoder pin changes now (at :meth:`edge_time`): ``code`` is its :func:`edge_byte`."""
        self.edges.append(code)
        self.edge_times_s.append(self.edge_time())

    def take_edges(self) -> bytes:
        """The edges noted since the last call, in order (their times are dropped)."""
        data = bytes(self.edges)
        self.edges.clear()
        self.edge_times_s.clear()
        return data

    def take_message(self) -> bytes:
        """The edges noted since the last call as one wire message (:func:`edges_message`); b"": none."""
        times_s, self.edge_times_s = self.edge_times_s, []
        message = edges_message(bytes(self.edges), times_s) if times_s else b""
        self.edges.clear()
        return message


def encoder_pins(config: Any) -> tuple[int, int, int, int]:
    """The four encoder pins in wire order (left A, left B, right A, right B)."""
    enc = config.encoders
    return enc.left_a_pin, enc.left_b_pin, enc.right_a_pin, enc.right_b_pin


async def serve_world(
    config: Any,
    maze_path: str | None,
    seed: int | None,
    size: tuple[int, int] | None,
    motor_rx: Connection,
    edge_tx: Connection,
    report_tx: Connection,
    control_rx: Connection,
) -> None:
    """Build the world, serve its lidar on a pty, and run it on the real clock until told to stop."""
    from mazebot.clock import RealClock
    from mazebot.sim.pty_lidar import pty_device
    from mazebot.sim.robot import SimulatedRobot
    from mazebot.sim.world_source import make_world

    loop = asyncio.get_running_loop()
    clock = RealClock()
    stop = asyncio.Event()
    daemon_gone = False

    def on_sigterm() -> None:
        # a SIGTERM to the whole process group: the daemon must stop its wheels first
        if daemon_gone:
            stop.set()
        else:
            loop.call_later(SIGTERM_GRACE_S, stop.set)

    loop.add_signal_handler(signal.SIGTERM, on_sigterm)
    world = make_world(config, maze_path, seed, size)
    factory = EdgeRecordingFactory(encoder_pins(config))
    robot = SimulatedRobot(world, config, seed=config.sim.seed if seed is None else seed, clock=clock,
                           pin_factory=factory)
    robot.step(clock.now_s())
    counts = {"motor_writes": 0, "edges_sent": 0}

    def on_motor() -> None:
        try:
            while motor_rx.poll():
                channel, throttle = decode_throttle(motor_rx.recv_bytes())
                getattr(robot.kit, f"motor{channel}").throttle = throttle
                counts["motor_writes"] += 1
        except (EOFError, OSError):  # the daemon is gone: its motors are off
            nonlocal daemon_gone
            daemon_gone = True
            loop.remove_reader(motor_rx.fileno())
            for channel in (1, 2, 3, 4):
                getattr(robot.kit, f"motor{channel}").throttle = None

    def on_control() -> None:
        try:
            message = control_rx.recv()
        except (EOFError, OSError):  # the parent is gone
            message = "stop"
        if message == "stop":
            loop.remove_reader(control_rx.fileno())
            stop.set()

    def send_edges() -> None:
        message = factory.take_message()
        if message:
            with contextlib.suppress(OSError):  # the daemon is gone; the world runs on until stopped
                # each edge with its own time, as the kernel stamps each edge on the robot: the daemon's
                # encoders date the ticks by it, not by when its throttled GPIO thread got to them
                edge_tx.send_bytes(message)
                counts["edges_sent"] += (len(message) - EDGES_TIME.size) // 5

    async def report_truth() -> None:
        while True:
            x, y, th = robot.physics.pose
            report_tx.send(("truth", clock.now_s(), x, y, th, int(robot.physics.collisions)))
            await clock.sleep(TRUTH_PERIOD_S)

    emulator = robot.make_lidar(clock, after_step=send_edges)
    loop.add_reader(motor_rx.fileno(), on_motor)
    loop.add_reader(control_rx.fileno(), on_control)
    start_s = clock.now_s()
    try:
        async with pty_device(emulator) as path:
            report_tx.send(("ready", path))
            tasks = [asyncio.create_task(robot.run(clock, after_step=send_edges), name="world-physics"),
                     asyncio.create_task(report_truth(), name="world-truth")]
            try:
                await stop.wait()
            finally:
                for task in tasks:
                    task.cancel()
                await asyncio.gather(*tasks, return_exceptions=True)
    finally:
        with contextlib.suppress(ValueError, OSError):
            loop.remove_reader(motor_rx.fileno())
        robot.close()
    with contextlib.suppress(OSError):
        report_tx.send(("summary", {
            "world": world.name,
            "start_s": start_s,
            "sim_time_s": (robot.time_s or start_s) - start_s,
            "trajectory": list(robot.trajectory),
            "collisions": int(robot.physics.collisions),
            "odometer_m": float(robot.physics.odometer_m),
            "edges_driven": robot.left_signal.edges + robot.right_signal.edges,
            "lidar_bytes_sent": emulator.stats.bytes_sent,
            "lidar_samples_sent": emulator.stats.samples_sent,
            "lidar_revolution_starts_s": list(emulator.stats.revolution_starts_s),
            **counts,
        }))


def world_main(
    config: Any,
    maze_path: str | None,
    seed: int | None,
    size: tuple[int, int] | None,
    motor_rx: Connection,
    edge_tx: Connection,
    report_tx: Connection,
    control_rx: Connection,
) -> None:
    """The world process's entry point (a ``multiprocessing`` target)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops us after the daemon
    try:
        asyncio.run(serve_world(config, maze_path, seed, size, motor_rx, edge_tx, report_tx, control_rx))
    except BaseException as exc:  # the parent reports it as one line; the daemon sees its lidar go
        with contextlib.suppress(OSError):
            report_tx.send(("error", f"{type(exc).__name__}: {exc}"))
        raise
    finally:
        for conn in (motor_rx, edge_tx, report_tx, control_rx):
            conn.close()
