"""The shared in-memory world of the daemon: run state, faults, pose, sensor health.

One writer per piece (see DESIGN.md, "Data flow"): SLAM writes map and pose, the
planner writes goal and path, control writes motor commands, the supervisor writes
faults, and the web layer only reads and posts commands into ``commands``. Everything
runs on one event loop, so plain attributes are enough; nothing here is touched from
another thread.
"""

from __future__ import annotations

import asyncio
import enum
from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

    from mazebot.io.scan import Scan
    from mazebot.slam.ekf import OdometryHistory
    from mazebot.slam.grid import OccupancyGrid
    from mazebot.slam.odometry import OdometryPose


class RunState(enum.StrEnum):
    """What the robot is doing, as the user sees it."""

    IDLE = "idle"  # ready, waiting for start
    RUNNING = "running"  # exploring
    STOPPED = "stopped"  # the user pressed stop
    DONE = "done"  # exploration finished, back at the start
    FAULT = "fault"  # something failed; motors are at zero until the fault clears


@dataclass(frozen=True)
class Fault:
    """A problem the user must see: where it happened and a human sentence."""

    source: str  # task or device name, e.g. "lidar"
    message: str  # one human sentence
    time_s: float  # clock time when it was raised


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
    encoder_invalid_transitions: int = 0


@dataclass
class SlamStats:
    """What SLAM has been doing, for the status page and the benchmark."""

    scans: int = 0  # revolutions processed
    scans_dropped: int = 0  # revolutions dropped because SLAM was behind
    keyframes: int = 0
    loop_closures: int = 0  # accepted
    loop_closures_rejected: int = 0
    map_rebuilds: int = 0
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
    run_dir: str | None = None  # where this run is saved
    saves: int = 0
    save_errors: int = 0


@dataclass
class SharedState:
    """Everything the tasks share. Created once by ``main.py`` and handed to each task."""

    run_state: RunState = RunState.IDLE
    faults: list[Fault] = field(default_factory=list)
    pose: Pose2D = field(default_factory=Pose2D)
    pose_time_s: float | None = None  # clock time ``pose`` describes (the odometry reading behind it)
    sensors: SensorStats = field(default_factory=SensorStats)
    commands: asyncio.Queue[str] = field(default_factory=lambda: asyncio.Queue(maxsize=32))
    started_at_s: float | None = None
    latest_scan: Scan | None = None  # written by the lidar task
    odometry: OdometryPose | None = None  # written by the odometry task
    #: (left, right) throttle the planner wants and the clock time it was set; the control
    #: task applies it only while RUNNING and only while it is fresh.
    throttle_command: tuple[float, float, float] | None = None
    #: recent lateness of control ticks beyond their period, milliseconds
    control_lateness_ms: deque[float] = field(default_factory=lambda: deque(maxlen=1000))
    #: lidar revolutions waiting for SLAM: the lidar task puts, the SLAM task gets; when SLAM is
    #: behind the oldest is dropped (``mazebot.tasks.lidar_task``); replaced at start-up with the
    #: configured ``[slam] scan_queue_size``
    scans: asyncio.Queue[Scan] = field(default_factory=lambda: asyncio.Queue(maxsize=2))
    #: time-stamped odometry poses of the last seconds (de-skew and SLAM's filter); written by
    #: the odometry task, read by SLAM; None until the odometry task starts
    odometry_history: OdometryHistory | None = None
    # --- written by SLAM ---------------------------------------------------------------
    #: the correction from the odometry frame to the map frame, (x_m, y_m, theta_rad) (ROS
    #: ``map -> odom``); the odometry task publishes ``pose`` as this ⊕ odometry
    map_from_odom: tuple[float, float, float] = (0.0, 0.0, 0.0)
    slam: SlamStats = field(default_factory=SlamStats)
    #: the live occupancy grid, in the map frame (the start pose); a new object with a new
    #: ``generation`` after a loop closure rebuilt it. Read it; never call ``take_dirty`` on it.
    map: OccupancyGrid | None = None
    pose_covariance: np.ndarray | None = None  # 3x3 covariance of (x_m, y_m, theta_rad)
    #: keyframe positions; replaced by a new deque when a loop closure moved them
    trajectory: deque[tuple[float, float]] = field(default_factory=lambda: deque(maxlen=2000))
    #: CPU time of SLAM's update per scan, ms (filter + ICP + grid; loop closures run in an executor)
    scan_ms: deque[float] = field(default_factory=lambda: deque(maxlen=20000))
    # --- written by the planner --------------------------------------------------------
    path: list[tuple[float, float]] = field(default_factory=list)  # planned waypoints, map frame
    goal: tuple[float, float] | None = None  # the current exploration goal, map frame
    coverage: float | None = None  # fraction of the maze the map knows, when the planner can tell
    # --- written by the recorder and the run saver (mazebot.tasks.record_task, persist_task) ---
    record: RecordStats = field(default_factory=RecordStats)

    def raise_fault(self, source: str, message: str, time_s: float) -> None:
        """Record a fault and move to FAULT. Motors are the supervisor's job, not this."""
        self.faults.append(Fault(source, message, time_s))
        del self.faults[:-50]  # keep the recent history bounded
        self.run_state = RunState.FAULT

    def clear_faults(self, source: str | None = None) -> None:
        """Forget faults (of one source, or all); FAULT falls back to IDLE when none remain."""
        self.faults = [f for f in self.faults if source is not None and f.source != source]
        if not self.faults and self.run_state is RunState.FAULT:
            self.run_state = RunState.IDLE

    @property
    def active_fault(self) -> Fault | None:
        return self.faults[-1] if self.faults else None
