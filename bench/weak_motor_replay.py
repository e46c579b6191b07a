"""Replay the weak-motor check on the control-tick traces of ``bench/motor_notes.py --trace``.

The check is passive (it writes a note, never a throttle), so its verdicts on a recorded
run are exactly the daemon's: this tries its parameters on every trace at once, the
injected weak motor's detection time and the notes in runs without it side by side.

Example::

    .venv/bin/python bench/weak_motor_replay.py /tmp/notes --tau 0.12 --window 0.25 --ratio 0.5

prints, per parameter set, the detection delay of each motor-weak trace and the runs
with a (false) note, the lowest healthy gain ratio seen and where.
"""

from __future__ import annotations

import argparse
import itertools
import logging
import sys
from pathlib import Path

import numpy as np

from mazebot.planner.wheel_control import WheelGainEstimator
from mazebot.state import Fault, RunState, SharedState
from mazebot.tasks.health_task import FAULT_SETTLE_S, HealthMonitor

#: what a weak-motor note says
WEAK_NOTE = "motor gives only"


def replay(trace: np.ndarray, cols: list[str], *, tau_s: float, window_s: float, min_speed_mps: float,
           ratio: float, checks: int, every: int, phase: int, latency_s: float = 0.05,
           healthy_until_s: float = np.inf) -> dict:
    """The daemon's estimator and health monitor on one trace: the notes, the lowest healthy ratio."""
    c = {name: k for k, name in enumerate(cols)}
    est = WheelGainEstimator(0.6, 0.08, 0.05, latency_s=latency_s, time_constant_s=tau_s, window_s=window_s,
                             min_speed_mps=min_speed_mps)
    monitor = HealthMonitor(startup_grace_s=1e9, weak_ratio=ratio, weak_checks=checks)
    state = SharedState(run_state=RunState.EXPLORING)
    fault = Fault("replay", "a fault of the recorded run", 0.0)
    fault_seen = -np.inf
    lowest = (np.inf, None)
    last = None
    for k, row in enumerate(trace):
        now = row[c["now_s"]]
        dt = None if last is None else now - last
        last = now
        state.wheel_gains = est.update((row[c["written_l"]], row[c["written_r"]]),
                                       (row[c["measured_l"]], row[c["measured_r"]]), dt)
        state.faults = [fault] if row[c["fault"]] else []
        if row[c["fault"]]:
            fault_seen = now
        if k % every != phase:
            continue
        monitor.check(state, now)
        g = state.wheel_gains
        if now < healthy_until_s and now - fault_seen >= FAULT_SETTLE_S and g[0] is not None and g[1] is not None:
            for side in (0, 1):
                if g[1 - side] > 0 and g[side] / g[1 - side] < lowest[0]:
                    lowest = (g[side] / g[1 - side], (round(now, 2), side))
    notes = [(e.time_s, e.message) for e in state.events if WEAK_NOTE in e.message]
    return {"notes": notes, "lowest": lowest}


def main(argv: list[str]) -> int:
    logging.disable(logging.WARNING)  # the monitor says every note; the summary below counts them
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder")
    parser.add_argument("--tau", type=float, nargs="+", default=[0.12])
    parser.add_argument("--window", type=float, nargs="+", default=[0.25])
    parser.add_argument("--min-speed", type=float, nargs="+", default=[0.02])
    parser.add_argument("--ratio", type=float, nargs="+", default=[0.5])
    parser.add_argument("--checks", type=int, nargs="+", default=[1])
    parser.add_argument("--every", type=int, default=2, help="control ticks per check (2: 10 Hz)")
    parser.add_argument("--latency", type=float, default=0.05, help="the model's delay, s")
    parser.add_argument("--verbose", action="store_true")
    args = parser.parse_args(argv)
    files = sorted(Path(args.folder).glob("*.npz"))
    data = []
    for f in files:
        z = np.load(f)
        data.append((f.stem, z["trace"], [str(x) for x in z["columns"]], z["injections"]))
    for tau, window, min_speed, ratio, checks in itertools.product(args.tau, args.window, args.min_speed,
                                                                     args.ratio, args.checks):
        delays, false_runs, lowest_all = [], [], (np.inf, None)
        for name, trace, cols, inj in data:
            weak = "motor-weak" in name
            begin = float(inj[0][0]) if weak and len(inj) else None
            for phase in range(args.every):
                r = replay(trace, cols, tau_s=tau, window_s=window, min_speed_mps=min_speed, ratio=ratio,
                           checks=checks, every=args.every, phase=phase, latency_s=args.latency,
                           healthy_until_s=begin if begin is not None else np.inf)
                notes = r["notes"]
                if weak:
                    after = [t for t, _ in notes if t >= begin]
                    delays.append(round(1000 * (after[0] - begin)) if after else None)
                    false_runs += [(name, phase, round(t, 2), m[:22]) for t, m in notes if t < begin]
                else:
                    false_runs += [(name, phase, round(t, 2), m[:22]) for t, m in notes]
                if r["lowest"][0] < lowest_all[0]:
                    lowest_all = (round(r["lowest"][0], 3), name, r["lowest"][1])
        print(f"tau {tau} window {window} min {min_speed} ratio {ratio} checks {checks}: weak delays ms {delays}; "
              f"false notes {len(false_runs)}; lowest healthy ratio {lowest_all}")
        if args.verbose:
            for fr in false_runs:
                print("   false:", fr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
