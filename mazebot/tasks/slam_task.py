"""SLAM in the daemon: scans in, map and pose correction out, heavy work in an executor.

Each revolution from ``state.scans`` goes through :meth:`mazebot.slam.slam.Slam.update_steps`
(filter, de-skew, ICP, keyframe, grid: a few milliseconds on the loop, in stages with the
loop free in between, so the 20 Hz control tick never waits for a whole keyframe scan). When an update
hands back a loop-closure job (verification, pose-graph optimization, grid rebuild:
tens to hundreds of milliseconds), it runs in ``executor`` (by default a worker process,
:mod:`mazebot.slam.loop_worker`) while scans keep being processed; its result is merged
with :meth:`Slam.apply` as soon as it is done. When the exploration ends (``returning``
or ``done``) one more job optimizes the whole graph and rebuilds the map from it
(:meth:`Slam.final_job`): the map the user keeps has the optimized keyframes' accuracy.

Written to the shared state (SLAM is their one writer): ``map`` (the occupancy grid; a
new object with a new generation after a rebuild), ``map_from_odom`` (the odometry task
composes it with the odometry into ``state.pose``; each move of it but a loop closure's is also
logged in ``odometry_fixes``, with the revolution it came from), ``pose_covariance``, ``trajectory``
(keyframe poses), ``scan_ms`` (CPU time of each update, for the benchmark) and ``slam``
(counters).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections import deque
from concurrent.futures import Executor
from dataclasses import replace

import numpy as np

from mazebot.clock import Clock
from mazebot.geometry import compose, inverse
from mazebot.io.scan import Scan
from mazebot.malloc_tuning import give_back_free_memory
from mazebot.slam.ekf import OdometryHistory
from mazebot.slam.relocalize import LocalizationGuard, SearchResult, search_pose
from mazebot.slam.slam import LoopClosureJob, LoopClosureResult, Slam, SlamParams, SlamUpdate
from mazebot.state import OdometryFix, RunState, SharedState
from mazebot.steps import run_steps_async

log = logging.getLogger(__name__)

#: A loop-closure job running longer than this is said in ``/api/status``.
SLOW_JOB_S = 0.45
#: At most one wheel-slip note this often.
SLIP_NOTE_EVERY_S = 5.0
#: Longest wait for the odometry to reach a scan's last sample, counted in revolutions the lidar
#: delivered meanwhile (0.55 s of an A1's), not in the clock's time: a process starved by a slow
#: CPU, whose lidar task and odometry task both ran late, gives the odometry as many turns as a
#: fast one. The odometry is dated by the encoder edges (``odometry_task``): it reaches a time
#: once the edges up to it are counted, which a starved encoder thread does late (270 ms once
#: under a 25 % quota, 981 ms once on a machine at load 10); at rest the odometry holds its pose
#: up to now after ``odometry_task.REST_AFTER_S``. A safety net for a stalled odometry task (the
#: lidar goes on): the revolution is left out, since one de-skewed past the odometry's end is bent.
ODOMETRY_WAIT_REVOLUTIONS = 3
#: Faults that say the wheel odometry cannot be trusted (an encoder dead, the robot lost).
ODOMETRY_FAULTS = frozenset({"encoders", "localization"})
#: Revolutions in a row that fit the odometry (matched, no slip) before SLAM paints again.
TRUSTED_AFTER = 5
#: Matched revolutions (no slip, no odometry fault) after a re-localization or an odometry fault
#: that confirm the robot's pose again: from then on revolutions at rest heal the trust too
#: (:class:`OdometryTrust`). Two: one match could be a look-alike, a second from another place
#: along the way with the odometry between them agreeing is not.
POSE_CONFIRMED_AFTER = 2
#: A revolution during which the wheel odometry moved less than this (metres, radians) was at rest.
AT_REST_M, AT_REST_RAD = 0.002, 0.005
#: Revolutions at rest in a row whose good ICP matches (``Slam.acceptable``, not degenerate) the
#: filter refused, all within ``REST_AGREE_M`` / ``REST_AGREE_RAD`` of the first, before SLAM takes
#: their pose (:class:`RestMatches`). At rest every revolution sees the same walls from the same
#: place: ICP from the same guess lands on the same pose, so agreement is cheap; three rule out a
#: revolution's noise, and cost 0.55 s of a robot that stands anyway.
REST_AGREE = 3
REST_AGREE_M, REST_AGREE_RAD = 0.01, math.radians(0.5)


class OdometryTrust:
    """Whether the wheel odometry is good enough for SLAM to paint revolutions into the map.

    A revolution is de-skewed and predicted with the wheels' motion; while a tyre slips, an
    encoder is dead or the robot was just found again, that motion is wrong, and the walls it
    paints land beside the true ones (the map's precision fell from 0.998 to 0.70 in the fault
    suite). Such revolutions only localize the robot (:meth:`Slam.update` with ``paint=False``)
    until ``TRUSTED_AFTER`` in a row were matched by ICP without a slip and no odometry fault
    is up.

    After a slip, revolutions at rest count too, matched or not: wheels that do not turn
    cannot slip. Without that, a slip could stop the map for good: the robot drives on into
    walls the map does not hold yet, ICP then fits no revolution (the submap lacks what the
    scan sees, residuals of 6-9 cm), none is painted, no keyframe brings the new walls in,
    and the explorer waits at rest for a target the map never resolves. After a fault or a
    re-localization (:meth:`distrust`) the pose itself is in doubt, so rest counts only once
    ``POSE_CONFIRMED_AFTER`` revolutions were matched again: a robot set down where the map
    has little (a kidnap) matched a few revolutions, drove on into walls the map did not hold
    and stopped there, and without rest counting it stood for good, its pose right to 5 mm. And a
    revolution at rest whose good ICP match the filter refused (``disputed``) starts the
    count again, as a slip does in motion: it would be painted at the pose ICP disputes
    (:class:`RestMatches` settles that dispute).

    Rest heals only a robot that stops, and an explorer goes on driving to its goal: after a
    slip in a turn, a robot that drove on one revolution short of ``trusted_after`` left the
    last keyframe's walls behind, ICP fitted none of the next revolutions (residuals of 4-11
    cm against the 3 cm limit), and the filter dead-reckoned the cheap odometry through the
    turns until the guard called the robot lost. ``rest_wanted`` says so: held back, not
    matched in motion, and rest would heal; the pilot then stands still until the trust is back.
    """

    def __init__(self, trusted_after: int = TRUSTED_AFTER) -> None:
        self.trusted_after = trusted_after
        self.clean = trusted_after  # revolutions in a row that fit the odometry
        self.held_back = 0  # revolutions not painted, in all
        self.rest_heals = True  # the last distrust was a slip: revolutions at rest count as clean
        #: held back, the last revolution in motion not matched, and revolutions at rest would heal the
        #: trust: the robot should stand still until they have (it stays so until trusted or distrusted)
        self.rest_wanted = False

    def distrust(self) -> None:
        """The odometry is known bad from now on (a fault, a re-localization)."""
        self.clean = 0
        self.rest_heals = False
        self.rest_wanted = False

    def observe(self, state: SharedState, slipped: bool, matched: bool, at_rest: bool = False,
                disputed: bool = False) -> bool:
        """One revolution's verdict: paint it (True) or localize only."""
        faulted = any(f.source in ODOMETRY_FAULTS for f in state.faults)
        if slipped or faulted:
            self.clean = 0
            self.rest_heals = not faulted
        elif disputed and at_rest:  # no slip at rest: the filter's pose is what is in doubt (RestMatches)
            self.clean = 0
        elif matched or (at_rest and self.rest_heals):  # an unmatched revolution in motion proves nothing
            self.clean = min(self.clean + 1, self.trusted_after)
            if matched and self.clean >= POSE_CONFIRMED_AFTER:
                self.rest_heals = True  # the pose is confirmed: wheels at rest cannot spoil it
        trusted = self.clean >= self.trusted_after
        self.held_back += not trusted
        unmatched_in_motion = not matched and not at_rest
        self.rest_wanted = not trusted and self.rest_heals and (self.rest_wanted or unmatched_in_motion)
        return trusted


