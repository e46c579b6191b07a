"""How fast the simulator runs the daemon on virtual time, and what SLAM takes of it.

Run from the repository root::

    .venv/bin/python bench/sim_speed.py --seeds 5

For each seed, one scripted tour of a generated 6×6 maze (``--size N`` for N×N; as ``mazebot bench --suite
standard``) with SLAM, then (unless ``--no-baseline``) the same tour with SLAM replaced
by a task that only drains the scan queue, so that the simulator, the drivers and the
other tasks are measured alone. Printed per run: simulated and wall seconds, the
realtime factor, the daemon process's CPU time (and simulated seconds per CPU second,
steadier than wall time on a shared machine), and SLAM's thread CPU split into per-scan
updates (on the event loop) and loop-closure jobs (in the executor: a worker process by
default, whose CPU is not in the process figure; ``--executor thread`` puts it back),
and the wall time the loop stood waiting for a loop-closure result the worker had not
finished by its hand-over time (:mod:`mazebot.bench.virtual_executor`). All are in the
wall time of a virtual-time run: the clock does not wait for them, the CPU does.

``--wakeups`` adds one more run without SLAM (seed 1) that counts the event loop's
passes and what each callback was (which task it stepped, or which plain callback),
per simulated second: what wakes the loop how often. Counting costs time, so that run's
speed is not reported.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import statistics
import time
from typing import Any

from mazebot.bench.loop_callbacks import callback_name
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
    """Stands in for ``slam_task.run``: takes every scan and does nothing with it.

    It says the map is anchored at once, or the scripted drive would wait for SLAM's anchor
    for ever (the tour then idles to the time limit).
    """
    state.slam.anchored = True
    while True:
        await state.scans.get()


def _one(seed: int, with_slam: bool, executor: str | None, paced: bool = False, size: int = 6) -> dict[str, float]:
    config = load_config(None)
    if paced:  # [sim] lidar_paced_by_robot (an older tree ignores the key)
        config = config.model_copy(update={"sim": config.sim.model_copy(update={"lidar_paced_by_robot": True})})
    if executor is not None:
        config = config.model_copy(update={"slam": config.slam.model_copy(update={"loop_closure_executor": executor})})
    jobs = _JobTimer()  # loop-closure jobs in this process (older code has no state.loop_job_ms)
    real_slam = slam_task.run
    if not with_slam:
        slam_task.run = _drain_scans  # type: ignore[assignment]
    try:
        metrics, record = run_one(config, RunSpec(None, (size, size), seed, "scripted"))
    finally:
        slam_task.run = real_slam  # type: ignore[assignment]
        jobs.close()
    job_ms = getattr(record.state, "loop_job_ms", None)
    job_cpu_s = [ms / 1e3 for ms in job_ms] if job_ms is not None else jobs.cpu_s
    cpu_s = metrics["cpu_percent"] * metrics["wall_s"] / 100.0
    return {
        "time_s": metrics["time_s"],
        "wall_s": metrics["wall_s"],
        "realtime_factor": metrics["realtime_factor"],
        "process_cpu_s": cpu_s,
        "sim_s_per_cpu_s": metrics["time_s"] / cpu_s,
        "slam_update_cpu_s": sum(record.state.scan_ms) / 1e3,
        "loop_job_cpu_s": sum(job_cpu_s),
        "loop_jobs": len(job_cpu_s),
        "job_ms": sorted(job_ms) if job_ms is not None else [],
        "worker_wait_s": record.executor.worker_wait_s if getattr(record, "executor", None) is not None else 0.0,
    }


def _wakeups(seed: int, paced: bool) -> None:
    """Event-loop passes and callbacks per simulated second of a run without SLAM."""
    counts: collections.Counter[str] = collections.Counter()
    passes = [0]
    run_once = asyncio.BaseEventLoop._run_once  # type: ignore[attr-defined]
    handle_run = asyncio.Handle._run  # type: ignore[attr-defined]

    def counting_run_once(loop: Any) -> None:
        passes[0] += 1
        run_once(loop)

    def counting_run(handle: asyncio.Handle) -> None:
        counts[callback_name(handle)] += 1
        handle_run(handle)

    asyncio.BaseEventLoop._run_once = counting_run_once  # type: ignore[attr-defined]
    asyncio.Handle._run = counting_run  # type: ignore[attr-defined]
    try:
        r = _one(seed, False, None, paced)
    finally:
        asyncio.BaseEventLoop._run_once = run_once  # type: ignore[attr-defined]
        asyncio.Handle._run = handle_run  # type: ignore[attr-defined]
    sim_s = r["time_s"]
    print(f"seed {seed} no SLAM: {passes[0] / sim_s:.0f} event-loop passes and "
          f"{sum(counts.values()) / sim_s:.0f} callbacks per simulated second; callbacks:")
    for name, n in counts.most_common(12):
        print(f"  {n / sim_s:7.1f}/s  {name}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5, help="seeds 1..N (default 5)")
    parser.add_argument("--no-baseline", action="store_true", help="skip the runs without SLAM")
    parser.add_argument(
        "--executor", choices=("process", "thread"), help="where loop-closure jobs run (default: config.toml's)"
    )
    parser.add_argument("--size", type=int, default=6, help="generated N×N mazes (default 6)")
    parser.add_argument("--paced", action="store_true", help="[sim] lidar_paced_by_robot = true for these runs")
    parser.add_argument("--wakeups", action="store_true", help="also count what wakes the event loop (one more run)")
    args = parser.parse_args()
    modes = [True] if args.no_baseline else [True, False]
    factors: dict[bool, list[float]] = {True: [], False: []}
    per_cpu: dict[bool, list[float]] = {True: [], False: []}
    for seed in range(1, args.seeds + 1):
        for with_slam in modes:
            r = _one(seed, with_slam, args.executor, args.paced, args.size)
            factors[with_slam].append(r["realtime_factor"])
            per_cpu[with_slam].append(r["sim_s_per_cpu_s"])
            label = "SLAM   " if with_slam else "no SLAM"
            print(
                f"seed {seed} {label}: {r['time_s']:.1f} s simulated in {r['wall_s']:.2f} s "
                f"({r['realtime_factor']}x), process CPU {r['process_cpu_s']:.2f} s "
                f"({r['sim_s_per_cpu_s']:.1f} simulated s per CPU s); SLAM updates {r['slam_update_cpu_s']:.2f} s CPU, "
                f"loop-closure jobs {r['loop_jobs']} x, {r['loop_job_cpu_s']:.2f} s CPU, "
                f"waited for {r['worker_wait_s']:.2f} s",
                flush=True,
            )
            if r["job_ms"]:
                ms = r["job_ms"]
                print(f"  loop-closure job ms: median {statistics.median(ms):.1f}, "
                      f"p90 {ms[int(0.9 * (len(ms) - 1))]:.1f}, max {ms[-1]:.1f}", flush=True)
    for with_slam in modes if args.seeds > 0 else []:
        label = "with SLAM" if with_slam else "without SLAM"
        print(
            f"median realtime factor {label}: {statistics.median(factors[with_slam])}, "
            f"simulated s per process CPU s: {statistics.median(per_cpu[with_slam]):.2f}"
        )
    if args.wakeups:
        _wakeups(1, args.paced)


if __name__ == "__main__":
    main()
