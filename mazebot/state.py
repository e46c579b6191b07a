"""The shared in-memory world of the daemon: run state, faults, pose, sensor health.

One writer per piece (docs/design.md, "The tasks and who writes what"): SLAM writes map and pose, the
planner writes goal and path, control writes motor commands, the supervisor writes
faults, and the web layer only reads and posts commands into ``commands``. Everything
runs on one event loop, so plain attributes are enough; nothing here is touched from
another thread.
"""

from __future__ import annotations

import asyncio
import enum
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from mazebot.clock import Beat
from mazebot.cpu_budget import CpuBudget, RecentValues
from mazebot.taps import notify

if TYPE_CHECKING:
    import numpy as np

    from mazebot.io.scan import Scan
    from mazebot.slam.ekf import OdometryHistory
    from mazebot.slam.grid import OccupancyGrid
    from mazebot.slam.odometry import OdometryPose


class RunState(enum.StrEnum):
    """What the robot is doing, as the user sees it."""

    IDLE = "idle"  # ready, waiting for start
    EXPLORING = "exploring"  # mapping: driving to the next unknown part of the maze
    RETURNING = "returning"  # nothing reachable is unknown: driving back to the start cell
    STOPPED = "stopped"  # the user pressed stop; start resumes
    DONE = "done"  # exploration finished, back at the start
    FAULT = "fault"  # something failed; motors are at zero until the fault clears

    @property
    def moving(self) -> bool:
        """The states in which the wheels may turn."""
        return self in (RunState.EXPLORING, RunState.RETURNING)

    @property
    def jog_allowed(self) -> bool:
        """The states in which the setup page's hold-to-run jog may turn the wheels."""
        return not self.moving and self is not RunState.FAULT


@dataclass(frozen=True)
class MotionRequest:
    """A body velocity the planner wants, for the control task's wheel controller.

    ``mode`` is a :class:`mazebot.planner.wheel_control.DriveMode` value (a change resets
    the wheel integrals); ``time_s`` the clock time it was decided, so the control task
    can refuse a stale one.
    """

    v_mps: float
    w_radps: float
    mode: str
    time_s: float


@dataclass(frozen=True)
class Fault:
    """A problem the user must see: where it happened and a human sentence.

    A fault clears itself when its source sees the cause gone (the lidar sends data
    again, a restarted task keeps running); a ``latched`` one cannot be seen to go away
    while the wheels are stopped (an encoder that counted nothing while its motor drove)
    and is cleared by the user's next start, which checks it again.
    """

    source: str  # task or device name, e.g. "lidar"
    message: str  # one human sentence
    time_s: float  # clock time when it was raised
    latched: bool = False


@dataclass(frozen=True)
class OdometryStep:
    """One encoder reading as the odometry task used it.

    ``pose_time_s`` is the time the pose of these counts was dated with in the odometry
    history (the newest encoder edge's own stamp, or the reading's time at rest), None when
    the reading added nothing to the history: a recording must date the counts the same way
    for a replay to give SLAM the same odometry.
    """

    reading_time_s: float
    pose_time_s: float | None
    left_ticks: int
    right_ticks: int
    invalid_transitions: int


@dataclass(frozen=True)
class OdometryFix:
    """SLAM moved the odometry frame under the map (``SharedState.map_from_odom``): from ``before`` to ``after``.

    ``revolution_end_s`` is the end time (``Scan.end_time_s``) of the revolution whose update
    gave ``after``; None when SLAM found the robot again (the lost robot's search, or the
    pose its revolutions at rest agreed on), which vouches for no revolution of its own.
    ``vouched``: SLAM stands by that revolution's pose (its scan match was taken, or the
    odometry was trusted enough to paint it); False when it was held back unmatched (its pose
    is only the odometry's, which SLAM just distrusted). ``serial`` counts the fixes (from 1), so
    a reader can tell which it has not seen yet. A loop closure is not a fix: it moves the map
    around the robot, not the odometry under it.
    """

    serial: int
    revolution_end_s: float | None
    before: tuple[float, float, float]
    after: tuple[float, float, float]
    vouched: bool


