"""SLAM in the daemon: scans in, map and pose correction out, heavy work in an executor.

Each revolution from ``state.scans`` goes through :meth:`mazebot.slam.slam.Slam.update`
(filter, de-skew, ICP, keyframe, grid: a few milliseconds on the loop). When an update
hands back a loop-closure job (verification, pose-graph optimization, grid rebuild:
tens to hundreds of milliseconds), it runs in ``executor`` (by default a worker process,
:mod:`mazebot.slam.loop_worker`) while scans keep being processed; its result is merged
with :meth:`Slam.apply` as soon as it is done.

Written to the shared state (SLAM is their one writer): ``map`` (the occupancy grid; a
new object with a new generation after a rebuild), ``map_from_odom`` (the odometry task
composes it with the odometry into ``state.pose``), ``pose_covariance``, ``trajectory``
(keyframe poses), ``scan_ms`` (CPU time of each update, for the benchmark) and ``slam``
(counters).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque
from concurrent.futures import Executor

from mazebot.clock import Clock
from mazebot.io.scan import Scan
from mazebot.slam.ekf import OdometryHistory
from mazebot.slam.loop_worker import LoopClosureExecutor
from mazebot.slam.slam import LoopClosureResult, Slam, SlamParams, SlamUpdate
from mazebot.state import SharedState

log = logging.getLogger(__name__)

#: Longest wait for the odometry to reach a scan's last sample (it runs at >= 50 Hz).
ODOMETRY_WAIT_S = 0.1


async def run(
    state: SharedState,
    clock: Clock,
    params: SlamParams,
    executor: LoopClosureExecutor | Executor | None = None,
    slam: Slam | None = None,
) -> None:
    """Consume ``state.scans`` for ever; ``executor`` runs loop-closure jobs (None: the loop's default).

    A :class:`LoopClosureExecutor` may run them in a worker process; any other executor
    runs ``job.run`` in one of its threads.
    """
    slam = slam or Slam(params, background=True, record_trajectory=False)
    loop = asyncio.get_running_loop()
    next_scan: asyncio.Future[Scan] | None = None
    job: asyncio.Future[LoopClosureResult] | None = None
    try:
        while True:
            if next_scan is None:
                next_scan = asyncio.ensure_future(state.scans.get())
            waiting: set[asyncio.Future] = {next_scan} if job is None else {next_scan, job}
            done, _ = await asyncio.wait(waiting, return_when=asyncio.FIRST_COMPLETED)
            if job is not None and job in done:
                result = job.result()  # a crashed job is a SLAM fault, not silence
                job = None
                _publish_closure(state, slam, result)
            if next_scan in done:
                scan = next_scan.result()
                next_scan = None
                history = await _odometry_covering(state, clock, scan.end_time_s)
                if history is None:
                    continue
                start_s = time.thread_time()
                try:
                    update = slam.update(scan, history)
                except Exception as exc:  # one bad scan must not cost the map: skip it, stop the wheels
                    _scan_failed(state, clock, exc)
                    continue
                state.scan_ms.append((time.thread_time() - start_s) * 1e3)
                if any(f.source == "slam" for f in state.faults):
                    state.clear_faults("slam")
                    state.note("slam", "SLAM processes scans again", clock.now_s())
                _publish_update(state, slam, update)
                if update.loop_job is not None and isinstance(executor, LoopClosureExecutor):
                    job = asyncio.wrap_future(executor.submit(update.loop_job))
                elif update.loop_job is not None:
                    job = loop.run_in_executor(executor, update.loop_job.run)
    finally:
        if job is not None:
            job.cancel()  # a job already running in its thread finishes unseen
        if next_scan is not None:
            next_scan.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await next_scan


def _scan_failed(state: SharedState, clock: Clock, exc: Exception) -> None:
    """A scan SLAM could not process: a ``slam`` fault (the wheels stop) until one succeeds."""
    if any(f.source == "slam" for f in state.faults):
        return
    message = f"SLAM could not process a lidar scan ({type(exc).__name__}: {exc}); wheels stopped, map kept"
    log.error("%s", message, exc_info=exc)
    state.raise_fault("slam", message, clock.now_s())


async def _odometry_covering(state: SharedState, clock: Clock, time_s: float) -> OdometryHistory | None:
    """The odometry history once it reaches ``time_s`` (at most ``ODOMETRY_WAIT_S`` later)."""
    deadline_s = clock.now_s() + ODOMETRY_WAIT_S
    while True:
        history = state.odometry_history
        latest = None if history is None else history.latest
        if latest is not None and latest[0] >= time_s:
            return history
        if clock.now_s() >= deadline_s:
            return history if latest is not None else None
        await clock.sleep(0.005)


def _publish_update(state: SharedState, slam: Slam, update: SlamUpdate) -> None:
    state.map = slam.grid
    state.map_from_odom = tuple(float(v) for v in update.map_from_odom)  # type: ignore[assignment]
    state.pose_covariance = update.covariance
    if update.keyframe is not None:
        state.trajectory.append((float(update.pose[0]), float(update.pose[1])))
    stats = state.slam
    stats.scans = slam.scans
    stats.keyframes = len(slam.keyframes)


def _publish_closure(state: SharedState, slam: Slam, result: LoopClosureResult) -> None:
    state.loop_job_ms.append(result.cpu_s * 1e3)
    rebuilt = slam.apply(result)
    stats = state.slam
    stats.loop_closures = len(slam.closures)
    for record in slam.closures[len(stats.closures) :]:
        stats.closures.append((record.old_time_s, record.new_time_s, tuple(float(v) for v in record.measurement)))
    stats.loop_closures_rejected = sum(slam.rejections.values())
    if result.poses is None:
        return
    state.map = slam.grid
    stats.map_rebuilds += rebuilt
    state.map_from_odom = tuple(float(v) for v in slam.map_from_odom)  # type: ignore[assignment]
    trail = slam.keyframe_poses()[-(state.trajectory.maxlen or len(slam.keyframes)) :]
    state.trajectory = deque(((float(x), float(y)) for x, y, _ in trail), maxlen=state.trajectory.maxlen)
    accepted = [f"{v.candidate.new}->{v.candidate.old}" for v in result.verdicts if v.accepted]
    log.info(
        "loop closure %s: the map moved up to %.3f m / %.4f rad%s",
        ", ".join(accepted),
        result.moved_m,
        result.turned_rad,
        ", rebuilt" if rebuilt else "",
    )
