"""Repeat the fault suite's kidnap run: is the robot found again, every time?

Run from /tmp (``-m mazebot`` style imports, the repository on the path)::

    cd /tmp && PYTHONPATH=$REPO nice -n 10 $REPO/.venv/bin/python $REPO/bench/kidnap_repeat.py 1 2 3 4 5 1 1

Each argument is one run: the kidnap spec of ``mazebot bench --suite faults`` (the 6x6
maze of that seed, explore drive, virtual time; the robot picked up and put down 0.2 m
away, turned 20°), and one JSON line per run: the fault row (detected_ms, motors_zero_ms,
recovered, map_intact, relocalized_s, passed) and what the guard logged (searches that found
nothing, partial finds waiting for the next revolution, views refused as ambiguous,
re-localizations), and the run's end: done or not, coverage. Loop-closure results and the
search for the lost robot land at fixed simulated times (:mod:`mazebot.bench.virtual_executor`),
so a run is a function of its seed and kidnap time. ``--recovery-window-s`` lets each run go on
that long after the kidnap (the suite's window ends it a few seconds after): long enough for
the maze to be finished, it shows whether the robot mapped on or stood for good.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from collections import Counter
from dataclasses import replace

from mazebot.bench.cli import suite_specs
from mazebot.bench.runner import RunSpec, run_one
from mazebot.config import load_config

ROW_KEYS = ("detail", "detected_ms", "motors_zero_ms", "recovered", "map_intact", "relocalized_s", "passed")
#: what the guard and the SLAM task log, by the start of the message
MESSAGES = {
    "not found": "the robot is not found",
    "partial": "the robot may be at",
    "ambiguous": "the view fits the map at",
    "relocalized": "re-localized at",
}


class _Tally(logging.Handler):
    """Counts the guard's messages of one run."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.counts: Counter[str] = Counter()

    def emit(self, record: logging.LogRecord) -> None:
        text = record.getMessage()
        for key, start in MESSAGES.items():
            if text.startswith(start):
                self.counts[key] += 1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("seeds", type=int, nargs="+", help="one run per seed (repeat a seed to repeat its run)")
    parser.add_argument("--at-s", type=float, nargs="+", default=None,
                        help="kidnap at these simulated seconds instead of the suite's (each seed at each time)")
    parser.add_argument("--recovery-window-s", type=float, default=None,
                        help="let each run go on this long after the kidnap (default: the suite's)")
    args = parser.parse_args()
    kidnap = next(s for s in suite_specs("faults", 1, "explore", "virtual") if s.faults[0].name == "kidnap")
    if args.recovery_window_s is not None:
        kidnap = replace(kidnap, recovery_window_s=args.recovery_window_s)
    times = args.at_s or [kidnap.faults[0].at_s]
    for seed, at_s in ((seed, at_s) for seed in args.seeds for at_s in times):
        _run(replace(kidnap, seed=seed, faults=(replace(kidnap.faults[0], at_s=at_s),)))


def _run(spec: RunSpec) -> None:
    """One kidnap run: its JSON line."""
    tally = _Tally()
    loggers = [logging.getLogger(name) for name in ("mazebot.slam.relocalize", "mazebot.tasks.slam_task")]
    for logger in loggers:
        logger.setLevel(logging.INFO)
        logger.addHandler(tally)
    t0 = time.perf_counter()
    try:
        metrics, _ = run_one(load_config(None), spec)
    finally:
        for logger in loggers:
            logger.removeHandler(tally)
    wall_s = round(time.perf_counter() - t0, 1)
    for row in metrics.get("faults") or [{}]:
        print(json.dumps({"seed": spec.seed, "at_s": spec.faults[0].at_s, "wall_s": wall_s,
                          **{k: row.get(k) for k in ROW_KEYS}, "log": dict(tally.counts),
                          "done": metrics.get("done"), "coverage": metrics.get("coverage")}), flush=True)


if __name__ == "__main__":
    main()
