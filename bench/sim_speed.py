"""How fast the simulator runs the daemon on virtual time, and what SLAM takes of it.

Run from the repository root::

    .venv/bin/python bench/sim_speed.py --seeds 5

For each seed, one scripted tour of a generated 6×6 maze (as ``mazebot bench --suite
standard``) with SLAM, then (unless ``--no-baseline``) the same tour with SLAM replaced
by a task that only drains the scan queue, so that the simulator, the drivers and the
other tasks are measured alone. Printed per run: simulated and wall seconds, the
realtime factor, and SLAM's thread CPU split into per-scan updates (on the event loop)
and loop-closure jobs (in the executor). Both are in the wall time of a virtual-time
run: the clock does not wait for them, the CPU does.
"""

from __future__ import annotations

import argparse
import statistics
import time
from typing import Any

from mazebot.bench.runner import RunSpec, run_one
from mazebot.config import load_config
from mazebot.slam import slam as slam_module
from mazebot.tasks import slam_task


class _JobTimer:
    """Wraps ``LoopClosureJob.run`` to add up the thread CPU the executor spends on it."""

    def __init__(self) -> None:
        self.cpu_s: list[float] = []
        self._run = slam_module.LoopClosureJob.run
        timer = self

        def run(job: Any, *args: Any, **kwargs: Any) -> Any:
            start_s = time.thread_time()
            try:
                return timer._run(job, *args, **kwargs)
            finally:
                timer.cpu_s.append(time.thread_time() - start_s)

        slam_module.LoopClosureJob.run = run  # type: ignore[method-assign]

    def close(self) -> None:
        slam_module.LoopClosureJob.run = self._run  # type: ignore[method-assign]


async def _drain_scans(state: Any, clock: Any, params: Any, executor: Any = None, slam: Any = None) -> None:
    """Stands in for ``slam_task.run``: takes every scan and does nothing with it."""
    while True:
        await state.scans.get()


def _one(seed: int, with_slam: bool) -> dict[str, float]:
    config = load_config(None)
    jobs = _JobTimer()
    real_slam = slam_task.run
    if not with_slam:
        slam_task.run = _drain_scans  # type: ignore[assignment]
    try:
        metrics, record = run_one(config, RunSpec(None, (6, 6), seed, "scripted"))
    finally:
        slam_task.run = real_slam  # type: ignore[assignment]
        jobs.close()
    return {
        "time_s": metrics["time_s"],
        "wall_s": metrics["wall_s"],
        "realtime_factor": metrics["realtime_factor"],
        "slam_update_cpu_s": sum(record.state.scan_ms) / 1e3,
        "loop_job_cpu_s": sum(jobs.cpu_s),
        "loop_jobs": len(jobs.cpu_s),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5, help="seeds 1..N (default 5)")
    parser.add_argument("--no-baseline", action="store_true", help="skip the runs without SLAM")
    args = parser.parse_args()
    modes = [True] if args.no_baseline else [True, False]
    factors: dict[bool, list[float]] = {True: [], False: []}
    for seed in range(1, args.seeds + 1):
        for with_slam in modes:
            r = _one(seed, with_slam)
            factors[with_slam].append(r["realtime_factor"])
            label = "SLAM   " if with_slam else "no SLAM"
            print(
                f"seed {seed} {label}: {r['time_s']:.1f} s simulated in {r['wall_s']:.2f} s "
                f"({r['realtime_factor']}x); SLAM updates {r['slam_update_cpu_s']:.2f} s CPU, "
                f"loop-closure jobs {r['loop_jobs']} x, {r['loop_job_cpu_s']:.2f} s CPU",
                flush=True,
            )
    for with_slam in modes:
        label = "with SLAM" if with_slam else "without SLAM"
        print(f"median realtime factor {label}: {statistics.median(factors[with_slam])}")


if __name__ == "__main__":
    main()
