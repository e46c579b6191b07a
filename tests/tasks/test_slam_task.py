"""The SLAM task and its feeders: scans and odometry in, map, pose and timings out."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import threading
import time
from collections import Counter
from collections.abc import AsyncIterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
import pytest

from mazebot.clock import RealClock
from mazebot.config import Config
from mazebot.geometry import compose
from mazebot.io.encoders import EncoderReading
from mazebot.io.scan import Scan
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.raycast import cast_rays
from mazebot.sim.world import world_from_layout
from mazebot.slam.ekf import OdometryHistory
from mazebot.slam.grid import OccupancyGrid
from mazebot.slam.preprocess import PrepareParams
from mazebot.slam.slam import LoopClosureResult, SlamParams, SlamUpdate
from mazebot.state import RunState, SharedState
from mazebot.tasks import lidar_task, odometry_task, slam_task


def _static_scan(end_s: float, pose: np.ndarray) -> Scan:
    world = world_from_layout(generate_maze(3, 3, seed=1, kind="perfect"), 0.012)
    origin = np.array(world.start_pose[:2]) + pose[:2]
    angles = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    ranges = cast_rays(origin, angles + world.start_pose[2] + pose[2], world.segments, world.circles, 12.0)
    valid = np.isfinite(ranges)
    times = np.linspace(end_s - 0.18, end_s, 360)
    return Scan(angles, np.where(valid, ranges, 0.0), np.full(360, 47, np.uint8), times, valid)


async def _until(condition, timeout_s: float = 5.0) -> None:
    for _ in range(int(timeout_s / 0.005)):
        if condition():
            return
        await asyncio.sleep(0.005)
    raise AssertionError("condition not met in time")


async def test_slam_task_publishes_the_map_the_pose_correction_and_its_timing() -> None:
    config = Config()
    state = SharedState()
    history = OdometryHistory()
    odom = np.array([0.02, -0.01, 0.1])  # the encoders' frame is not the map's
    history.append(0.0, *odom)
    history.append(100.0, *odom)  # covers every scan below: the task need not wait
    state.odometry_history = history
    for k in range(2):
        state.scans.put_nowait(_static_scan(1.0 + 0.2 * k, np.zeros(3)))
    params = SlamParams.from_config(config.slam, config.lidar)
    with ThreadPoolExecutor(max_workers=1) as executor:
        task = asyncio.create_task(slam_task.run(state, RealClock(), params, executor))
        await _until(lambda: state.slam.scans == 2)
        await state.scans.put(_static_scan(1.4, np.zeros(3)))
        await _until(lambda: state.slam.scans == 3)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
    # the 3x3 maze's walls seen from the start cell: about 100 cells one cell thin
    assert isinstance(state.map, OccupancyGrid) and state.map.occupied_mask().sum() > 60
    assert len(state.scan_ms) == 3 and all(ms > 0 for ms in state.scan_ms)
    assert state.pose_covariance is not None and state.pose_covariance.shape == (3, 3)
    assert list(state.trajectory) == [(pytest.approx(odom[0]), pytest.approx(odom[1]))]  # one keyframe: it stood still
    assert state.slam.keyframes == 1
    # the map frame starts where the odometry was at the first scan: the correction undoes nothing else
    np.testing.assert_allclose(compose(state.map_from_odom, odom), odom, atol=2e-3)


@dataclass
class FakeSlam:
    """Stands in for ``Slam``: every second update hands out a job; records where things ran."""

    grid: OccupancyGrid = field(default_factory=OccupancyGrid)
    scans: int = 0
    keyframes: list = field(default_factory=list)
    closures: list = field(default_factory=list)
    rejections: Counter = field(default_factory=Counter)
    map_from_odom: np.ndarray = field(default_factory=lambda: np.array([0.5, 0.0, 0.0]))
    job_threads: list[str] = field(default_factory=list)
    applied_on: list[str] = field(default_factory=list)
    # what the localization guard reads (an empty grid: every revolution is "ok")
    time_offset: SimpleNamespace = field(default_factory=lambda: SimpleNamespace(offset_s=0.0))
    params: SimpleNamespace = field(default_factory=lambda: SimpleNamespace(prepare=PrepareParams()))
    target: None = None  # no local submap: the guard judges by the grid alone
    anchored: bool = True
    final_jobs: int = 0

    def final_job(self):  # the end-of-exploration job: the same result as the others
        self.final_jobs += 1
        return self.run

    def update_steps(self, scan: Scan, odometry: OdometryHistory, **kwargs: object):  # the task calls: one stage
        self.scans += 1
        yield
        self.keyframes.append(self.scans)
        job = None
        if self.scans == 2:
            job = self.run  # below: a job is a callable returning a LoopClosureResult
        return SlamUpdate(
            time_s=scan.end_time_s, pose=np.zeros(3), covariance=np.eye(3) * 1e-4, map_from_odom=np.zeros(3),
            match=None, matched=False, keyframe=self.scans - 1, points=0, loop_job=job,  # type: ignore[arg-type]
        )

    def run(self) -> LoopClosureResult:  # the job
        self.job_threads.append(threading.current_thread().name)
        return LoopClosureResult(verdicts=[], poses=np.array([[0.1, 0.2, 0.0], [0.3, 0.4, 0.0]]))

    def apply_steps(self, result: LoopClosureResult):  # what the SLAM task calls: one stage
        yield
        self.applied_on.append(threading.current_thread().name)
        self.grid = OccupancyGrid()
        self.grid.generation = 7
        return True

    def keyframe_poses(self) -> np.ndarray:
        return np.array([[0.1, 0.2, 0.0], [0.3, 0.4, 0.0]])


def _standing_still() -> OdometryHistory:
    """Odometry of a robot that has not moved, covering every scan of these tests (0-100 s)."""
    history = OdometryHistory()
    history.append(0.0, 0.0, 0.0, 0.0)
    history.append(100.0, 0.0, 0.0, 0.0)
    return history


@contextlib.asynccontextmanager
async def _slam_task_on(fake: FakeSlam, workers: int = 1, guard: object = None) -> AsyncIterator[SharedState]:
    """The SLAM task running on ``fake`` (its jobs in a pool of ``workers`` threads) until the block
    ends, then cancelled; the shared state it reads, of a robot standing still."""
    state = SharedState()
    state.odometry_history = _standing_still()
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="test-slam") as executor:
        task = asyncio.create_task(slam_task.run(state, RealClock(), SlamParams(), executor, slam=fake,  # type: ignore[arg-type]
                                                 guard=guard))  # type: ignore[arg-type]
        try:
            yield state
        finally:
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task


async def test_loop_closure_job_runs_in_the_executor_and_its_result_is_published() -> None:
    fake = FakeSlam()
    async with _slam_task_on(fake) as state:
        for k in range(2):
            await state.scans.put(_static_scan(1.0 + 0.2 * k, np.zeros(3)))
        await _until(lambda: fake.applied_on)
    assert fake.job_threads[0].startswith("test-slam")  # off the event loop ...
    assert fake.applied_on == [threading.current_thread().name]  # ... merged back on it
    assert state.map is fake.grid and state.map.generation == 7 and state.slam.map_rebuilds == 1
    assert list(state.trajectory) == [(0.1, 0.2), (0.3, 0.4)]  # a new trail: the keyframes moved
    assert state.map_from_odom == (0.5, 0.0, 0.0)


class FakeLidar:
    def __init__(self, scans: list[Scan]) -> None:
        self._scans = scans
        self.stats = type("Stats", (), {"bytes_dropped": 0, "reconnects": 0})()

    async def scans(self):
        for scan in self._scans:
            yield scan


async def test_when_the_exploration_ends_the_map_is_rebuilt_once_from_the_optimized_keyframes() -> None:
    fake = FakeSlam()
    async with _slam_task_on(fake) as state:
        state.run_state = RunState.EXPLORING
        await state.scans.put(_static_scan(1.0, np.zeros(3)))
        await _until(lambda: fake.scans == 1)
        assert fake.final_jobs == 0  # still exploring
        state.run_state = RunState.RETURNING
        for k in range(3):
            await state.scans.put(_static_scan(1.2 + 0.2 * k, np.zeros(3)))
        await _until(lambda: fake.scans == 4 and len(fake.applied_on) == 2)  # scan 2's job, then the final one
        state.run_state = RunState.DONE
        await state.scans.put(_static_scan(2.0, np.zeros(3)))
        await _until(lambda: fake.scans == 5)
    assert fake.final_jobs == 1  # once, not once per scan nor again at done
    assert state.slam.map_rebuilds == 2 and state.map is fake.grid


async def test_lidar_task_drops_the_oldest_scan_when_slam_is_behind(caplog) -> None:
    caplog.set_level(logging.WARNING, logger="mazebot.tasks.lidar_task")
    state = SharedState()
    state.scans = asyncio.Queue(maxsize=2)
    state.slam.job_started_wall_s = time.perf_counter()
    scans = [_static_scan(1.0 + 0.2 * k, np.zeros(3)) for k in range(5)]
    await lidar_task.run(FakeLidar(scans), state)
    assert state.sensors.lidar_revolutions == 5 and state.slam.scans_dropped == 3
    # each drop says which revolution went and what SLAM did while it waited
    said = [r.getMessage() for r in caplog.records if "dropped" in r.getMessage()]
    assert len(said) == 3 and all("0 revolutions matched" in m and "a loop-closure job running for" in m for m in said)
    assert all(r.levelno == logging.WARNING for r in caplog.records if "dropped" in r.getMessage())
    assert all("planner ticks" in m and "the process's other threads" in m for m in said)
    assert state.slam.drop_notes == said  # kept for the benchmark's report too
    assert state.slam.queue_peak == 2 and state.slam.queue_behind == 0  # the queue's bound; never 4 behind
    assert [m.split("ending at ")[1].split(" s")[0] for m in said] == ["1.00", "1.20", "1.40"]
    assert [state.scans.get_nowait().end_time_s for _ in range(2)] == [s.end_time_s for s in scans[3:]]
    assert state.latest_scan is scans[-1]


class CountingEncoders:
    """Both wheels forward at one tick per read."""

    def __init__(self) -> None:
        self.ticks = 0

    def read(self) -> EncoderReading:
        self.ticks += 10
        return EncoderReading(self.ticks, self.ticks, 0)


async def test_odometry_task_keeps_a_history_and_publishes_the_map_pose() -> None:
    config = Config()
    config.encoders.odometry_rate_hz = 200.0
    state = SharedState()
    state.map_from_odom = (1.0, 2.0, math.pi / 2)  # what SLAM found
    task = asyncio.create_task(
        odometry_task.run(CountingEncoders(), state, RealClock(), config.encoders, config.drive, history_s=1.0)
    )
    await _until(lambda: state.odometry_history is not None and len(state.odometry_history) >= 5)
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    history = state.odometry_history
    assert history is not None
    t, odo = history.latest
    assert odo[0] > 0 and odo[1] == pytest.approx(0.0) and odo[2] == pytest.approx(0.0)  # straight ahead
    pose = compose(state.map_from_odom, odo)
    assert (state.pose.x_m, state.pose.y_m, state.pose.theta_rad) == pytest.approx(tuple(pose))
    assert state.pose.x_m == pytest.approx(1.0) and state.pose.y_m > 2.0  # map frame: x forward became +y
    assert state.pose_time_s == t


class LosingGuard:
    """Stands in for ``LocalizationGuard``: the third revolution finds the robot lost."""

    def __init__(self) -> None:
        self.checked = 0
        self.guess = np.zeros(3)
        self.params = None
        self.search_scale = 1.0
        self.last_fit = None
        self.accepted: list[str] = []

    def check(self, slam, scan, history) -> str:
        self.checked += 1
        return "lost" if self.checked == 3 else "ok"

    def accept(self, slam, found) -> bool:
        self.accepted.append(f"accepted after {len(slam.applied_on)} merges")
        return False

    def slipped(self, predicted, corrected):
        return None


async def test_a_loop_closure_is_not_merged_while_the_search_for_the_lost_robot_reads_the_map(monkeypatch) -> None:
    """The search reads the live grid and keyframes in a thread; a loop closure finishing meanwhile
    must wait until the search is over, or the grid would be rebuilt under it."""
    job_may_end, search_may_end, searching = threading.Event(), threading.Event(), threading.Event()
    fake = FakeSlam()
    real_job = fake.run

    def slow_job() -> LoopClosureResult:
        job_may_end.wait(10)
        return real_job()

    fake.run = slow_job  # type: ignore[method-assign]

    def search(slam, scan, history, guess, params, scale):
        searching.set()
        search_may_end.wait(10)
        return SimpleNamespace(pose=None, tried=0)

    monkeypatch.setattr(slam_task, "search_pose", search)
    guard = LosingGuard()
    async with _slam_task_on(fake, workers=2, guard=guard) as state:
        for k in range(3):  # the second hands out the job, the third is lost: the search starts
            await state.scans.put(_static_scan(1.0 + 0.2 * k, np.zeros(3)))
        await _until(searching.is_set)
        job_may_end.set()  # the loop closure is done while the search still runs
        await asyncio.sleep(0.2)
        assert fake.applied_on == []  # held back
        search_may_end.set()
        await _until(lambda: fake.applied_on)
    assert guard.accepted == ["accepted after 0 merges"]  # the search's answer first, then the merge
    assert fake.applied_on == [threading.current_thread().name] and state.slam.map_rebuilds == 1


async def test_the_default_queue_holds_a_burst_of_revolutions_that_the_odometry_history_still_covers() -> None:
    """SLAM busy for a few revolutions (a keyframe, a loop closure merged, a throttled CPU) loses none of them.

    A dropped revolution leaves a longer gap for the odometry to bridge before the next match;
    a queued one is matched later, from the odometry history, which must still reach back to it.
    """
    config = Config()
    state = SharedState()
    state.scans = asyncio.Queue(maxsize=config.slam.scan_queue_size)
    revolution_s = 1.0 / 5.5  # an A1's standard scan
    burst = 6  # ~1.1 s of SLAM falling behind
    scans = [_static_scan(1.0 + revolution_s * k, np.zeros(3)) for k in range(burst)]
    await lidar_task.run(FakeLidar(scans), state)
    assert state.slam.scans_dropped == 0
    assert state.scans.qsize() == burst
    oldest_age_s = config.slam.scan_queue_size * revolution_s
    assert oldest_age_s < config.slam.odometry_history_s


async def test_a_revolution_the_odometry_never_reaches_is_left_out_once_the_lidar_delivered_more() -> None:
    """The encoder edges of a revolution's end never came (a starved encoder thread): left out, counted.

    Judged and de-skewed with the pose held at the odometry's end, a turning robot's revolution
    looks rotated and the guard calls the robot lost; the next revolution, which the odometry
    reaches, is processed. The wait counts the revolutions the lidar delivered, not the clock: in
    a starved process they come late, and so do the odometry's turns.
    """
    state = SharedState()
    history = OdometryHistory()
    history.append(0.0, 0.0, 0.0, 0.0)
    history.append(1.1, 0.0, 0.0, 0.0)  # the odometry stops at 1.1 s
    state.odometry_history = history
    fake = FakeSlam()
    with ThreadPoolExecutor(max_workers=1) as executor:
        task = asyncio.create_task(slam_task.run(state, RealClock(), SlamParams(), executor, slam=fake))  # type: ignore[arg-type]
        await state.scans.put(_static_scan(1.0, np.zeros(3)))  # reached
        await state.scans.put(_static_scan(1.2, np.zeros(3)))  # not reached, ever
        for _ in range(slam_task.ODOMETRY_WAIT_REVOLUTIONS):  # the lidar goes on: then the wait is over
            await asyncio.sleep(0.25)  # a starved process: the revolutions come late, the odometry's turns too
            assert state.slam.uncovered == 0
            state.sensors.lidar_revolutions += 1
        await _until(lambda: state.slam.uncovered == 1, timeout_s=5.0)
        history.append(1.5, 0.0, 0.0, 0.0)  # the late edges arrive
        await state.scans.put(_static_scan(1.4, np.zeros(3)))
        await _until(lambda: fake.scans == 2)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
    assert state.slam.uncovered == 1 and fake.scans == 2


class PausableExecutor(ThreadPoolExecutor):
    """A thread executor that records the SLAM task's pauses and resumes of its worker."""

    def __init__(self) -> None:
        super().__init__(max_workers=1)
        self.calls: list[str] = []

    def pause(self) -> bool:
        self.calls.append("pause")
        return True

    def resume(self) -> None:
        self.calls.append("resume")


