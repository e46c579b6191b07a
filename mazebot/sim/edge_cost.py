"""What one encoder edge costs on the Pi's GPIO path, emulated here: the simulator's share of the daemon.

On the robot, lgpio's Python notification thread reads each edge report (16 bytes) from the
kernel's pipe, unpacks it, finds the callback and hands it to gpiozero, which dispatches it
to our quadrature decoder (:class:`mazebot.io.encoders.WheelEncoder`). In the quota
benchmark the same decoder runs behind gpiozero's ``MockFactory`` pins, driven by
:class:`mazebot.sim.remote_devices.GpioEdgeThread` from the world's pipe: the mock's own
bookkeeping (a state history per pin, a clock read, ``drive_high``/``drive_low``) is the
simulator's, not the robot's, and costs several times what the Pi's path does.

This module times the parts of both paths per edge, on the CPU time of the calling thread
(:func:`time.thread_time`: load on the machine does not count, the work of other threads
neither), with the stages interleaved so that they see the same caches and frequency:

1. ``decode``: our two callbacks called directly (the lock and the transition table);
2. ``mock_noop``: mock pins dispatching to a no-op through gpiozero;
3. ``mock_decode``: mock pins dispatching to a real :class:`WheelEncoder` (a check: 3 − 2 ≈ 1);
4. ``mock_alone``: mock pins with no callback (2 − 4 is gpiozero's dispatch, on the Pi too);
5. ``lgpio_loop``: lgpio's notification loop body per report, ending in a no-op (the shape of
   ``_callback_thread`` in ``PY_LGPIO/lgpio_extra.py`` of joan2937/lg: a buffered read, a
   ``struct.unpack``, a scan of the callback list, gpiozero's ``LGPIOPin`` wrapper);
6. ``sim_path``: what the quota benchmark's GPIO edge thread does per edge, batch by batch:
   the world's message unpacked, each edge driven onto the simulator's own pins
   (:class:`mazebot.sim.sim_pins.SimPinFactory`, :class:`~mazebot.sim.sim_pins.BoundedHistoryPin`)
   and decoded by a real :class:`WheelEncoder` (the pipe's read left out, as lgpio's is).

The Pi's path, on this machine, is ``(mock_decode − mock_alone) + lgpio_loop``
(:func:`pi_path_s_per_edge`); what the simulator's stand-in does beyond it per edge is
``sim_path`` minus that (:func:`simulator_excess_s_per_edge`). ``mazebot bench --cpu-quota``
takes the edges times that excess out of the daemon's CPU for its "simulator's share out"
figure. Timed like this, in a loop, the stand-in costs about 1.4 µs an edge and the Pi's
path about 1.1: the excess is small. The edge thread itself is charged several times that
per edge in a quota run: ~45 µs each time it wakes (a hundred times a second, a message of
~13 edges each), the cost of waking a Python thread with cold caches in a busy process that
shares one interpreter lock, which lgpio's callback thread (a Python thread too) pays on the
Pi as well; not the mock's bookkeeping.

Example::

    costs = measure_stages(cycles=5_000, repeats=7)
    pi_path_s_per_edge(costs)            # seconds of CPU per edge, ~1e-6 here
    simulator_excess_s_per_edge(costs)   # ~3e-7
"""

from __future__ import annotations

import io
import statistics
import struct
import time
from collections.abc import Callable
from contextlib import ExitStack

from gpiozero.pins.mock import MockFactory

from mazebot.io.encoders import WheelEncoder

A_PIN = 17
B_PIN = 18

#: A stage: given an exit stack for what it opens, a function that runs ``cycles`` quadrature cycles.
Stage = Callable[[ExitStack], Callable[[int], None]]


def _drive_cycles(factory: MockFactory) -> Callable[[int], None]:
    a, b = factory.pin(A_PIN), factory.pin(B_PIN)

    def run(cycles: int) -> None:
        for _ in range(cycles):
            a.drive_low()
            b.drive_low()
            a.drive_high()
            b.drive_high()

    return run


def stage_decode(stack: ExitStack) -> Callable[[int], None]:
    """Stage 1: our two callbacks called directly, no pins."""
    wheel = stack.enter_context(WheelEncoder(A_PIN, B_PIN, pin_factory=MockFactory()))
    on_a, on_b = wheel.edge_callbacks

    def run(cycles: int) -> None:
        for _ in range(cycles):
            on_a(0.0, 0)
            on_b(0.0, 0)
            on_a(0.0, 1)
            on_b(0.0, 1)

    return run


def stage_mock_noop(stack: ExitStack) -> Callable[[int], None]:
    """Stage 2: mock pins dispatching to a no-op through gpiozero."""
    factory = MockFactory()
    pins = (factory.pin(A_PIN), factory.pin(B_PIN))

    def noop(ticks: float, state: int) -> None:
        pass

    for pin in pins:
        pin.function = "input"
        pin.pull = "up"
        pin.edges = "both"
        pin.when_changed = noop  # the pin holds only a weak reference...
    drive = _drive_cycles(factory)

    def run(cycles: int) -> None:
        drive(cycles)
        assert all(pin.when_changed is noop for pin in pins)  # ...so keep noop alive here

    return run


def stage_mock_decode(stack: ExitStack) -> Callable[[int], None]:
    """Stage 3: mock pins dispatching to a real WheelEncoder."""
    factory = MockFactory()
    wheel = stack.enter_context(WheelEncoder(A_PIN, B_PIN, pin_factory=factory))
    drive = _drive_cycles(factory)

    def run(cycles: int) -> None:
        before = wheel.ticks
        drive(cycles)
        assert wheel.ticks - before == 4 * cycles and wheel.invalid_transitions == 0

    return run


