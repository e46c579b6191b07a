"""Where the daemon's CPU goes: thread CPU time per part, per call, measured where it is spent.

The robot's computer is a Raspberry Pi, three to five times slower per core than the
machine it is developed on, so every part has a budget: CPU milliseconds per second of
the robot's life and the 99th percentile of one call. Each part measures its own calls
with :func:`time.thread_time` (CPU time of the calling thread only: time the loop spent
in other tasks, or the process spent waiting for the CPU, never counts), so the figures
hold whether the machine is busy or not, and a part that runs in a worker thread or
process is measured there.

Each :class:`PartMeter` has one writer, the task or thread whose part it is (the
DESIGN's one writer per piece of shared state); the budget only reads them.

Example::

    budget = CpuBudget()
    with budget.part("control tick").measure():
        control.tick(state, now_s)
    budget.table(robot_s=60.0)   # {"control tick": {"cpu_ms_per_s": ..., "p99_ms": ..., "calls": ...}}
"""

from __future__ import annotations

import gc
import time
from collections.abc import Generator, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

import numpy as np

from mazebot.steps import timed_stages

T = TypeVar("T")

#: Calls kept per part for the percentile: minutes of the busiest part (the 50 Hz odometry).
RECENT_CALLS = 20000


class RecentValues:
    """The last ``maxlen`` numbers of a series (a ring in one float64 array), oldest first.

    It replaces ``deque(maxlen=...)`` of floats for the daemon's per-call figures: a deque
    holds a Python float object and a slot per value, about 32 bytes, this holds 8, and its
    whole bound is one array made at the start (pages the kernel maps only once written), so
    a run of any length stays within ``8 · maxlen`` bytes per series.

    One writer; a reader on another thread may see the newest value missing, never a value
    that was not appended.

    Example::

        ms = RecentValues(maxlen=3)
        for v in (1.0, 2.0, 3.0, 4.0):
            ms.append(v)
        list(ms)            # [2.0, 3.0, 4.0]
        np.asarray(ms)      # array([2., 3., 4.])
    """

    def __init__(self, maxlen: int) -> None:
        if maxlen < 1:
            raise ValueError(f"a series keeps at least one value, got maxlen {maxlen}")
        self._values = np.empty(int(maxlen), dtype=np.float64)
        self._count = 0  # values appended over the whole life

    @property
    def maxlen(self) -> int:
        return int(self._values.shape[0])

    def append(self, value: float) -> None:
        count = self._count
        self._values[count % self._values.shape[0]] = value
        self._count = count + 1  # after the write: a reader never sees an unwritten slot

    def clear(self) -> None:
        self._count = 0

    def __len__(self) -> int:
        return min(self._count, self._values.shape[0])

    def values(self) -> np.ndarray:
        """A copy of the values kept, oldest first."""
        count, size = self._count, self._values.shape[0]
        if count <= size:
            return self._values[:count].copy()
        split = count % size
        return np.concatenate((self._values[split:], self._values[:split]))

    def __array__(self, dtype: Any = None, copy: bool | None = None) -> np.ndarray:
        out = self.values()
        return out if dtype is None else out.astype(dtype, copy=False)

    def __getitem__(self, index: int) -> float:
        """The value at ``index``, oldest first (negative from the newest), as a deque's."""
        return float(self.values()[index])

    def __iter__(self) -> Iterator[float]:
        return iter(self.values().tolist())

    def __repr__(self) -> str:
        return f"RecentValues(maxlen={self.maxlen}, len={len(self)})"

#: The parts of the daemon, in the order a reader follows the data (docs/design.md, "Data flow").
PARTS = (
    "lidar decoding",
    "odometry",
    "slam per revolution",
    "loop closure (worker)",
    "planner tick",
    "dwa",
    "control tick",
    "health check",
    "web packet",
    "web send per viewer",
    "recording",
    "foxglove live",
    "saving",
    "zenoh poll",
    "zenoh publish",
    "garbage collection",
)