#: Fixes kept in ``SharedState.odometry_fixes``: 256 revolutions, 46 s of an A1, far longer than
#: the planner (their one reader, every tick at 5 Hz, stopped or driving) ever goes without reading them.
ODOMETRY_FIXES_KEPT = 256


@dataclass(frozen=True)
class Event:
    """Something the user may want to know that stopped nothing for long (a loop stall, a reconnect)."""

    source: str
    message: str
    time_s: float


@dataclass
class Pose2D:
    """Robot pose in the map frame: metres and radians (counter-clockwise)."""

    x_m: float = 0.0
    y_m: float = 0.0
    theta_rad: float = 0.0


@dataclass
class SensorStats:
    """Counters a user debugging the wiring wants to see."""

    lidar_revolutions: int = 0
    lidar_bytes_dropped: int = 0
    lidar_reconnects: int = 0
    encoder_ticks_left: int = 0
    encoder_ticks_right: int = 0
    #: the stamp of the newest encoder edge in those counts (either wheel's; the clock's time): the
    #: wheels' own time up to which the counts are complete. None: no edge yet, or no usable stamp
    encoder_edge_time_s: float | None = None
    encoder_invalid_transitions: int = 0


@dataclass
class SlamStats:
    """What SLAM has been doing, for the status page and the benchmark."""

    scans: int = 0  # revolutions processed
    scans_dropped: int = 0  # revolutions dropped because SLAM was behind
    #: the most revolutions that waited for SLAM at once, and how many revolutions were queued
    #: behind ``lidar_task.BEHIND_REVOLUTIONS`` or more (the queue's early signs of a drop)
    queue_peak: int = 0
    queue_behind: int = 0
    #: the latest drops' log lines (what held SLAM up: ``lidar_task.why_behind``), oldest first
    drop_notes: list[str] = field(default_factory=list)
    keyframes: int = 0
    held_back: int = 0  # revolutions that only localized, not painted: the odometry was known bad
    #: SLAM holds revolutions back since a slip and matched none in motion: revolutions at rest
    #: bring its trust in the wheels back, so the pilot stands still until they have
    rest_wanted: bool = False
    #: revolutions left out because the odometry had not reached their end within the wait (its
    #: encoder edges late beyond it): de-skewed and judged with a held pose they looked lost
    uncovered: int = 0
    anchored: bool = False  # keyframe 0 holds its revolutions at rest (the robot waits for it before driving)
    loop_closures: int = 0  # accepted
    loop_closures_rejected: int = 0
    map_rebuilds: int = 0
    #: where the SLAM task's time went, cumulative (seconds of the wall clock, and of its thread's
    #: CPU): the lidar task says from their growth what held SLAM up when it drops a revolution
    update_wall_s: float = 0.0  # revolutions checked and matched (guard, update)
    update_cpu_s: float = 0.0
    odometry_wait_s: float = 0.0  # waiting for the odometry to reach a revolution's end
    merge_wall_s: float = 0.0  # loop-closure results merged (:meth:`Slam.apply_steps`)
    merge_cpu_s: float = 0.0
    merges: int = 0
    #: times SLAM paused the loop-closure worker to catch up, and the wall seconds it stayed paused
    worker_pauses: int = 0
    worker_paused_s: float = 0.0
    #: when the loop-closure job now in the worker was started (``time.perf_counter``), None: none
    job_started_wall_s: float | None = None
    #: accepted loop closures: (old keyframe time_s, new keyframe time_s, measured pose of the new
    #: keyframe in the old one's frame (x_m, y_m, theta_rad)), for checking against ground truth
    closures: list[tuple[float, float, tuple[float, float, float]]] = field(default_factory=list)


@dataclass
class RecordStats:
    """The recorder's and the run saver's counters (``/api/status``): drops are never silent."""

    path: str | None = None  # the MCAP file being written, when recording
    messages: int = 0  # written to the file
    dropped: int = 0  # not recorded because the writer's queue was full
    files: int = 0  # files begun (rotation)
    error: str | None = None  # the writer stopped (disk full ...); the robot carries on
    writer_cpu_s: float = 0.0  # CPU time the recorder's writer thread used so far
    run_dir: str | None = None  # where this run is saved
    saves: int = 0
    save_errors: int = 0