def stage_mock_alone(stack: ExitStack) -> Callable[[int], None]:
    """Stage 4: mock pins with no callback: the mock's own bookkeeping."""
    factory = MockFactory()
    for pin in (factory.pin(A_PIN), factory.pin(B_PIN)):
        pin.function = "input"
        pin.pull = "up"
    return _drive_cycles(factory)


class _CallbackADT:
    """Shape of lgpio's ``_callback_ADT``: the Python loop matches on chip and gpio."""

    def __init__(self, chip: int, gpio: int, func: Callable[[int, int, int, int], None]) -> None:
        self.chip = chip
        self.gpio = gpio
        self.func = func


def stage_lgpio_loop(stack: ExitStack) -> Callable[[int], None]:
    """Stage 5: lgpio's notification loop body per report, ending in a no-op."""

    def noop(ticks: float, state: int) -> None:
        pass

    def lgpio_pin_wrapper(chip: int, gpio: int, level: int, tick: int) -> None:
        # gpiozero's LGPIOPin._call_when_changed converts ns to s before dispatching.
        noop(tick / 1_000_000_000, level)

    callbacks = [_CallbackADT(0, gpio, lgpio_pin_wrapper) for gpio in (17, 18, 22, 23)]
    one_cycle = b"".join(
        struct.pack("QBBBBI", 1_000 * i, 0, (A_PIN, B_PIN)[i % 2], (i // 2) % 2, 0, 0)
        for i in range(4)
    )

    def run(cycles: int) -> None:
        stream = io.BufferedReader(io.BytesIO(one_cycle * cycles))
        for _ in range(4 * cycles):
            msgbuf = stream.read(16)
            tick, chip, gpio, level, flags, _pad = struct.unpack("QBBBBI", msgbuf)
            if flags == 0:
                for cb in callbacks:
                    if cb.chip == chip and cb.gpio == gpio:
                        cb.func(chip, gpio, level, tick)

    return run


def stage_sim_path(stack: ExitStack) -> Callable[[int], None]:
    """Stage 6: the GPIO edge thread's loop body on the simulator's pins, a real encoder attached.

    The world's messages are prebuilt (one per quadrature cycle here: the thread unpacks each
    and drives its edges), so the pipe's read is left out, as stage 5 leaves lgpio's out.
    """
    from mazebot.sim.sim_pins import BoundedHistoryPin, SimPinFactory
    from mazebot.sim.world_process import drive_edges, edges_message

    factory = SimPinFactory(pin_class=BoundedHistoryPin)
    wheel = stack.enter_context(WheelEncoder(A_PIN, B_PIN, pin_factory=factory))
    pins = [factory.pin(A_PIN), factory.pin(B_PIN)]
    # the wire format of the world's edges: a byte per edge (pin index << 1 | level), each edge's time
    message = edges_message(bytes([0 << 1 | 0, 1 << 1 | 0, 0 << 1 | 1, 1 << 1 | 1]), (1.0, 1.0005, 1.001, 1.0015))
    drive = factory.drive

    def run(cycles: int) -> None:
        before = wheel.ticks
        for _ in range(cycles):
            drive_edges(message, pins, drive)
        assert wheel.ticks - before == 4 * cycles and wheel.invalid_transitions == 0

    return run


STAGES: dict[str, Stage] = {
    "decode": stage_decode,
    "mock_noop": stage_mock_noop,
    "mock_decode": stage_mock_decode,
    "mock_alone": stage_mock_alone,
    "lgpio_loop": stage_lgpio_loop,
    "sim_path": stage_sim_path,
}


def measure_stages(
    cycles: int = 5_000, repeats: int = 7, clock: Callable[[], float] = time.thread_time, best: bool = False
) -> dict[str, float]:
    """Seconds per edge of each stage: the median of ``repeats`` runs (``best``: the fastest).

    The stages run interleaved, each ``4 * cycles`` edges a run, timed by ``clock`` (the
    calling thread's CPU time by default: what a thread of the daemon's own would be charged).
    """
    if cycles < 1 or repeats < 1:
        raise ValueError(f"cycles and repeats must be at least 1, got {cycles} and {repeats}")
    times: dict[str, list[float]] = {name: [] for name in STAGES}
    with ExitStack() as stack:
        runs = {name: make(stack) for name, make in STAGES.items()}
        for _ in range(repeats):
            for name, run in runs.items():
                start = clock()
                run(cycles)
                times[name].append((clock() - start) / (4 * cycles))
    pick = min if best else statistics.median
    return {name: float(pick(values)) for name, values in times.items()}


def pi_path_s_per_edge(costs: dict[str, float]) -> float:
    """The Pi's path per edge from :func:`measure_stages`: our decode behind gpiozero's dispatch, lgpio's loop.

    ``mock_decode − mock_alone`` is the mock path with the mock's own bookkeeping taken out:
    gpiozero's dispatch and our decoder as gpiozero calls them (a little more than stage 1's
    direct call plus stage 2's dispatch to a no-op, so the larger of the two readings).
    """
    ours = max(costs["mock_decode"] - costs["mock_alone"], costs["decode"], 0.0)
    return ours + costs["lgpio_loop"]


def simulator_excess_s_per_edge(costs: dict[str, float]) -> float:
    """What the simulator's GPIO stand-in does per edge beyond the Pi's path (never below 0)."""
    return max(costs["sim_path"] - pi_path_s_per_edge(costs), 0.0)
