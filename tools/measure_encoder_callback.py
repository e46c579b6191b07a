"""Measure what one encoder edge costs on the GPIO callback thread.

Run from the repository root:

    .venv/bin/python tools/measure_encoder_callback.py

Optional: ``--cycles N`` (full quadrature cycles per run, default 20 000 = 80 000
edges), ``--repeats R`` (runs per stage, best kept, default 15).

Stages, each timed per edge in thread CPU time (best of the repeats; the stages
run interleaved so that they see the same machine load; they live in
:mod:`mazebot.sim.edge_cost`, which ``mazebot bench --cpu-quota`` also uses, there on thread
CPU time and the median of its repeats, to take the simulator's share out of the daemon's CPU):

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
6. ``sim path``: the quota benchmark's GPIO edge thread's loop body (a message of the
   world unpacked, its edges driven onto the simulator's pins, a real decoder attached).

The Pi estimate printed at the end uses explicit assumptions (``--pi-slowdown``, default
5×, the pessimistic end of docs/design.md's 3–5×; ``--gil-share``, default 0.5, the fraction
of the interpreter the callback thread gets while SLAM and the web server run).
"""

from __future__ import annotations

import argparse
import time

from mazebot.sim.edge_cost import measure_stages, pi_path_s_per_edge


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=20_000)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--pi-slowdown", type=float, default=5.0)
    parser.add_argument("--gil-share", type=float, default=0.5)
    args = parser.parse_args()

    # thread CPU time: a shared machine's other processes do not count (wall time did, several-fold at load 12)
    best = measure_stages(args.cycles, args.repeats, clock=time.thread_time, best=True)
    decode, mock_noop, mock_decode = best["decode"], best["mock_noop"], best["mock_decode"]
    mock_alone, lgpio_loop = best["mock_alone"], best["lgpio_loop"]

    dispatch = max(mock_noop - mock_alone, 0.0)
    ours_via_gpiozero = max(mock_decode - mock_noop, 0.0)
    per_edge_here = pi_path_s_per_edge(best)
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
    print(f"  on the Pi path, here (3-4 + 5)       {per_edge_here * us:7.3f} us/edge")
    print(f"6 the bench's GPIO stand-in, in a loop {best['sim_path'] * us:7.3f} us/edge")
    print(
        f"Pi 4 estimate: x{args.pi_slowdown:g} slower -> {per_edge_pi * us:.1f} us/edge; "
        f"with {args.gil_share:.0%} of the GIL -> {max_rate_pi:,.0f} edges/s (both wheels)"
    )


if __name__ == "__main__":
    main()
