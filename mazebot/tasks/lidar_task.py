"""Reads lidar revolutions and hands them to the rest of the daemon."""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from typing import NamedTuple

from mazebot.cpu_budget import CpuBudget
from mazebot.state import SharedState, SlamStats

log = logging.getLogger(__name__)

#: At most one "garbled bytes" event this often.
GARBLED_NOTE_EVERY_S = 5.0
#: SLAM counts as behind when this many revolutions wait for it (``state.slam.queue_behind``): a
#: drop's early sign, seen in runs that drop nothing (the queue holds ``[slam] scan_queue_size``).
BEHIND_REVOLUTIONS = 4
#: The latest drop lines kept in ``state.slam.drop_notes`` (for the benchmark's report).
DROP_NOTES_KEPT = 50


class SlamTimes(NamedTuple):
    """The SLAM task's cumulative times (:class:`SlamStats`), this thread's and this process's CPU,
    the planner's and the garbage collector's, when a revolution was queued."""

    wall_s: float
    thread_cpu_s: float
    process_cpu_s: float  # every thread of the daemon's process (the GPIO edge thread, executor threads)
    planner_cpu_s: float  # the planner task's ticks (on the loop's thread)
    gc_cpu_s: float  # the cyclic garbage collector, in whichever thread it ran
    update_wall_s: float
    update_cpu_s: float
    odometry_wait_s: float
    merge_wall_s: float
    merge_cpu_s: float
    merges: int
    scans: int

    @classmethod
    def now(cls, slam: SlamStats, cpu: CpuBudget) -> SlamTimes:
        return cls(time.perf_counter(), time.thread_time(), time.process_time(), _meter_s(cpu, "planner tick"),
                   _meter_s(cpu, "garbage collection"), slam.update_wall_s, slam.update_cpu_s,
                   slam.odometry_wait_s, slam.merge_wall_s, slam.merge_cpu_s, slam.merges, slam.scans)


def _meter_s(cpu: CpuBudget, name: str) -> float:
    meter = cpu.meters.get(name)
    return 0.0 if meter is None else meter.cpu_s


def why_behind(then: SlamTimes, now: SlamTimes, job_started_wall_s: float | None) -> str:
    """What held SLAM up while a dropped revolution waited in the queue: one line for the log.

    The event loop's thread is SLAM's: its CPU against the wall time says whether the
    process was starved (a CPU quota, the loop-closure worker) or busy; SLAM's own
    counters say on what (matching revolutions, waiting for the odometry, merging closures);
    the planner's ticks and the garbage collector are the loop thread's other big users, and
    the process's other threads (CPU beyond the loop's thread) the ones that hold the
    interpreter lock while the loop waits for it.
    """
    wall_s = now.wall_s - then.wall_s
    loop_cpu_s = now.thread_cpu_s - then.thread_cpu_s
    others_cpu_s = (now.process_cpu_s - then.process_cpu_s) - loop_cpu_s
    job = ("no loop-closure job running" if job_started_wall_s is None
           else f"a loop-closure job running for {now.wall_s - job_started_wall_s:.2f} s")
    return (f"in the {wall_s:.2f} s it waited: {now.scans - then.scans} revolutions matched in "
            f"{now.update_wall_s - then.update_wall_s:.2f} s ({now.update_cpu_s - then.update_cpu_s:.2f} s CPU), "
            f"{now.odometry_wait_s - then.odometry_wait_s:.2f} s waiting for the odometry, "
            f"{now.merges - then.merges} closure results merged in {now.merge_wall_s - then.merge_wall_s:.2f} s "
            f"({now.merge_cpu_s - then.merge_cpu_s:.2f} s CPU); the loop's thread ran "
            f"{loop_cpu_s:.2f} s CPU (planner ticks {now.planner_cpu_s - then.planner_cpu_s:.2f} s, "
            f"garbage collection {now.gc_cpu_s - then.gc_cpu_s:.2f} s), the process's other threads "
            f"{others_cpu_s:.2f} s; {job}")


async def run(lidar, state: SharedState) -> None:
    """Publish every revolution as ``state.latest_scan``, queue it for SLAM, keep the counters fresh.

    SLAM's queue (``state.scans``) is bounded: when SLAM is behind, the oldest waiting
    revolution is dropped (and counted), never the lidar reader blocked. The driver itself
    resyncs, restarts and reconnects; this loop only ends on cancellation.
    """
    last_garbled_s: float | None = None
    meter = getattr(lidar, "decode_meter", None)  # fakes in tests may have none
    if meter is not None:
        state.cpu.adopt(meter)
    queued: deque[SlamTimes] = deque()  # SLAM's times when each waiting revolution was queued
    async for scan in lidar.scans():
        state.latest_scan = scan
        queue = state.scans
        slam = state.slam
        now = SlamTimes.now(slam, state.cpu)
        while len(queued) > queue.qsize():  # the oldest were taken by SLAM
            queued.popleft()
        while queue.full():
            try:
                dropped_scan = queue.get_nowait()
            except asyncio.QueueEmpty:  # pragma: no cover - single loop, cannot race
                break
            slam.scans_dropped += 1
            then = queued.popleft() if queued else now
            # a warning: the map misses a revolution, and the line must say why wherever warnings go
            # (the journal's "-p warning", a benchmark's output)
            line = (f"SLAM is {queue.maxsize} revolutions behind: the revolution ending at "
                    f"{dropped_scan.end_time_s:.2f} s dropped; {why_behind(then, now, slam.job_started_wall_s)}")
            log.warning("%s", line)
            slam.drop_notes.append(line)
            del slam.drop_notes[:-DROP_NOTES_KEPT]
        queue.put_nowait(scan)
        queued.append(now)
        waiting = queue.qsize()
        slam.queue_peak = max(slam.queue_peak, waiting)
        slam.queue_behind += waiting >= BEHIND_REVOLUTIONS
        stats = state.sensors
        stats.lidar_revolutions += 1
        driver_stats = lidar.stats
        dropped = driver_stats.bytes_dropped - stats.lidar_bytes_dropped
        reconnected = driver_stats.reconnects - stats.lidar_reconnects
        stats.lidar_bytes_dropped = driver_stats.bytes_dropped
        stats.lidar_reconnects = driver_stats.reconnects
        end_s = scan.end_time_s
        if reconnected > 0:
            state.note("lidar", f"the lidar is scanning again after a reconnect ({driver_stats.last_error})", end_s)
        if dropped > 0 and (last_garbled_s is None or end_s - last_garbled_s >= GARBLED_NOTE_EVERY_S):
            last_garbled_s = end_s
            state.note("lidar", f"{dropped} bytes from the lidar made no sense and were skipped (noise on its "
                       "serial line?); the decoder resynchronised and scanning goes on", end_s)