class RestMatches:
    """A robot at rest whose filter refuses ICP's matches that agree with each other: the filter is wrong.

    The filter (:class:`mazebot.slam.ekf.PoseEkf`) gates each match by its own covariance, and
    at rest nothing makes that covariance grow (the odometry adds its noise per metre and
    per radian driven). A filter that stopped a few degrees off (a turn's late edges under a
    CPU quota) then refuses every match for as long as the robot stands, while ICP finds
    the same pose revolution after revolution: each revolution looked like a slip (ICP moved
    the prediction by the filter's error), none was painted, and the planner's stand-still
    watch gave the goal up ("SLAM painted 0 of 45"), on a published pose that stayed wrong.
    ``REST_AGREE`` such matches in a row, at rest, agreeing within ``REST_AGREE_M`` /
    ``REST_AGREE_RAD``, are the best-known pose there is: the filter restarts there
    (:meth:`Slam.relocalized`, as when the lost robot is found), keeps its covariance, and
    the next revolutions are matched (and heal the trust) as usual.

    Example (the SLAM task, after each update)::

        pose = rest.observe(at_rest, disputed_pose)   # None, or the pose to take
    """

    def __init__(self, agree: int = REST_AGREE) -> None:
        self.agree = agree
        self.poses: list[np.ndarray] = []  # the disputed matches of the revolutions at rest in a row
        self.taken = 0  # poses taken, in all

    def observe(self, at_rest: bool, disputed_pose: np.ndarray | None) -> np.ndarray | None:
        """One revolution: the pose to take once ``agree`` disputed matches at rest agree, else None."""
        if not at_rest or disputed_pose is None:
            self.poses.clear()
            return None
        if self.poses and not _same_place(self.poses[0], disputed_pose):
            self.poses.clear()
        self.poses.append(np.asarray(disputed_pose, dtype=np.float64).copy())
        if len(self.poses) < self.agree:
            return None
        poses = np.array(self.poses)
        self.poses.clear()
        self.taken += 1
        theta = math.atan2(float(np.sin(poses[:, 2]).mean()), float(np.cos(poses[:, 2]).mean()))
        return np.array([poses[:, 0].mean(), poses[:, 1].mean(), theta])


