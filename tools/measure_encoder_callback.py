"""Measure what one encoder edge costs on the GPIO callback thread.

Run from the repository root:

    .venv/bin/python tools/measure_encoder_callback.py

Optional: ``--cycles N`` (full quadrature cycles per run, default 20 000 = 80 000
edges), ``--repeats R`` (runs per stage, best kept, default 15).

Stages, each timed per edge (best of the repeats, to shed scheduler noise; the stages
run interleaved so that they see the same machine load):

1. ``decode``: our callback alone (``WheelEncoder._on_a_changed``/``_on_b_changed``
   called directly): the lock and the decoder step. This is the cost that is ours.
2. ``mock+dispatch, no-op``: MockFactory pins driven through the cycle with a no-op
   ``when_changed``: the mock's own bookkeeping (state history, monotonic clock) plus
   gpiozero's dispatch (``PiPin._call_when_changed``, weak-method lookup).
3. ``mock+dispatch+decode``: the same with a real :class:`WheelEncoder` attached.
   Stage 3 minus stage 2 is our cost as seen through gpiozero (should match stage 1).
4. ``mock alone``: the mock pins with no callback at all; stage 2 minus stage 4 is
   gpiozero's dispatch, which also exists on the Pi.
5. ``lgpio loop emulation``: what lgpio's Python notification thread does per report
   before gpiozero sees it (read 16 bytes from a buffered file, ``struct.unpack``,
   scan the callback list, gpiozero's ``LGPIOPin`` wrapper dividing the timestamp),
   calling a no-op. See ``PY_LGPIO/lgpio_extra.py`` in joan2937/lg.

The Pi estimate printed at the end uses explicit assumptions (``--pi-slowdown``, default
5×, the pessimistic end of docs/design.md's 3–5×; ``--gil-share``, default 0.5, the fraction
of the interpreter the callback thread gets while SLAM and the web server run).
"""

from __future__ import annotations

import argparse
import io
import struct
import time
from collections.abc import Callable
from contextlib import ExitStack

from gpiozero.pins.mock import MockFactory

from mazebot.io.encoders import WheelEncoder

A_PIN = 17
B_PIN = 18
N_CALLBACKS = 4  # two encoders, two pins each: lgpio scans all registered callbacks


def _per_edge_s(run: Callable[[int], None], cycles: int) -> float:
    start = time.perf_counter()
    run(cycles)
    return (time.perf_counter() - start) / (4 * cycles)


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
    on_a, on_b = wheel._on_a_changed, wheel._on_b_changed

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

    def __init__(self, chip: int, gpio: int, func: Callable[[int, int, int, int], None]):
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


STAGES = {
    "decode": stage_decode,
    "mock_noop": stage_mock_noop,
    "mock_decode": stage_mock_decode,
    "mock_alone": stage_mock_alone,
    "lgpio_loop": stage_lgpio_loop,
}


def measure(cycles: int, repeats: int) -> dict[str, float]:
    """Best per-edge time of each stage; stages interleaved so they share the noise."""
    best = dict.fromkeys(STAGES, float("inf"))
    with ExitStack() as stack:
        runs = {name: make(stack) for name, make in STAGES.items()}
        for _ in range(repeats):
            for name, run in runs.items():
                best[name] = min(best[name], _per_edge_s(run, cycles))
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=20_000)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--pi-slowdown", type=float, default=5.0)
    parser.add_argument("--gil-share", type=float, default=0.5)
    args = parser.parse_args()

    best = measure(args.cycles, args.repeats)
    decode, mock_noop, mock_decode = best["decode"], best["mock_noop"], best["mock_decode"]
    mock_alone, lgpio_loop = best["mock_alone"], best["lgpio_loop"]

    dispatch = max(mock_noop - mock_alone, 0.0)
    ours_via_gpiozero = max(mock_decode - mock_noop, 0.0)
    per_edge_here = decode + dispatch + lgpio_loop
    per_edge_pi = per_edge_here * args.pi_slowdown
    max_rate_pi = args.gil_share / per_edge_pi

    us = 1e6
    print(f"edges per run: {4 * args.cycles}, best of {args.repeats}")
    print(f"1 decode (lock + table), direct call   {decode * us:7.3f} us/edge")
    print(f"2 mock + gpiozero dispatch, no-op      {mock_noop * us:7.3f} us/edge")
    print(f"3 mock + gpiozero dispatch + decode    {mock_decode * us:7.3f} us/edge")
    print(f"4 mock alone (no callback)             {mock_alone * us:7.3f} us/edge")
    print(f"5 lgpio Python loop emulation, no-op   {lgpio_loop * us:7.3f} us/edge")
    print(f"  our cost seen through gpiozero (3-2) {ours_via_gpiozero * us:7.3f} us/edge")
    print(f"  gpiozero dispatch (2-4)              {dispatch * us:7.3f} us/edge")
    print(f"  on the Pi path, here (1 + 2-4 + 5)   {per_edge_here * us:7.3f} us/edge")
    print(
        f"Pi 4 estimate: x{args.pi_slowdown:g} slower -> {per_edge_pi * us:.1f} us/edge; "
        f"with {args.gil_share:.0%} of the GIL -> {max_rate_pi:,.0f} edges/s (both wheels)"
    )


if __name__ == "__main__":
    main()