async def test_the_loop_closure_worker_waits_while_slam_is_behind_and_goes_on_once_it_caught_up() -> None:
    state = SharedState()
    state.scans = asyncio.Queue(maxsize=8)
    executor = PausableExecutor()
    task = slam_task.SlamTask(state, RealClock(), SimpleNamespace(), executor, pause_behind=3)
    try:
        def waiting(n: int) -> None:
            while state.scans.qsize() > n:
                state.scans.get_nowait()
            while state.scans.qsize() < n:
                state.scans.put_nowait(_static_scan(1.0, np.zeros(3)))

        waiting(5)
        task.pace_worker()
        assert executor.calls == []  # no job running: nothing to pause
        task.job = asyncio.get_running_loop().create_future()
        waiting(2)
        task.pace_worker()
        assert executor.calls == []  # two behind: SLAM still keeps up
        waiting(3)
        task.pace_worker()
        waiting(4)
        task.pace_worker()
        waiting(2)
        task.pace_worker()
        assert executor.calls == ["pause"]  # once, and held while more than one revolution waits
        waiting(1)
        task.pace_worker()
        assert executor.calls == ["pause", "resume"]
        assert state.slam.worker_pauses == 1 and state.slam.worker_paused_s > 0
        waiting(3)
        task.pace_worker()
        task.job = None  # the job ended (paused jobs cannot: a job cancelled on the way out)
        task.pace_worker()
        assert executor.calls == ["pause", "resume", "pause", "resume"]
        task.pause_behind = 0  # [slam] loop_closure_pause_behind = 0: never
        task.job = asyncio.get_running_loop().create_future()
        waiting(7)
        task.pace_worker()
        assert executor.calls == ["pause", "resume", "pause", "resume"]
    finally:
        executor.shutdown()
