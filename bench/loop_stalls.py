"""Where the event loop's long synchronous stretches come from, during one benchmark run.

Run from the repository root::

    .venv/bin/python bench/loop_stalls.py --drive explore --clock real --seed 1

Every event-loop callback (a task's step, a timer, a future's done-callback) is timed
on the wall clock; inside it, the heavy functions of SLAM and the planner listed in
``SECTIONS`` are timed too. Printed: per callback kind, how many ran longer than
``--slow-ms`` (default 5 ms), their p99 and max; then the sections inside those slow
callbacks, by total time: what to cut or move off the loop for the control task (20 Hz,
its lateness is the loop's longest stretch) to keep its deadline. Functions that are
generators (``*_steps``, :mod:`mazebot.steps`) cannot be timed this way, so the list
names what they call. Timing costs a few percent; the run's own metrics (control
lateness, scan ms) are printed as well.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import functools
import importlib
import time
from typing import Any

import numpy as np

from mazebot.bench.loop_callbacks import callback_name
from mazebot.bench.runner import RunSpec, run_one
from mazebot.config import load_config

#: (module, attribute path) of the functions timed inside callbacks.
SECTIONS: tuple[tuple[str, str], ...] = (
    ("mazebot.slam.slam", "Slam.apply"),
    ("mazebot.slam.icp", "_associate"),  # the ICP's nearest-neighbour search, each iteration
    ("mazebot.slam.slam", "Slam._add_keyframe"),
    ("mazebot.slam.keyframes", "voxel_downsample"),  # the submap's voxel filter
    ("mazebot.slam.keyframes", "Keyframe.surface"),
    ("mazebot.slam.slam", "Slam._loop_closure_job"),
    ("mazebot.slam.slam", "prepare_scan"),
    ("mazebot.slam.slam", "map_rays"),
    ("mazebot.slam.keyframes", "Keyframe.from_scan"),
    ("mazebot.slam.grid", "OccupancyGrid.integrate"),
    ("mazebot.slam.relocalize", "LocalizationGuard.check"),
    ("mazebot.planner.pilot", "Pilot.plan"),
    ("mazebot.planner.pilot", "Pilot.drive"),
    ("mazebot.planner.dwa", "LocalCostmap.clearance_m"),
    ("mazebot.web.server", "_status"),
)


class Profile:
    """Callback and section timings of one run."""

    def __init__(self, slow_ms: float) -> None:
        self.slow_ms = slow_ms
        self.callbacks: dict[str, list[float]] = collections.defaultdict(list)
        self.slow: list[tuple[float, str, list[tuple[str, float]]]] = []
        self._sections: list[tuple[str, float]] = []
        self._depth = 0
        self._undo: list[tuple[Any, str, Any]] = []

    def install(self) -> None:
        handle_run = asyncio.Handle._run  # type: ignore[attr-defined]
        profile = self

        def timed_run(handle: asyncio.Handle) -> None:
            profile._sections = []
            start = time.perf_counter()
            handle_run(handle)
            ms = (time.perf_counter() - start) * 1e3
            name = callback_name(handle)
            profile.callbacks[name].append(ms)
            if ms >= profile.slow_ms:
                profile.slow.append((ms, name, profile._sections))

        self._patch(asyncio.Handle, "_run", timed_run)
        for module_name, path in SECTIONS:
            try:
                module = importlib.import_module(module_name)
            except ImportError:
                continue
            owner: Any = module
            *parents, attr = path.split(".")
            for parent in parents:
                owner = getattr(owner, parent, None)
            if owner is None or not hasattr(owner, attr):
                continue
            self._patch(owner, attr, self._timed(path, getattr(owner, attr)))

    def _timed(self, name: str, fn: Any) -> Any:
        profile = self

        @functools.wraps(fn)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                profile._sections.append((name, (time.perf_counter() - start) * 1e3))

        return wrapper

    def _patch(self, owner: Any, attr: str, value: Any) -> None:
        self._undo.append((owner, attr, owner.__dict__[attr] if attr in owner.__dict__ else getattr(owner, attr)))
        setattr(owner, attr, value)

    def uninstall(self) -> None:
        for owner, attr, value in reversed(self._undo):
            setattr(owner, attr, value)
        self._undo.clear()

    def report(self, sim_s: float) -> None:
        print(f"callbacks >= {self.slow_ms:g} ms (wall), by kind:")
        rows = []
        for name, ms in self.callbacks.items():
            a = np.asarray(ms)
            slow = a[a >= self.slow_ms]
            rows.append((float(slow.sum()), name, len(a), len(slow), int((a >= 10.0).sum()),
                         float(np.percentile(a, 99)), float(a.max())))
        rows.sort(reverse=True)
        print(f"  {'slow ms total':>13} {'calls':>7} {'>=slow':>6} {'>=10ms':>6} {'p99 ms':>7} {'max ms':>7}  callback")
        for total, name, n, n_slow, n10, p99, mx in rows[:12]:
            print(f"  {total:13.1f} {n:7d} {n_slow:6d} {n10:6d} {p99:7.2f} {mx:7.2f}  {name}")
        print(f"sections inside the slow callbacks ({len(self.slow)} in {sim_s:.0f} simulated s):")
        totals: collections.Counter[str] = collections.Counter()
        counts: collections.Counter[str] = collections.Counter()
        worst: dict[str, float] = {}
        for _, _, sections in self.slow:
            for name, ms in sections:
                totals[name] += ms
                counts[name] += 1
                worst[name] = max(worst.get(name, 0.0), ms)
        for name, total in totals.most_common():
            print(f"  {total:9.1f} ms in {counts[name]:4d} calls (max {worst[name]:6.2f} ms)  {name}")
        print("the 10 longest callbacks:")
        for ms, name, sections in sorted(self.slow, key=lambda s: -s[0])[:10]:
            inner = ", ".join(f"{n.rsplit('.', 1)[-1]} {t:.1f}" for n, t in sections if t >= 1.0)
            print(f"  {ms:7.2f} ms  {name}: {inner}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--drive", choices=("explore", "scripted"), default="explore")
    parser.add_argument("--clock", choices=("virtual", "real"), default="real")
    parser.add_argument("--slow-ms", type=float, default=5.0)
    args = parser.parse_args()
    profile = Profile(args.slow_ms)
    profile.install()
    try:
        metrics, _ = run_one(load_config(None), RunSpec(None, (6, 6), args.seed, args.drive, clock=args.clock))
    finally:
        profile.uninstall()
    keys = ("done", "time_s", "wall_s", "collisions", "ate_rms_m", "map_f1", "scan_ms_p50", "scan_ms_p99",
            "control_jitter_ms_p99")
    print({k: metrics.get(k) for k in keys})
    profile.report(float(metrics["time_s"]))


if __name__ == "__main__":
    main()