@dataclass
class SharedState:
    """Everything the tasks share. Created once by ``main.py`` and handed to each task."""

    run_state: RunState = RunState.IDLE
    #: set once the daemon is stopping (``Supervisor.request_stop``): from then on the control
    #: loop commands zero, whichever thread it ticks on, until its task is cancelled
    stopping: bool = False
    faults: list[Fault] = field(default_factory=list)  # the active faults, one per source
    #: how many faults were ever raised: the control task stops the wheels for a tick on each new
    #: one, even one that cleared before the tick saw it (``mazebot.tasks.control_task``)
    faults_raised: int = 0
    events: deque[Event] = field(default_factory=lambda: deque(maxlen=20))  # recent faults and notices
    #: the moving state a fault interrupted, or ``stopped`` if the user stopped during the fault
    #: (see ``clear_faults``)
    interrupted: RunState | None = None
    auto_resume: bool = False  # ``daemon.auto_resume``: a cleared fault resumes the run by itself
    #: the throttles the control task last wrote (left, right)
    throttles: tuple[float, float] = (0.0, 0.0)
    #: (time_s, left, right) of each control tick's write, oldest first: the throttles the motors
    #: had from that time to the next entry's (10 s kept). Appended by the control loop (the main
    #: process appends the control process's ticks as it reads them); the health monitor's
    #: weak-motor check pairs each with the wheels' travel in the same interval
    throttle_history: deque[tuple[float, float, float]] = field(default_factory=lambda: deque(maxlen=200))
    pose: Pose2D = field(default_factory=Pose2D)
    pose_time_s: float | None = None  # clock time ``pose`` describes (the odometry reading behind it)
    #: (time_s, left_ticks, right_ticks) of the latest encoder reading, written by the
    #: odometry task in one assignment: the control loop, on a thread of its own, reads it
    #: whole (two separate fields could pair this reading's left with the last one's right)
    wheel_ticks: tuple[float, int, int] | None = None
    sensors: SensorStats = field(default_factory=SensorStats)
    commands: asyncio.Queue[str] = field(default_factory=lambda: asyncio.Queue(maxsize=32))
    started_at_s: float | None = None
    #: the odometry's ``distance_m`` when the exploration started (see ``run_distance_m``)
    started_distance_m: float = 0.0
    latest_scan: Scan | None = None  # written by the lidar task
    odometry: OdometryPose | None = None  # written by the odometry task
    #: (left, right) throttle and the clock time it was set: a direct drive that bypasses
    #: the wheel controller (the benchmark's scripted tour, tests); the control task applies
    #: it only while the run state is moving, only while it is fresh, and only when no
    #: ``motion_command`` is set.
    throttle_command: tuple[float, float, float] | None = None
    #: (left, right) throttle and the clock time it was sent: the setup page's hold-to-run jog
    #: (``mazebot.web.setup``); the control task applies it only while the robot is not running
    #: and not in a fault, and only while it is younger than ``[motors] command_ttl_s``
    jog_command: tuple[float, float, float] | None = None
    #: a calibration from the setup page drives the wheels through ``jog_command`` (written by
    #: ``mazebot.calibration.on_daemon``): the health monitor does not judge the wiring meanwhile
    calibrating: bool = False
    #: the planner's body-velocity command (written by the planner task, read by control)
    motion_command: MotionRequest | None = None
    #: measured wheel surface speeds (left, right), m/s, written by the control task
    wheel_speeds_mps: tuple[float, float] = (0.0, 0.0)
    #: why the safety layer last stopped the wheels (empty: it has not), for the status page
    safety_stop: str = ""
    safety_stops: int = 0
    #: incremented by each start from idle or done: a new exploration (the planner resets)
    run_number: int = 0
    finished_at_s: float | None = None  # clock time the run reached DONE
    #: (time_s, left_m, right_m): each wheel's travel since the encoders were opened, dated by the
    #: newest encoder edge counted (the time up to which the counts are complete), or by the
    #: reading once the wheels rest; written by the odometry task (10 s kept at 50 Hz)
    wheel_travel: deque[tuple[float, float, float]] = field(default_factory=lambda: deque(maxlen=500))
    #: age of the newest encoder edge counted, at each odometry reading with new edges,
    #: milliseconds: how late a pose dated by the reading time would be (the odometry task)
    odometry_edge_age_ms: RecentValues = field(default_factory=lambda: RecentValues(1000))
    #: recent lateness of control ticks beyond their period, milliseconds
    control_lateness_ms: RecentValues = field(default_factory=lambda: RecentValues(1000))
    #: CPU time per part of the daemon (:mod:`mazebot.cpu_budget`); each part's meter is
    #: written only by the task or thread whose part it is
    cpu: CpuBudget = field(default_factory=CpuBudget)
    #: lidar revolutions waiting for SLAM: the lidar task puts, the SLAM task gets; when SLAM is
    #: behind the oldest is dropped (``mazebot.tasks.lidar_task``); replaced at start-up with the
    #: configured ``[slam] scan_queue_size``
    scans: asyncio.Queue[Scan] = field(default_factory=lambda: asyncio.Queue(maxsize=2))
    #: time-stamped odometry poses of the last seconds (de-skew and SLAM's filter); written by
    #: the odometry task, read by SLAM; None until the odometry task starts
    odometry_history: OdometryHistory | None = None
    #: ticked by the odometry task after each reading: tasks that need to run about as often, at no
    #: particular moment, run in its wake-ups instead of waking the loop themselves (:class:`Beat`)
    odometry_beat: Beat = field(default_factory=Beat)
    # --- written by SLAM ---------------------------------------------------------------
    #: the correction from the odometry frame to the map frame, (x_m, y_m, theta_rad) (ROS
    #: ``map -> odom``); the odometry task publishes ``pose`` as this ⊕ odometry
    map_from_odom: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: each change of ``map_from_odom`` by a revolution's update or a re-localization, oldest first
    #: (:class:`OdometryFix`; loop closures are not in it): the planner's blind-zone memory places
    #: each revolution's returns with SLAM's own pose of that revolution
    odometry_fixes: deque[OdometryFix] = field(default_factory=lambda: deque(maxlen=ODOMETRY_FIXES_KEPT))
    slam: SlamStats = field(default_factory=SlamStats)
    #: the live occupancy grid, in the map frame (the start pose); a new object with a new
    #: ``generation`` after a loop closure rebuilt it. Read it; never call ``take_dirty`` on it.
    map: OccupancyGrid | None = None
    pose_covariance: np.ndarray | None = None  # 3x3 covariance of (x_m, y_m, theta_rad)
    #: keyframe positions; replaced by a new deque when a loop closure moved them
    trajectory: deque[tuple[float, float]] = field(default_factory=lambda: deque(maxlen=2000))
    #: CPU time of SLAM's update per scan, ms (filter + ICP + grid; loop closures run in an executor)
    scan_ms: RecentValues = field(default_factory=lambda: RecentValues(20000))
    #: CPU time of each loop-closure job, ms, in the thread or worker process that ran it
    loop_job_ms: RecentValues = field(default_factory=lambda: RecentValues(20000))
    # --- written by the planner --------------------------------------------------------
    path: list[tuple[float, float]] = field(default_factory=list)  # planned waypoints, map frame
    goal: tuple[float, float] | None = None  # the current exploration goal, map frame
    coverage: float | None = None  # fraction of the maze the map knows, when the planner can tell
    planner_status: str = ""  # one human line: what the planner is doing and why
    #: lidar returns the planner remembers from inside the lidar's minimum range (odometry frame,
    #: (N, 2), read-only; :meth:`mazebot.planner.safety.BlindZoneMemory.snapshot`), replaced whole
    #: once a revolution; the control loop's collision guard reads them beside the latest scan
    blind_zone_points: np.ndarray | None = None
    #: CPU time of each planner tick, ms (graph update, goal choice, DWA)
    planner_ms: RecentValues = field(default_factory=lambda: RecentValues(20000))
    #: what the planner decided and when, ``(time_s, text)``: new targets, blacklists, recoveries
    planner_events: deque[tuple[float, str]] = field(default_factory=lambda: deque(maxlen=5000))
    # --- written by the recorder and the run saver (mazebot.tasks.record_task, persist_task) ---
    record: RecordStats = field(default_factory=RecordStats)
    #: the control process's shared memory (:class:`mazebot.tasks.control_process.ControlLink`) while
    #: the control loop runs in a process of its own: the fields it reads are mirrored into it as
    #: they are assigned (:meth:`__setattr__`), so every writer reaches the child at once
    control_link: Any = None
    #: a tap (:mod:`mazebot.taps`): each listener is given every :class:`Event` :meth:`note` keeps
    #: (the benchmark's fault metrics, a logger); one that raises is logged, the note and the
    #: fault that made it still happen
    note_listeners: tuple[Callable[[Event], None], ...] = ()
    #: a tap: each listener is given every encoder reading the odometry task integrated, with the
    #: time it dated the pose by (:class:`OdometryStep`; the recorder writes them)
    odometry_listeners: tuple[Callable[[OdometryStep], None], ...] = ()

    def __setattr__(self, name: str, value: Any) -> None:
        object.__setattr__(self, name, value)
        link = self.__dict__.get("control_link")
        if link is not None and name in link.MIRRORED:
            link.mirror(self, name)

    def raise_fault(self, source: str, message: str, time_s: float, *, latched: bool = False) -> None:
        """Record a fault (one per source: the newest) and move to FAULT.

        The control task stops the wheels in FAULT; the supervisor also stops them at
        once when a task crashes. A run under way is remembered, so it can resume when
        the fault clears.
        """
        self.faults = [f for f in self.faults if f.source != source]
        self.faults.append(Fault(source, message, time_s, latched))
        self.faults_raised += 1
        del self.faults[:-50]  # bounded, whatever happens
        self.note(source, message, time_s)
        if self.run_state.moving:
            self.interrupted = self.run_state
        self.run_state = RunState.FAULT

    def clear_faults(self, source: str | None = None, *, latched_only: bool = False) -> None:
        """Forget the faults of one source (or all, or all latched ones).

        When none remain, FAULT gives way to ``stopped`` if a run was interrupted (start
        resumes it) or, with ``auto_resume``, straight back to the interrupted state;
        otherwise to ``idle``.
        """
        self.faults = [
            f
            for f in self.faults
            if not ((source is None or f.source == source) and (f.latched or not latched_only))
        ]
        if self.faults or self.run_state is not RunState.FAULT:
            return
        if self.interrupted is None:
            self.run_state = RunState.IDLE
        elif self.auto_resume:
            self.run_state = self.interrupted
        else:
            self.run_state = RunState.STOPPED
        self.interrupted = None

    def note(self, source: str, message: str, time_s: float) -> None:
        """Keep a human sentence about something that happened, for the status page."""
        event = Event(source, message, time_s)
        self.events.append(event)
        if self.note_listeners:
            notify(self.note_listeners, event, "state.note")

    def elapsed_s(self, now_s: float) -> float | None:
        """Time since the exploration started, frozen when it finished; None before any start."""
        if self.started_at_s is None:
            return None
        end_s = self.finished_at_s if self.finished_at_s is not None else now_s
        return max(0.0, end_s - self.started_at_s)

    def run_distance_m(self) -> float | None:
        """Path length the wheels drove since the exploration started (odometry), None before any start."""
        if self.started_at_s is None or self.odometry is None:
            return None
        return max(0.0, self.odometry.distance_m - self.started_distance_m)

    def begin_run(self, now_s: float) -> None:
        """A new exploration starts now: its clock and its distance count from here."""
        self.started_at_s = now_s
        self.started_distance_m = 0.0 if self.odometry is None else self.odometry.distance_m
        self.finished_at_s = None

    @property
    def active_fault(self) -> Fault | None:
        return self.faults[-1] if self.faults else None