class PartMeter:
    """CPU time of one part of the daemon: a running total and the recent calls.

    Example::

        meter = PartMeter("odometry")
        with meter.measure():
            odometry.update(left, right)
    """

    def __init__(self, name: str) -> None:
        self.name = name
        self.calls = 0
        self.cpu_s = 0.0
        self.recent_ms = RecentValues(RECENT_CALLS)

    def add(self, cpu_s: float) -> None:
        """One call that took ``cpu_s`` seconds of CPU (measured by the caller, e.g. in a worker)."""
        self.calls += 1
        self.cpu_s += cpu_s
        self.recent_ms.append(cpu_s * 1e3)

    @contextmanager
    def measure(self) -> Iterator[None]:
        """Measure the body as one call, in the calling thread's CPU time."""
        start_s = time.thread_time()
        try:
            yield
        finally:
            self.add(time.thread_time() - start_s)

    def steps(self, steps: Generator[None, None, T]) -> Generator[None, None, T]:
        """Wrap work in stages (:mod:`mazebot.steps`): its stages are one call together.

        Only the stages' own CPU counts, not what the loop did between them.
        """
        spent_s = [0.0]
        try:
            return (yield from timed_stages(steps, spent_s))
        finally:
            self.add(spent_s[0])

    def summary(self, robot_s: float | None) -> dict[str, Any]:
        """CPU ms per robot-second over the whole life, p50/p99 ms of the recent calls."""
        ms = self.recent_ms.values()
        return {
            "calls": self.calls,
            "cpu_ms_per_s": round(1e3 * self.cpu_s / robot_s, 3) if robot_s else None,
            "p50_ms": round(float(np.percentile(ms, 50)), 3) if len(ms) else None,
            "p99_ms": round(float(np.percentile(ms, 99)), 3) if len(ms) else None,
        }


@contextmanager
def garbage_collection_metered(meter: PartMeter) -> Iterator[None]:
    """Charge every cyclic garbage collection of this process to ``meter`` while the body runs.

    Python's collector runs in whichever thread's allocation set it off, inside that thread
    (``gc.callbacks``: called at its start and its stop, in the collecting thread), so the
    thread CPU between the two is the collection's. It belongs to no part: the allocations
    of every part and of the event loop add up to it. Each collection costs the two
    callbacks (a microsecond or two) on top.
    """
    started: list[float] = []

    def on_collection(phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            started.append(time.thread_time())
        elif started:
            meter.add(time.thread_time() - started.pop())

    gc.callbacks.append(on_collection)
    try:
        yield
    finally:
        gc.callbacks.remove(on_collection)


class CpuBudget:
    """The daemon's parts by name; each task takes its own meter with :meth:`part`."""

    def __init__(self) -> None:
        self.meters: dict[str, PartMeter] = {}
        #: the daemon's clock when its tasks started (``run_daemon`` sets it); None before
        self.started_s: float | None = None

    def age_s(self, now_s: float) -> float | None:
        """Seconds of the daemon's life so far on its clock; None before it started."""
        return None if self.started_s is None else max(0.0, now_s - self.started_s)

    def part(self, name: str) -> PartMeter:
        """The meter of ``name`` (one of :data:`PARTS`), created on first use (a dict lookup after that)."""
        meter = self.meters.get(name)
        if meter is None:
            if name not in PARTS:
                raise ValueError(f"unknown part {name!r} of the CPU budget; the parts are {', '.join(PARTS)}")
            meter = self.meters[name] = PartMeter(name)
        return meter

    def adopt(self, meter: PartMeter) -> None:
        """Take a meter a device keeps itself (the lidar driver's decoding) as its part."""
        if meter.name not in PARTS:
            raise ValueError(f"unknown part {meter.name!r} of the CPU budget; the parts are {', '.join(PARTS)}")
        self.meters[meter.name] = meter

    def table(self, robot_s: float | None) -> dict[str, dict[str, Any]]:
        """Every part in :data:`PARTS` order; a part that never ran has ``None`` figures."""
        out: dict[str, dict[str, Any]] = {}
        for name in PARTS:
            meter = self.meters.get(name)
            if meter is None:
                out[name] = {"calls": 0, "cpu_ms_per_s": None, "p50_ms": None, "p99_ms": None}
            else:
                out[name] = meter.summary(robot_s)
        return out