def _same_place(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(math.hypot(float(a[0] - b[0]), float(a[1] - b[1])) <= REST_AGREE_M
                and abs(math.remainder(float(a[2] - b[2]), math.tau)) <= REST_AGREE_RAD)


async def run(
    state: SharedState,
    clock: Clock,
    params: SlamParams,
    executor: Executor | None = None,
    slam: Slam | None = None,
    guard: LocalizationGuard | None = None,
    pause_behind: int = 0,
) -> None:
    """Consume ``state.scans`` for ever; ``executor`` runs loop-closure jobs (None: the loop's default).

    A :class:`LoopClosureExecutor` may run them in a worker process; any other executor
    runs the job (a callable) in one of its threads.

    ``guard`` (:mod:`mazebot.slam.relocalize`; a default one if None) holds back revolutions
    that do not fit the map; when the robot is lost it raises a ``localization`` fault and
    searches for it in the executor (in this process: it reads the live SLAM), and clears
    the fault once found. ``pause_behind`` (``[slam] loop_closure_pause_behind``): the
    revolutions waiting at which an executor that can pause its worker is paused
    (:meth:`SlamTask.pace_worker`); 0 never.
    """
    task = SlamTask(state, clock, slam or Slam(params, background=True, record_trajectory=False), executor, guard,
                    pause_behind)
    await task.run()


class SlamTask:
    """SLAM's side of the daemon as one object: what is pending, and one method per event.

    Three things can be outstanding at once: the next revolution from ``state.scans``, a
    loop-closure (or final) job in the executor, and a search for the lost robot. :meth:`run`
    waits for whichever comes first and hands it to :meth:`on_scan`, :meth:`on_job_done` or
    :meth:`on_search_done`; :meth:`on_job_slow` says when a job runs long and
    :meth:`on_run_state` starts the final rebuild once the exploration is over.
    """

    def __init__(self, state: SharedState, clock: Clock, slam: Slam, executor: Executor | None = None,
                 guard: LocalizationGuard | None = None, pause_behind: int = 0) -> None:
        self.state, self.clock, self.slam, self.executor = state, clock, slam, executor
        #: revolutions waiting behind the one in hand at which the loop-closure worker is paused
        #: (``[slam] loop_closure_pause_behind``; 0: never)
        self.pause_behind = pause_behind
        self.paused_since_s: float | None = None  # the wall clock (perf_counter) when the worker was paused
        self.guard = guard or LocalizationGuard()
        self.trust = OdometryTrust()
        self.rest = RestMatches()
        self.next_scan: asyncio.Future[Scan] | None = None
        self.job: asyncio.Future[LoopClosureResult] | None = None
        self.job_since_s = 0.0
        self.job_noted = False  # the running job was said to run long
        self.search: asyncio.Future[SearchResult] | None = None
        self.final_done = False  # this exploration's final rebuild has been asked for

    async def run(self) -> None:
        """Wait for the next event and handle it, for ever; what is pending is cancelled on the way out."""
        if self.slam.keyframes:  # a resumed run: its map is served before the first revolution
            self.state.map = self.slam.grid
            self.state.slam.keyframes = len(self.slam.keyframes)
            self.state.slam.anchored = self.slam.anchored
        try:
            while True:
                done = await self._wait()
                if self._job_is_slow(done):
                    self.on_job_slow()
                if self.job is not None and self.job in done:
                    await self.on_job_done(self.job)
                if self.search is not None and self.search in done:
                    self.on_search_done(self.search)
                if self.next_scan is not None and self.next_scan in done:
                    scan = self.next_scan.result()
                    self.next_scan = None
                    self.pace_worker()
                    if not await self.on_scan(scan):
                        continue  # a revolution left out waits for the next one to look at the run state
                self.on_run_state()
        finally:
            self._resume_worker()
            await self._cancel_pending()

    async def _wait(self) -> set[asyncio.Future]:
        """The futures done after waiting for the first (or until a running job is due to be said slow)."""
        if self.next_scan is None:
            self.next_scan = asyncio.ensure_future(self.state.scans.get())
        # a loop closure's result waits while a search for the lost robot reads the map (in a
        # thread): merging it then would rebuild the grid and move the keyframes under the search
        mergeable = self.job if self.search is None else None
        waiting: set[asyncio.Future] = {f for f in (self.next_scan, mergeable, self.search) if f is not None}
        timeout_s = None
        if self.job is not None and not self.job_noted:  # wake up to say so when a job runs long
            timeout_s = max(0.0, self.job_since_s + SLOW_JOB_S - self.clock.now_s())
        done, _ = await asyncio.wait(waiting, timeout=timeout_s, return_when=asyncio.FIRST_COMPLETED)
        return done

    def _job_is_slow(self, done: set[asyncio.Future]) -> bool:
        return (self.job is not None and not self.job_noted and self.job not in done
                and self.clock.now_s() - self.job_since_s >= SLOW_JOB_S)

    def _start_job(self, job: LoopClosureJob) -> None:
        """A loop-closure job into the executor (the job itself, so a LoopClosureExecutor can ship it).

        After the final job (the exploration over) every job is told so: the map it may rebuild is the
        one the robot keeps ([slam.graph] rebuild_after_exploration).
        """
        if self.final_done and isinstance(job, LoopClosureJob) and not job.exploration_over:
            job = replace(job, exploration_over=True)
        self.job = asyncio.get_running_loop().run_in_executor(self.executor, job)
        self.job_since_s, self.job_noted = self.clock.now_s(), False
        self.state.slam.job_started_wall_s = time.perf_counter()

    def pace_worker(self) -> None:
        """Pause the loop-closure worker while SLAM is ``pause_behind`` revolutions behind; resume once caught up.

        SLAM's revolutions come first: a loop closure corrects the map a little later, a
        revolution dropped is lost. Where the worker has a core to itself SLAM does not fall
        behind and nothing happens; where the two share a budget (a CPU quota, one Pi core
        for the whole daemon) the worker's job took what SLAM's thread needed
        (:meth:`LoopClosureExecutor.pause`). Resumed when at most one revolution waits, so
        a job always goes on between the stretches SLAM is behind.
        """
        pause = getattr(self.executor, "pause", None)
        if pause is None or self.pause_behind <= 0:
            return
        waiting = self.state.scans.qsize()
        stats = self.state.slam
        if self.paused_since_s is None:
            if self.job is not None and waiting >= self.pause_behind and pause():
                self.paused_since_s = time.perf_counter()
                stats.worker_pauses += 1
                log.info("SLAM is %d revolutions behind: the loop-closure job waits until it catches up", waiting)
        elif waiting <= 1 or self.job is None:
            self._resume_worker()

    def _resume_worker(self) -> None:
        if self.paused_since_s is None:
            return
        self.state.slam.worker_paused_s += time.perf_counter() - self.paused_since_s
        self.paused_since_s = None
        self.executor.resume()  # type: ignore[union-attr]  # paused: it has one

    # -- the events ---------------------------------------------------------------------

    def on_job_slow(self) -> None:
        """A loop-closure job has run for ``SLOW_JOB_S``: said once, in the log and the status."""
        self.job_noted = True
        message = (f"a loop-closure job has been running for {self.clock.now_s() - self.job_since_s:.1f} s; "
                   "scans go on, its result is merged when it is done")
        log.info("%s", message)
        self.state.note("slam", message, self.clock.now_s())

    async def on_job_done(self, job: asyncio.Future[LoopClosureResult]) -> None:
        """A loop-closure job's result merged into SLAM (in stages, as the updates) and published."""
        result = job.result()  # a crashed job is a SLAM fault, not silence
        self.job = None
        stats = self.state.slam
        stats.job_started_wall_s = None
        wall_s, cpu_s = time.perf_counter(), [0.0]
        rebuilt = await run_steps_async(self.slam.apply_steps(result), cpu_s)
        stats.merge_wall_s += time.perf_counter() - wall_s
        stats.merge_cpu_s += cpu_s[0]
        stats.merges += 1
        _publish_closure(self.state, self.slam, result, rebuilt)
        del result, job
        give_back_free_memory()  # the old grid and submap, the job's result: all freed at this one moment

    def on_search_done(self, search: asyncio.Future[SearchResult]) -> None:
        """The search for the lost robot ended: found (the fault cleared), or searched again later."""
        found = search.result()
        self.search = None
        if self.guard.accept(self.slam, found):
            self.trust.distrust()  # found, but the odometry that lost it may still be wrong
            _publish_relocalized(self.state, self.slam, found, self.clock)
        elif found.pose is not None:  # from a partly known view: the guard waits for it again
            log.info("the robot may be at (%.3f m, %.3f m) by the part of its view the map knows; "
                     "the next revolution must find it there again", found.pose[0], found.pose[1])
        else:
            log.info("the robot is not found near where the odometry has it (%d poses tried); "
                     "searching again with the next revolution", found.tried)

    async def on_scan(self, scan: Scan) -> bool:
        """One revolution: checked by the guard, then localized and (if the odometry is trusted) painted.

        False when the revolution was left out (calibrating, no odometry, searching, lost, not
        fitting the map, failed).
        """
        state = self.state
        if state.calibrating:
            # the setup page's calibration measures what the odometry assumes (wiring, wheel sizes,
            # track width): its motions would paint walls where they are not, and lose the robot.
            # Afterwards the guard finds the robot in the map again, as after a kidnap.
            return False
        wait_start_s = time.perf_counter()
        history = await _odometry_covering(state, self.clock, scan.end_time_s)
        state.slam.odometry_wait_s += time.perf_counter() - wait_start_s
        if history is None or self.search is not None:
            return False  # no odometry yet, or a search for the robot is under way
        span = history.span_s
        if span is not None and span[1] < scan.end_time_s:
            # the encoder edges of the revolution's end are still on their way (a process
            # starved for longer than the wait): a pose held there would bend the revolution
            # and make the guard call the robot lost; this one is left out, the next will do
            state.slam.uncovered += 1
            return False
        wall_start_s = time.perf_counter()
        try:
            return await self._localize(scan, history)
        finally:
            state.slam.update_wall_s += time.perf_counter() - wall_start_s

    async def _localize(self, scan: Scan, history: OdometryHistory) -> bool:
        """:meth:`on_scan` once the odometry covers the revolution: the guard's check, the update, publishing."""
        state, slam, guard = self.state, self.slam, self.guard
        guard_start_s = time.thread_time()
        verdict = guard.check(slam, scan, history)
        guard_cpu_s = time.thread_time() - guard_start_s  # part of this revolution's SLAM cost
        if verdict == "lost":
            self.on_lost(scan, history)
            return False
        if verdict == "skip":  # does not fit the map: SLAM must not paint it in, nor rest wait for it
            self.trust.rest_wanted = state.slam.rest_wanted = False
            return False
        predicted = guard.guess
        slip: list[tuple[float, float] | None] = [None]
        disputed: list[np.ndarray | None] = [None]  # a good match the filter refused
        at_rest = _at_rest(history, scan)

        def paint(match, matched: bool) -> bool:
            good = match is not None and slam.acceptable(match)
            if predicted is not None and good:
                # the lidar's pose, before the filter; wheels at rest cannot slip
                slip[0] = guard.slipped(predicted, match.pose, at_rest=at_rest)
            if good and not matched and not match.degenerate:
                disputed[0] = match.pose.copy()
            return self.trust.observe(state, slip[0] is not None, matched, at_rest, disputed[0] is not None)

        await asyncio.sleep(0)  # the guard's check and the update are two stretches, not one
        held_back = self.trust.held_back
        cpu_s = [0.0]
        try:  # in stages, the loop free in between: a keyframe scan is too long for the control tick
            update = await run_steps_async(slam.update_steps(scan, history, paint=paint), cpu_s)
        except Exception as exc:  # one bad scan must not cost the map: skip it, stop the wheels
            _scan_failed(state, self.clock, exc)
            return False
        state.scan_ms.append(cpu_s[0] * 1e3)
        state.cpu.part("slam per revolution").add(guard_cpu_s + cpu_s[0])  # the guard's check too
        state.slam.update_cpu_s += guard_cpu_s + cpu_s[0]
        if any(f.source == "slam" for f in state.faults):
            state.clear_faults("slam")
            state.note("slam", "SLAM processes scans again", self.clock.now_s())
        _publish_update(state, slam, update, scan.end_time_s, update.matched or self.trust.held_back == held_back)
        state.slam.held_back = self.trust.held_back
        state.slam.rest_wanted = self.trust.rest_wanted
        taken = self.rest.observe(at_rest, disputed[0])
        if taken is not None:
            _take_rest_pose(state, slam, update, taken, self.clock)
        if slip[0] is not None:
            _note_slip(state, slip[0], self.clock)
        if update.loop_job is not None:
            self._start_job(update.loop_job)
        return True

    def on_lost(self, scan: Scan, history: OdometryHistory) -> None:
        """The guard lost the robot: a ``localization`` fault, and a search for it in the executor."""
        self.trust.distrust()
        self.state.slam.rest_wanted = False
        _lost(self.state, self.guard, self.clock)
        guess = self.guard.guess
        assert guess is not None  # check() predicted the pose of the revolution it calls lost
        self.search = asyncio.get_running_loop().run_in_executor(
            self.executor, search_pose, self.slam, scan, history, guess, self.guard.params, self.guard.search_scale
        )

    def on_run_state(self) -> None:
        """The maze is explored: once, the map rebuilt from the optimized keyframes (Slam.final_job)."""
        run_state = self.state.run_state
        if run_state is RunState.EXPLORING:
            self.final_done = False
        elif run_state in (RunState.RETURNING, RunState.DONE) and not self.final_done and self.job is None:
            final = self.slam.final_job()
            if final is not None:
                self.final_done = True
                log.info("exploration over: optimizing the pose graph and rebuilding the map once more")
                self._start_job(final)

    async def _cancel_pending(self) -> None:
        if self.job is not None:
            self.job.cancel()  # a job already running in its thread finishes unseen
        if self.search is not None:
            self.search.cancel()
        if self.next_scan is not None:
            self.next_scan.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self.next_scan


def _at_rest(history: OdometryHistory, scan: Scan) -> bool:
    """Whether the wheel odometry stood still over the revolution (``AT_REST_M``, ``AT_REST_RAD``)."""
    x, y, th = history.at(np.array([scan.start_time_s, scan.end_time_s]))
    x, y, th = np.ravel(x), np.ravel(y), np.ravel(th)
    turned = abs(math.remainder(float(th[1] - th[0]), math.tau))
    return bool(math.hypot(float(x[1] - x[0]), float(y[1] - y[0])) < AT_REST_M and turned < AT_REST_RAD)


def _take_rest_pose(state: SharedState, slam: Slam, update: SlamUpdate, pose: np.ndarray, clock: Clock) -> None:
    """The filter restarts at the pose ICP found at rest (:class:`RestMatches`), and the pose is published."""
    odom = compose(inverse(update.map_from_odom), update.pose)  # the odometry at the revolution's end
    moved_m = math.hypot(float(pose[0] - update.pose[0]), float(pose[1] - update.pose[1]))
    turned_rad = abs(math.remainder(float(pose[2] - update.pose[2]), math.tau))
    slam.relocalized(pose, odom)
    _fix_odometry(state, slam.map_from_odom, None, vouched=True)
    message = (f"at rest, {REST_AGREE} revolutions in a row fit the map {100 * moved_m:.1f} cm / "
               f"{math.degrees(turned_rad):.1f}° from where the filter had the robot, which refused them: "
               "SLAM takes their pose")
    log.info("%s", message)
    state.note("slam", message, clock.now_s())


def _lost(state: SharedState, guard: LocalizationGuard, clock: Clock) -> None:
    """The robot does not know where it is: a ``localization`` fault (the wheels stop) while it searches."""
    if any(f.source == "localization" for f in state.faults):
        return
    fit = guard.last_fit
    share = f"{100 * fit.contradiction:.0f} % of the lidar's hits" if fit is not None else "the lidar's hits"
    message = (f"the robot does not know where it is ({share} fall where the map is free: pushed, lifted "
               "or slipping?); wheels stopped, searching for it in the map")
    log.warning("%s", message)
    state.raise_fault("localization", message, clock.now_s())


def _publish_relocalized(state: SharedState, slam: Slam, found: SearchResult, clock: Clock) -> None:
    _fix_odometry(state, slam.map_from_odom, None, vouched=True)
    moved_m = math.hypot(*(found.pose[:2] - found.guess[:2]))  # type: ignore[index]
    message = f"found the robot in the map again, {100 * moved_m:.0f} cm from where the odometry had it"
    state.clear_faults("localization")
    state.note("localization", message, clock.now_s())


def _note_slip(state: SharedState, slip: tuple[float, float], clock: Clock) -> None:
    """A revolution that ICP had to move far from the odometry's prediction: say so (rate-limited)."""
    now_s = clock.now_s()
    last = next((e for e in reversed(state.events) if e.source == "odometry"), None)
    if last is not None and now_s - last.time_s < SLIP_NOTE_EVERY_S:
        return
    message = (f"lidar and wheel odometry disagree by {100 * slip[0]:.0f} cm / {math.degrees(slip[1]):.0f}° "
               "within a few revolutions: a wheel slips (or the robot was pushed); the lidar corrects the pose")
    log.info("%s", message)
    state.note("odometry", message, now_s)


def _scan_failed(state: SharedState, clock: Clock, exc: Exception) -> None:
    """A scan SLAM could not process: a ``slam`` fault (the wheels stop) until one succeeds."""
    if any(f.source == "slam" for f in state.faults):
        return
    message = f"SLAM could not process a lidar scan ({type(exc).__name__}: {exc}); wheels stopped, map kept"
    log.error("%s", message, exc_info=exc)
    state.raise_fault("slam", message, clock.now_s())


async def _odometry_covering(state: SharedState, clock: Clock, time_s: float) -> OdometryHistory | None:
    """The odometry history once it reaches ``time_s``, or as it is once the lidar delivered
    ``ODOMETRY_WAIT_REVOLUTIONS`` more revolutions (None: no odometry yet)."""
    give_up_at = state.sensors.lidar_revolutions + ODOMETRY_WAIT_REVOLUTIONS
    while True:
        history = state.odometry_history
        span = None if history is None else history.span_s
        if span is not None and span[1] >= time_s:
            return history
        if state.sensors.lidar_revolutions >= give_up_at:
            return history if span is not None else None
        await clock.sleep(0.005)


def _fix_odometry(state: SharedState, map_from_odom: np.ndarray, revolution_end_s: float | None,
                  vouched: bool) -> None:
    """``map_from_odom`` published, and the move in ``state.odometry_fixes`` (:class:`OdometryFix`)."""
    before, after = state.map_from_odom, (float(map_from_odom[0]), float(map_from_odom[1]), float(map_from_odom[2]))
    last = state.odometry_fixes[-1].serial if state.odometry_fixes else 0
    state.odometry_fixes.append(OdometryFix(last + 1, revolution_end_s, before, after, vouched))
    state.map_from_odom = after


def _publish_update(state: SharedState, slam: Slam, update: SlamUpdate, revolution_end_s: float,
                    vouched: bool) -> None:
    """One revolution's update published; ``vouched``: its pose was matched, or it was painted."""
    state.map = slam.grid
    _fix_odometry(state, update.map_from_odom, revolution_end_s, vouched)
    state.pose_covariance = update.covariance
    if update.keyframe is not None:
        state.trajectory.append((float(update.pose[0]), float(update.pose[1])))
    stats = state.slam
    stats.scans = slam.scans
    stats.keyframes = len(slam.keyframes)
    stats.anchored = slam.anchored


def _publish_closure(state: SharedState, slam: Slam, result: LoopClosureResult, rebuilt: bool) -> None:
    """What a merged loop-closure job (``rebuilt``: it replaced the grid) changed, into the shared state."""
    state.loop_job_ms.append(result.cpu_s * 1e3)
    state.cpu.part("loop closure (worker)").add(result.cpu_s)
    stats = state.slam
    stats.loop_closures = len(slam.closures)
    for record in slam.closures[len(stats.closures) :]:
        dx, dy, dth = (float(v) for v in record.measurement)
        stats.closures.append((record.old_time_s, record.new_time_s, (dx, dy, dth)))
    stats.loop_closures_rejected = sum(slam.rejections.values())
    if result.poses is None:
        return
    state.map = slam.grid
    stats.map_rebuilds += rebuilt
    # not an odometry fix: the closure moves the map (and the robot in it) around the robot's
    # surroundings, which keep their place relative to the odometry
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
