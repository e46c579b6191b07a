"""Loop-closure jobs in a worker process compute what they would in a thread.

The worker keeps a replica of the keyframes and each job ships only the new ones
(:mod:`mazebot.slam.loop_worker`), so the test drives SLAM over a real simulated tour
(scans and odometry captured from a virtual-time run of the daemon) and compares every
job's result from the worker with the same job run in this thread, bit for bit: a
keyframe sent twice, missed or out of order would move a pose or a grid cell.
"""

from __future__ import annotations

import math
import os
import signal
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import numpy as np
import pytest

from mazebot.bench.runner import RunSpec, run_one
from mazebot.config import Config
from mazebot.slam.ekf import OdometryHistory
from mazebot.slam.loop_worker import LoopClosureExecutor
from mazebot.slam.slam import LoopClosureResult, Slam, SlamParams, SlamUpdated

pytestmark = pytest.mark.slow  # a simulated run's keyframes and a worker process
SHM = Path("/dev/shm")  # where POSIX shared memory segments are named on Linux


class _FrozenOdometry:
    """The odometry history as SLAM saw it at one scan."""

    def __init__(self, live: np.ndarray) -> None:
        self.live = live

    def at(self, times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = self.live[:, 0]
        return tuple(np.interp(np.asarray(times_s, dtype=np.float64), t, self.live[:, c]) for c in (1, 2, 3))  # type: ignore[return-value]


@pytest.fixture(scope="module")
def frames() -> list[tuple[object, np.ndarray]]:
    """What SLAM was given during 80 simulated seconds of a scripted 4x4 tour (thread executor).

    The tour starts once SLAM has its anchor (about 4 s at rest), so this is its first 76 s.
    """
    captured: list[tuple[object, np.ndarray]] = []

    def capture(seen: SlamUpdated) -> None:  # the odometry as it stood when the update ended
        assert isinstance(seen.odometry, OdometryHistory)
        captured.append((seen.scan, seen.odometry.since(-math.inf)))  # every entry it holds, a copy

    def watch(slam: Slam) -> None:
        slam.taps.on_update += (capture,)

    config = Config()
    config = config.model_copy(update={"slam": config.slam.model_copy(update={"loop_closure_executor": "thread"})})
    run_one(config, RunSpec(None, (4, 4), 5, "scripted", max_sim_s=80.0), watch_slam=watch)
    return captured


def _same(a: LoopClosureResult, b: LoopClosureResult) -> None:
    assert [(v.candidate.old, v.candidate.new, v.accepted, v.reason) for v in a.verdicts] == [
        (v.candidate.old, v.candidate.new, v.accepted, v.reason) for v in b.verdicts
    ]
    assert (a.poses is None) == (b.poses is None)
    if a.poses is not None:
        np.testing.assert_array_equal(a.poses, b.poses)
    assert (a.grid is None) == (b.grid is None)
    if a.grid is not None:
        np.testing.assert_array_equal(a.grid.log_odds, b.grid.log_odds)


def _replay(frames: list, executor: LoopClosureExecutor, between_jobs=None, max_jobs: int = 1000) -> tuple[int, int]:
    """SLAM over the frames; every job runs here and in ``executor``, results compared. (jobs, accepted)."""
    config = Config()
    slam = Slam(SlamParams.from_config(config.slam, config.lidar), background=True, record_trajectory=False)
    jobs = accepted = 0
    for scan, live in frames:
        if jobs >= max_jobs:
            break
        update = slam.update(scan, _FrozenOdometry(live))  # type: ignore[arg-type]
        if update.loop_job is None:
            continue
        here = update.loop_job.run()
        if between_jobs is not None and jobs:
            between_jobs(jobs)
        there = executor.submit(update.loop_job).result(timeout=120)
        _same(here, there)
        assert there.cpu_s > 0  # measured where it ran
        slam.apply(here)
        jobs += 1
        accepted += sum(v.accepted for v in here.verdicts)
    return jobs, accepted


def test_worker_process_computes_what_this_thread_computes(frames: list) -> None:
    executor = LoopClosureExecutor("process")
    try:
        jobs, accepted = _replay(frames, executor)
    finally:
        executor.shutdown()
        executor.shutdown()  # idempotent
    assert jobs >= 3 and accepted >= 1  # several jobs, so keyframes were shipped in several parts


def test_the_worker_process_runs_at_the_nice_value_asked_and_the_daemon_keeps_its_own() -> None:
    executor = LoopClosureExecutor("process", nice=19)
    try:
        worker_nice = executor._pool.submit(os.getpriority, os.PRIO_PROCESS, 0).result(timeout=60)  # type: ignore[union-attr]
    finally:
        executor.shutdown()
    assert worker_nice == 19  # its jobs take what the daemon leaves of a shared CPU
    assert os.getpriority(os.PRIO_PROCESS, 0) < 19


def _process_state(pid: int) -> str:
    """The one-letter state of ``/proc/PID/stat`` (R running, S sleeping, T stopped)."""
    return Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[0]


def test_a_paused_worker_is_stopped_until_resumed_and_then_finishes_its_work() -> None:
    import time

    executor = LoopClosureExecutor("process", nice=19)
    try:
        pool = executor._pool
        pid = pool.submit(os.getpid).result(timeout=60)  # type: ignore[union-attr]
        assert executor.pause() and executor.paused
        assert not executor.pause()  # already paused: nothing more to stop
        work = pool.submit(time.sleep, 0.05)  # type: ignore[union-attr]
        time.sleep(0.5)
        assert _process_state(pid) == "T" and not work.done()  # ten times its time, and not done
        executor.resume()
        assert not executor.paused
        work.result(timeout=30)  # it went on where it stood
        assert pool.submit(os.getpid).result(timeout=30) == pid  # type: ignore[union-attr]  # the same worker
        assert _process_state(pid) in "RS"
        executor.pause()
    finally:
        executor.shutdown()  # resumes a paused worker first, or it could never exit
    assert not executor.paused


def test_a_thread_executor_has_nothing_to_pause() -> None:
    executor = LoopClosureExecutor("thread")
    try:
        assert not executor.pause() and not executor.paused
        executor.resume()
    finally:
        executor.shutdown()


def test_thread_executor_runs_the_job_as_is(frames: list) -> None:
    executor = LoopClosureExecutor("thread")
    try:
        jobs, _ = _replay(frames, executor, max_jobs=2)
    finally:
        executor.shutdown()
    assert jobs >= 1


def test_a_worker_that_missed_keyframes_or_died_gets_them_all_again(frames: list, caplog) -> None:
    executor = LoopClosureExecutor("process")

    def trouble(job_number: int) -> None:
        if job_number == 1:  # as if a job had been cancelled before it reached the worker
            executor._shipper.shipped += 3
        if job_number == 2:  # the worker is killed between two jobs
            for pid in list(executor._pool._processes):  # type: ignore[union-attr]
                os.kill(pid, signal.SIGKILL)
            with pytest.raises(BrokenProcessPool):
                executor._pool.submit(int).result(timeout=30)  # type: ignore[union-attr]

    arena = executor._shipper.arena
    assert arena is not None  # the keyframes go through shared memory
    try:
        jobs, _ = _replay(frames, executor, between_jobs=trouble, max_jobs=4)
        assert arena.segment_names and all((SHM / name).exists() for name in arena.segment_names)  # the worker's
        #                                                        death left the daemon's segments as they were
    finally:
        executor.shutdown()
    assert jobs >= 3
    assert "sending every keyframe again" in caplog.text and "worker died" in caplog.text
    assert not any((SHM / name).exists() for name in arena.segment_names)  # unlinked at shutdown


def test_unknown_executor_kind_is_refused() -> None:
    with pytest.raises(ValueError, match="process, thread"):
        LoopClosureExecutor("gpu")
