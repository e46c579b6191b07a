"""CPU cost of recording: the same virtual-time simulated run with and without ``--record``.

    .venv/bin/python bench/record_overhead.py [--runs 3] [--maze mazebot/sim/mazes/minimaze.txt]

Runs alternate (without, with, without, ...) so both see the same machine load; prints
the median process CPU seconds (all threads, the writer thread included) of each and the
overhead in percent. The recording's modules (the mcap library, zstd, lz4: ~0.75 s of
CPU to import) are imported before the first timed run: a start-up cost, paid once per
daemon, not a cost of recording.
"""

from __future__ import annotations

import argparse
import importlib
import statistics
import tempfile
import time
from pathlib import Path

from mazebot.bench.runner import RunSpec, run_one
from mazebot.config import Config


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--maze", default="mazebot/sim/mazes/minimaze.txt")
    args = parser.parse_args()
    for module in ("mazebot.run_session", "mazebot.record.writer", "mazebot.tasks.record_task"):
        importlib.import_module(module)  # before timing: see the docstring
    cpu: dict[str, list[float]] = {"plain": [], "record": []}
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.runs):
            for mode in ("plain", "record"):
                path = str(Path(tmp) / f"run{i}.mcap") if mode == "record" else None
                spec = RunSpec(maze_path=args.maze, size=None, seed=1, record_path=path)
                start = time.process_time()
                metrics, record = run_one(Config(), spec)
                cpu[mode].append(time.process_time() - start)
                stats = record.state.record
                writer_s = getattr(stats, "writer_cpu_s", None)  # None: code from before it was counted
                writer = "" if writer_s is None else f" (writer thread {writer_s:.2f} s)"
                extra = f"{writer}, dropped {stats.dropped}" if path else ""
                print(f"{mode}: {cpu[mode][-1]:.2f} s CPU, {metrics['time_s']} s simulated{extra}", flush=True)
    plain, rec = statistics.median(cpu["plain"]), statistics.median(cpu["record"])
    print(f"median CPU without {plain:.2f} s, with --record {rec:.2f} s: overhead {100 * (rec / plain - 1):.1f} %")


if __name__ == "__main__":
    main()
