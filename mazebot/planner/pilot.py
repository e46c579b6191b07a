"""The planner tick: map and pose in, an exploration goal and a body velocity out.

One :class:`Pilot` ties the parts of ``mazebot/planner`` together the way the daemon
runs them, at the planner rate (5 Hz by default):

1. the explorer reads SLAM's three-state grid, keeps the maze graph up to date and picks
   the next goal (an unknown link, a grid frontier, or the start cell once nothing
   reachable is unknown);
2. the local planner (DWA with in-place turns and recovery) follows the goal's waypoints
   on the latest lidar returns, the occupied map cells and the wall outlines the graph
   knows (posts closer than the lidar's minimum range included);
3. the result goes into ``state.motion_command`` for the control task, which owns the
   wheels (PI control and the safety layer).

It is plain synchronous code so that tests and the benchmark can step it directly; the
asyncio loop around it is :mod:`mazebot.tasks.planner_task`. The run state it may write:
``exploring → returning → done``; it never starts the robot (only the user does) and
leaves ``stopped`` and ``fault`` alone.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Generator
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from mazebot.config import (
    Config,
    ControlConfig,
    DriveConfig,
    LidarConfig,
    PlannerConfig,
    RobotConfig,
)
from mazebot.io.scan import Scan
from mazebot.planner.dwa import (
    FREED_M,
    DynamicWindowPlanner,
    LocalCostmap,
    LocalPlanner,
    LocalStatus,
    cells_without_hits,
    map_points_robot,
    to_robot_frame,
)
from mazebot.planner.exploration import Explorer, Phase
from mazebot.planner.maze_graph import MazeGraph
from mazebot.planner.passages import LANE_WINDOW_M, PATH_STEP_M, first_unreachable
from mazebot.planner.safety import BlindZoneMemory, deskewed_points_robot, reframe_points
from mazebot.planner.wheel_control import DiffDriveKinematics, DriveMode
from mazebot.state import MotionRequest, RunState, SharedState
from mazebot.steps import all_at_once_method

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PilotParams:
    """The configuration sections the pilot reads, as they are: each value and its default defined once.

    The explorer and the local planner read ``[planner]``; the body's speed and turn limits
    ``[drive]``; its footprint ``[robot]``; the stopping distance ``[control]`` (braking, the
    emergency stop's margin, the motors' reaction); the lidar's range and mount ``[lidar]``;
    and the control period of ``[daemon]`` (braking can start one control tick later).
    :meth:`from_config` picks them from a loaded configuration (``Config()``: the defaults).
    """

    planner: PlannerConfig
    drive: DriveConfig
    robot: RobotConfig
    control: ControlConfig
    lidar: LidarConfig
    control_period_s: float

    @classmethod
    def from_config(cls, config: Config) -> PilotParams:
        return cls(config.planner, config.drive, config.robot, config.control, config.lidar,
                   config.daemon.control_period_s)

    @property
    def period_s(self) -> float:
        return 1.0 / self.planner.rate_hz

    @property
    def interim_due_s(self) -> float:
        """Age of the last command at which a motion half runs between a goal half's stages.

        A planner period and a control period. The regular motion half comes a period
        after the previous one plus however much longer this goal half runs than the
        previous one did: at a period alone, every goal half a few milliseconds longer
        than its predecessor set off a second DWA step (a third of the ticks under a Pi 4's
        share on 6x6, a quarter of the DWA's CPU), for a command a few milliseconds
        fresher than the regular one right behind it. A control period later the
        regular one is late by a whole control tick: the control loop, which reads the
        command once a control period, would then run a tick on a command older than the
        DWA's latency (a planner period, a control period, the motors' lag) counts on.
        """
        return self.period_s + self.control_period_s


class DriveInputs(NamedTuple):
    """What a goal half hands to the motion half: the map it read and the goal's target."""

    three: np.ndarray
    origin_m: tuple[float, float]
    resolution_m: float
    target_m: tuple[float, float]


class LaneInputs(NamedTuple):
    """What the DWA saw on the latest motion half (robot frame), to ask for a lane when it gives up."""

    pose: tuple[float, float, float]
    scan_xy: np.ndarray
    map_xy: np.ndarray
    walls_xy: np.ndarray | None
    drive: DriveInputs


#: The robot counts as standing still while it stays within this of where it was (metres, radians).
STILL_M, STILL_RAD = 0.03, 0.15
#: The back-off drives this far back along the robot's own track (metres): known free, it came that way.
BACKOFF_M = 0.15
#: The track is kept as points this far apart, this many of them (enough for the back-off).
TRACK_STEP_M, TRACK_POINTS = 0.03, 20
#: A robot that stays within this of a spot (metres, any heading) for ``WRIGGLE_FACTOR`` times the
#: stand-still revolutions is stuck too, however it turns and shuffles there: the local planner's
#: recoveries turn it and move it 3-6 cm, which starts the stand-still count again each time (a
#: hand-built 8x8 maze: 300 s beside a table leg, the watch acting three times).
WRIGGLE_M, WRIGGLE_FACTOR = 0.1, 3


@dataclass
class StandStill:
    """How long the robot has stood still while it had a goal, in lidar revolutions.

    The explorer and the local planner each have clocks that should move a robot that
    stands (the explorer's dwell and progress counts, the local planner's stuck time-out
    and recoveries), but each can be held: the explorer counts the revolutions SLAM
    *painted*, and SLAM paints none while it distrusts the odometry; the local planner's
    timers start again with every new path. This watch counts what the robot saw
    instead, and acts in steps when the count reaches ``[planner] stand_still_revolutions``:
    give the goal up, then back off along the robot's own track, then stop with a fault.
    """

    limit_revolutions: int = 45  # [planner] stand_still_revolutions
    mark: tuple[float, float, float] | None = None  # where the robot stood when the count began
    revolutions: int = 0
    escalations: int = 0  # steps taken since the robot was last free (FREED_M from where it began)
    freed_from: tuple[float, float] | None = None
    last_scan: object | None = None  # the last revolution counted, told apart by identity (held: an id() may be reused)
    painted_at_mark: int = 0  # SLAM's painted revolutions when the count (re)started
    painted: int = 0  # of the revolutions stood, how many SLAM painted (the explorer's clock)
    track: deque[tuple[float, float]] = field(default_factory=lambda: deque(maxlen=TRACK_POINTS))
    wriggle_mark: tuple[float, float] | None = None  # where the robot was when the wriggle count began
    wriggle_revolutions: int = 0  # revolutions since, all within WRIGGLE_M of it
    wriggle_painted_at: int = 0  # SLAM's painted revolutions when the wriggle count began
    wriggled: bool = False  # the last count that reached its limit was the wriggle count

    def reset(self) -> None:
        self.mark, self.revolutions, self.escalations, self.freed_from, self.last_scan = None, 0, 0, None, None
        self.wriggle_mark, self.wriggle_revolutions = None, 0
        self.track.clear()

    def observe(self, pose: tuple[float, float, float], scan: object | None, painted: int = 0) -> int:
        """Count one planner tick at ``pose`` (``scan``: the latest revolution, held to tell a new one;
        ``painted``: SLAM's count of painted revolutions, for the report).

        Returns the revolutions stood when they have just reached the limit (the count
        then starts again from there, and :attr:`painted` says how many SLAM painted), else 0.
        """
        xy = (pose[0], pose[1])
        if not self.track or math.dist(self.track[-1], xy) >= TRACK_STEP_M:
            self.track.append(xy)
        if self.freed_from is not None and math.dist(self.freed_from, xy) >= FREED_M:
            self.escalations, self.freed_from = 0, None
        if self.wriggle_mark is None or math.dist(self.wriggle_mark, xy) > WRIGGLE_M:
            self.wriggle_mark, self.wriggle_revolutions, self.wriggle_painted_at = xy, 0, painted
        mark = self.mark
        turned = 0.0 if mark is None else abs(math.remainder(pose[2] - mark[2], math.tau))
        new_scan = scan is not None and scan is not self.last_scan
        if mark is None or math.dist(mark[:2], xy) > STILL_M or turned > STILL_RAD:
            self.mark, self.revolutions, self.last_scan, self.painted_at_mark = pose, 0, scan, painted
            # the robot moved or turned, yet within WRIGGLE_M: that revolution counts as wriggling
            return self._wriggled(xy, painted) if new_scan else 0
        if not new_scan:
            return 0
        self.last_scan = scan
        self.revolutions += 1
        if self.revolutions < self.limit_revolutions:
            return self._wriggled(xy, painted)
        stood, self.revolutions = self.revolutions, 0
        self.wriggle_mark, self.wriggle_revolutions, self.wriggle_painted_at, self.wriggled = xy, 0, painted, False
        self.painted, self.painted_at_mark = painted - self.painted_at_mark, painted
        return stood

    def _wriggled(self, xy: tuple[float, float], painted: int) -> int:
        """One more revolution within WRIGGLE_M: the revolutions wriggled once they reach the limit, else 0."""
        self.wriggle_revolutions += 1
        if self.wriggle_revolutions < WRIGGLE_FACTOR * self.limit_revolutions:
            return 0
        wriggled, self.wriggle_revolutions, self.wriggle_mark, self.wriggled = self.wriggle_revolutions, 0, xy, True
        self.painted, self.wriggle_painted_at = painted - self.wriggle_painted_at, painted
        self.mark, self.revolutions = None, 0  # the stand-still count starts again from here too
        return wriggled

    def backoff_path(self, xy_m: tuple[float, float]) -> list[tuple[float, float]]:
        """Waypoints from ``xy_m`` back along the track, ``BACKOFF_M`` of it (empty: no track behind)."""
        path = [xy_m]
        run = 0.0
        for point in reversed(self.track):
            step = math.dist(path[-1], point)
            if step < TRACK_STEP_M / 2:
                continue
            path.append(point)
            run += step
            if run >= BACKOFF_M:
                break
        return path if len(path) > 1 else []


class Pilot:
    """Explorer + local planner for one daemon; :meth:`tick` once per planner period."""

    def __init__(self, params: PilotParams) -> None:
        self.params = params
        self.kinematics = DiffDriveKinematics(params.drive.track_width_m, params.drive.max_wheel_speed_mps)
        self.run_number = -1  # the run the explorer was built for
        self.explorer = self._new_explorer((0.0, 0.0))
        self.local = self._new_local_planner()
        self._was_moving = False
        self._recovering = False
        #: motion halves run so far: the local planner's clock is this times the period, so its
        #: time-outs (stuck, blocked, aligning, backing off) count ticks run, not wall time
        self.drive_ticks = 0
        self._last_reason: str | None = None
        #: (the Scan, its robot-frame points). The Scan itself is held, not its ``id()``: once a
        #: revolution is dropped, CPython may give a later one its address, and a cache keyed by
        #: the id would then serve a revolution the planner skipped as the newest one (whether it
        #: does depends on what other threads allocate, so a run would not be a function of its seed)
        self._scan_cache: tuple[Scan, np.ndarray] | None = None
        #: returns the lidar saw close by and can no longer see (inside its minimum range)
        self.blind_zone = BlindZoneMemory(params.lidar.min_range_m, lidar_xy_m=params.lidar.mount_xy_m,
                                          body_radius_m=params.robot.footprint_radius_m)
        #: the serial of SLAM's last odometry fix the memory took in (``state.odometry_fixes``)
        self._fixes_seen = 0
        #: what plan() hands to drive(): (three-state grid, origin_m, resolution_m, goal target_m)
        self._drive_inputs: DriveInputs | None = None
        #: the inputs of the latest motion half, for one between the stages of a long goal half
        #: (:meth:`interim_drive_steps`); None once a goal half decided not to drive
        self._last_drive_inputs: DriveInputs | None = None
        #: when this pilot last wrote ``state.motion_command`` (the clock's seconds)
        self.last_command_s = -math.inf
        #: a motion half between stages gave up on the goal: reported by the next regular one
        self._give_up_pending = False
        #: motion halves run between the stages of a goal half (:meth:`interim_drive_steps`)
        self.interim_drives = 0
        #: standing still with a goal, in lidar revolutions (see :class:`StandStill`)
        self.still = StandStill(params.planner.stand_still_revolutions)
        #: the back-off path while the pilot backs the robot off along its track, else None
        self._backoff: list[tuple[float, float]] | None = None
        #: what the DWA saw on the latest regular motion half (for the lane check of a give-up)
        self._lane_inputs: LaneInputs | None = None

    # -- construction ------------------------------------------------------------------

    def _new_explorer(self, start_xy_m: tuple[float, float]) -> Explorer:
        p, robot = self.params.planner, self.params.robot
        graph = MazeGraph(
            cell_size_m=p.cell_size_m,
            wall_thickness_m=p.wall_thickness_m,
            anchor_xy_m=start_xy_m,
            pitch_search=p.cell_size_search,
        )
        return Explorer(
            graph,
            strategy=p.strategy,
            mode=p.mode,
            start_xy_m=start_xy_m,
            goal_tolerance_m=p.goal_tolerance_m,
            progress_revolutions=p.progress_revolutions,
            dwell_revolutions=p.dwell_revolutions,
            retry_after_m=p.retry_after_m,
            max_attempts=p.max_attempts,
            max_drops=p.max_drops,
            footprint_radius_m=robot.footprint_radius_m,
            clearance_m=robot.clearance_m,
            lidar_min_range_m=self.params.lidar.min_range_m,
        )

    def _new_local_planner(self) -> LocalPlanner:
        p = self.params
        dwa = DynamicWindowPlanner(
            max_speed_mps=p.drive.max_speed_mps,
            max_yaw_rate_radps=p.drive.max_yaw_rate_radps,
            max_accel_mps2=p.drive.max_accel_mps2,
            max_yaw_accel_radps2=p.drive.max_yaw_accel_radps2,
            brake_decel_mps2=p.control.brake_decel_mps2,
            # the emergency stop's margin: an arc admissible here is one the safety layer lets run
            stop_margin_m=p.control.stop_margin_m,
            footprint_radius_m=p.robot.footprint_radius_m,
            clearance_m=p.robot.clearance_m,
            # the dynamic window spans one planner period; braking can start one period
            # later at the earliest, plus a control period and the motors' reaction
            window_s=p.period_s,
            latency_s=p.period_s + p.control_period_s + p.control.actuation_latency_s,
            horizon_s=p.planner.horizon_s,
        )
        # arrive a little inside the explorer's tolerance, or it would never see "arrived"
        return LocalPlanner(
            dwa,
            goal_tolerance_m=min(0.04, 0.7 * p.planner.goal_tolerance_m),
            stuck_timeout_s=p.planner.stuck_timeout_s,
            max_recoveries=p.planner.max_recoveries,
            recoveries_per_place=p.planner.close_passages,
        )

    # -- the tick ------------------------------------------------------------------------

    def tick(self, state: SharedState, now_s: float) -> None:
        """Decide this period's goal and command, writing them into ``state``."""
        if self.plan(state, now_s):
            self.drive(state, now_s)

    def plan_steps(self, state: SharedState, now_s: float) -> Generator[None, None, bool]:
        """:meth:`plan` in stages (:mod:`mazebot.steps`): the map's three states, the maze graph, the goal.

        The map and pose are read before the first stage; a stop pressed while the stages
        run leaves the state alone (no goal, no ``returning``).
        """
        self._drive_inputs = None
        follow = yield from self._plan_steps(state, now_s)
        if not follow:  # held, done, stopped or a new run: nothing to follow between stages either
            self._last_drive_inputs = None
        return follow

    def _plan_steps(self, state: SharedState, now_s: float) -> Generator[None, None, bool]:
        if not state.run_state.moving:
            if self._was_moving:  # stopped, done or faulted since the last tick: forget the path
                self.local.clear()
                state.motion_command = None
                self.still.mark = None  # a pause is not standing still with a goal
            self._was_moving = False
            # SLAM goes on fixing the odometry frame while the robot waits: the blind-zone memory follows
            # it, so a pause longer than the fixes are kept does not cost the memory a leg beside the robot
            if self._take_fixes(state):
                state.blind_zone_points = self.blind_zone.snapshot()
            return False
        self._was_moving = True
        pose = (state.pose.x_m, state.pose.y_m, state.pose.theta_rad)
        if state.run_number != self.run_number:  # a new exploration starts where the robot stands
            self.run_number = state.run_number
            self.explorer = self._new_explorer((pose[0], pose[1]))
            self.local.clear()
            self._last_drive_inputs, self._give_up_pending = None, False
            self.still.reset()
            self._backoff = None
            log.info("exploration %d starts at (%.2f, %.2f) m", self.run_number, pose[0], pose[1])
        grid = state.map
        if grid is None:
            self._hold(state, now_s, "waiting for the first map")
            return False
        if not state.slam.anchored:  # SLAM fuses revolutions at rest into the map's anchor (20, ~3.6 s)
            self._hold(state, now_s, "waiting for SLAM to anchor the map (standing still)")
            return False
        if state.slam.rest_wanted:  # SLAM paints nothing and matches nothing in motion: rest heals its trust
            self._hold(state, now_s, "standing still: SLAM takes the wheels' motion again after a slip")
            return False
        three = grid.three_state()
        yield
        # the explorer's clock: revolutions SLAM painted into the map (what can resolve a target)
        painted = max(0, state.slam.scans - state.slam.held_back)
        goal = yield from self.explorer.update_steps(three, grid.origin_m, grid.resolution_m, pose, painted)
        if not state.run_state.moving:  # stopped while the stages ran: the next tick forgets the path
            return False
        self._note_events(state, now_s, goal.reason if goal is not None else None, pose)
        state.coverage = self._coverage()
        if self.explorer.no_way_home is not None:
            self._no_way_home(state, now_s, self.explorer.no_way_home)
            return False
        if goal is None:
            self._hold(state, now_s, "waiting for the map to cover the robot")
            return False
        if goal.phase is Phase.DONE:
            self._finish(state, now_s)
            return False
        if goal.phase is Phase.RETURNING and state.run_state is RunState.EXPLORING:
            state.run_state = RunState.RETURNING
            log.info("nothing reachable is unknown: returning to the start")
        if self._backoff is not None:  # backing off along the track: the goal waits
            self.local.set_path(self._backoff)
            state.path = list(self._backoff)
            state.goal = self._backoff[-1]
            state.planner_status = f"{goal.phase.value}: backing off along its track"
            self._drive_inputs = DriveInputs(three, grid.origin_m, grid.resolution_m, self._backoff[-1])
            return True
        self.local.set_path(goal.waypoints_m)
        state.path = [(float(x), float(y)) for x, y in goal.waypoints_m]
        state.goal = (float(goal.target_m[0]), float(goal.target_m[1]))
        state.planner_status = f"{goal.phase.value}: {goal.reason}" if goal.reason else goal.phase.value
        self._drive_inputs = DriveInputs(three, grid.origin_m, grid.resolution_m, goal.target_m)
        return True

    plan = all_at_once_method(
        plan_steps,
        """The goal half of a tick: map → maze graph → goal → path. True when :meth:`drive` should follow.

        The two halves are separate so the planner task can let the event loop run in
        between (the control loop's ticks must not wait for a whole planner tick).
        """,
    )

    def drive_steps(self, state: SharedState, now_s: float) -> Generator[None, None, None]:
        """:meth:`drive` in stages (:mod:`mazebot.steps`): the planner task lets the loop run between them.

        The inputs (pose, scan, map) are read before the first stage; a stop pressed while
        the stages run leaves the command alone (the control task already commands zero).
        """
        if self._drive_inputs is None or not state.run_state.moving:  # stopped since plan(): nothing to drive
            return
        inputs, self._drive_inputs = self._drive_inputs, None
        self._last_drive_inputs = inputs
        if self._give_up_pending:  # a motion half between the stages gave up: the explorer hears it now
            self._give_up_pending = False
            self._check_passage(state, now_s)  # on what that motion half saw
            self._report_give_up(state, now_s, inputs.target_m)
        yield from self._follow_steps(state, now_s, inputs, interim=False)

    drive = all_at_once_method(
        drive_steps, "The motion half of a tick: the DWA along the path on the latest scan, map and pose."
    )

    def motion_due(self, now_s: float) -> bool:
        """True when a motion half should run before the goal half in progress ends.

        A goal half on a large map (a frontier search over the whole grid) can take
        longer than a planner period of wall time on a slow or shared CPU, and the control
        loop stops the wheels when the command is ``command_ttl_ticks`` old. The path of the
        previous goal half is still the one to follow until the new one is chosen, so
        the motion half follows it on the latest pose and scan, once the last command is
        :attr:`PilotParams.interim_due_s` old. Never due on the virtual clock (no time
        passes inside a tick there), nor when the previous goal half decided not to drive.
        """
        return self._last_drive_inputs is not None and now_s - self.last_command_s >= self.params.interim_due_s

    def interim_drive_steps(self, state: SharedState, now_s: float) -> Generator[None, None, None]:
        """A motion half between the stages of a goal half (:meth:`motion_due`): the previous path,
        the map the previous goal half read, the latest pose and scan.

        Everything it reads the goal half leaves alone until its last stage (the local
        planner's path is set there, after the stages); a give-up is reported to the
        explorer by the next regular motion half, not in the middle of the explorer's update.
        """
        inputs = self._last_drive_inputs
        if inputs is None or not state.run_state.moving:
            return
        self.interim_drives += 1
        yield from self._follow_steps(state, now_s, inputs, interim=True)

    def _follow_steps(
        self, state: SharedState, now_s: float, inputs: DriveInputs, interim: bool
    ) -> Generator[None, None, None]:
        """The DWA along the local planner's path on ``inputs``' map and the latest pose and scan."""
        three, origin_m, resolution_m, target_m = inputs
        pose = (state.pose.x_m, state.pose.y_m, state.pose.theta_rad)
        window_m = self.params.planner.map_window_m
        map_xy = map_points_robot(three, origin_m, resolution_m, pose, window_m)
        walls_xy = None
        if self.explorer.mode == "maze":
            walls_xy = to_robot_frame(self.explorer.graph.wall_points_m(pose[:2], window_m), pose)
        velocity = self.kinematics.body_velocity(*state.wheel_speeds_mps)
        scan_xy = self._scan_points(state)
        if self.params.planner.hits_replace_cells:
            map_xy = cells_without_hits(map_xy, scan_xy, pose, origin_m, resolution_m)
        self.drive_ticks += 1
        tick_time_s = self.drive_ticks * self.params.period_s  # a late tick is one tick, not its lateness
        yield
        cmd = yield from state.cpu.part("dwa").steps(
            self.local.step_steps(pose, velocity, scan_xy, map_xy, resolution_m * math.sqrt(0.5), tick_time_s, walls_xy)
        )
        if not state.run_state.moving:  # stopped while the stages ran
            return
        if cmd.status is LocalStatus.RECOVERING and not self._recovering and not cmd.give_up:
            where = f"{pose[0]:.2f}, {pose[1]:.2f}"
            state.planner_events.append((now_s, f"stuck: recovery {self.local.recoveries} at {where}"))
        self._recovering = cmd.status is LocalStatus.RECOVERING
        if self._backoff is not None and (cmd.give_up or cmd.status is LocalStatus.REACHED):
            if not interim:  # backed off (or could not): the goal again from here
                self._backoff = None
                self.local.clear()
        elif cmd.give_up and interim:
            self._give_up_pending = True
            self._lane_inputs = LaneInputs(pose, scan_xy, map_xy, walls_xy, inputs)
        elif cmd.give_up:
            self._lane_inputs = LaneInputs(pose, scan_xy, map_xy, walls_xy, inputs)
            self._check_passage(state, now_s)
            self._report_give_up(state, now_s, target_m)
        self._command(state, MotionRequest(cmd.v_mps, cmd.w_radps, cmd.mode.value, now_s))
        if interim:  # the watch acts on the explorer: only between goal halves, never inside one
            return
        scan = state.latest_scan
        painted = max(0, state.slam.scans - state.slam.held_back)
        stood = self.still.observe(pose, scan, painted)
        if stood:
            self._lane_inputs = LaneInputs(pose, scan_xy, map_xy, walls_xy, inputs)
            self._stood_still(state, now_s, pose, stood)

    def _stood_still(self, state: SharedState, now_s: float, pose: tuple[float, float, float], stood: int) -> None:
        """The robot has stood still ``stand_still_revolutions`` with a goal: act, one step further each time.

        1. give the goal up (the explorer blacklists it; in ``returning``, the route is
           planned afresh); 2. back off along the robot's own track, which it drove, so is
           free; 3. stop with a latched ``planner`` fault that says why (start tries again).
        A robot that cannot move never sits for ever in ``exploring`` or ``returning``.
        """
        still = self.still
        still.escalations += 1
        if still.freed_from is None:
            still.freed_from = (pose[0], pose[1])
        where = f"({pose[0]:.2f}, {pose[1]:.2f})"
        how = f"stayed within {WRIGGLE_M:.2f} m" if still.wriggled else "stood still"
        what = (f"{how} for {stood} lidar revolutions at {where}, SLAM painted {still.painted} of them "
                f"({state.planner_status})")  # revolutions as its ticks saw them: two in one tick count once
        backoff = still.backoff_path((pose[0], pose[1])) if still.escalations == 2 else []
        if still.escalations == 1:
            text = f"{what}: giving the goal up"
            self._check_passage(state, now_s)
            self.explorer.report_unreachable()
            self.local.clear()
        elif backoff:
            text = f"{what}: backing off {BACKOFF_M:.2f} m along its track"
            self._backoff = backoff
            self.local.clear()
        else:
            text = f"{what}: neither giving the goal up nor backing off moved it; stopped (start tries again)"
            self._backoff = None
            self.local.clear()
            self._command(state, MotionRequest(0.0, 0.0, DriveMode.STOP.value, now_s))
            state.raise_fault("planner", text, now_s, latched=True)
        log.warning("%s", text)
        state.planner_events.append((now_s, text))
        self._note_events(state, now_s, None, pose)

    def _check_passage(self, state: SharedState, now_s: float) -> bool:
        """On a give-up: is the path ahead without a lane for the robot's body? Then the explorer closes
        the passage there and plans round it (:mod:`mazebot.planner.passages`). True if it did.

        The lane is asked of the costmap the DWA had on the latest motion half (the scan, the
        occupied map cells, the walls the graph knows, inflated alike), so it agrees with the DWA.
        """
        lane, path = self._lane_inputs, self.local.path
        if not self.params.planner.close_passages or lane is None or path is None:
            return False
        costmap = LocalCostmap(
            lane.scan_xy if lane.walls_xy is None else np.concatenate((lane.scan_xy, lane.walls_xy)),
            lane.map_xy,
            lane.drive.resolution_m * math.sqrt(0.5),
            self.local.dwa.footprint_radius_m,
            self.local.dwa.clearance_m,
        )
        # the path ahead, from the robot's progress to past the lane's window
        s_m = np.arange(path.progress_m, path.progress_m + 2.0 * LANE_WINDOW_M, PATH_STEP_M)
        path_m = path.points_at(np.minimum(s_m, path.length_m))
        k = first_unreachable(costmap, to_robot_frame(path_m, lane.pose), self.local.dwa.contact_m)
        if k is None:
            return False
        drive = lane.drive
        self.explorer.close_passage(path_m, k, drive.three, drive.origin_m, drive.resolution_m)
        self._note_events(state, now_s, None, lane.pose)
        return True

    def _no_way_home(self, state: SharedState, now_s: float, why: str) -> None:
        """The only way home passes a closed passage: stop the motors, say where (a latched fault)."""
        self.local.clear()
        self._backoff = None
        self._command(state, MotionRequest(0.0, 0.0, DriveMode.STOP.value, now_s))
        text = f"{why}; stopped (start tries again)"
        log.warning("%s", text)
        state.planner_events.append((now_s, text))
        state.raise_fault("planner", text, now_s, latched=True)
        self.explorer.forget_closed()  # a start tries the passage again (what closed it may have been moved)

    def _report_give_up(self, state: SharedState, now_s: float, target_m: tuple[float, float]) -> None:
        log.info("giving up on the goal at (%.2f, %.2f) m: the local planner cannot reach it", *target_m)
        state.planner_events.append((now_s, "the local planner gave up on the goal"))
        self.explorer.report_unreachable()
        pose = (state.pose.x_m, state.pose.y_m, state.pose.theta_rad)
        self._note_events(state, now_s, None, pose)

    def _command(self, state: SharedState, command: MotionRequest) -> None:
        state.motion_command = command
        self.last_command_s = command.time_s

    def _note_events(
        self, state: SharedState, now_s: float, reason: str | None, pose: tuple[float, float, float]
    ) -> None:
        """Log the explorer's blacklists and each new target into ``state.planner_events``."""
        for text in self.explorer.events:
            log.info("%s", text)
            state.planner_events.append((now_s, text))
        self.explorer.events.clear()
        if reason is not None and reason != self._last_reason:
            state.planner_events.append((now_s, f"{reason}; robot at {pose[0]:.2f}, {pose[1]:.2f}"))
            self._last_reason = reason

    def _hold(self, state: SharedState, now_s: float, why: str) -> None:
        self._command(state, MotionRequest(0.0, 0.0, DriveMode.STOP.value, now_s))
        state.planner_status = why

    def _finish(self, state: SharedState, now_s: float) -> None:
        self.local.clear()
        self._command(state, MotionRequest(0.0, 0.0, DriveMode.STOP.value, now_s))
        state.run_state = RunState.DONE
        state.finished_at_s = now_s
        state.path = []
        state.goal = None
        elapsed = state.elapsed_s(now_s)
        coverage = "unknown" if state.coverage is None else f"{100 * state.coverage:.0f} %"
        state.planner_status = f"done: back at the start after {elapsed or 0.0:.0f} s, coverage {coverage}"
        log.info("%s", state.planner_status)
        self._was_moving = False

    def _coverage(self) -> float | None:
        """Explored cells over the cells known to be reachable (maze mode); None otherwise.

        During the run the denominator grows as the graph discovers cells; once nothing
        reachable is unknown it is the whole reachable maze.
        """
        if self.explorer.mode != "maze" or not self.explorer.graph.ready:
            return None
        graph = self.explorer.graph
        start = graph.frame.cell_of(*self.explorer.start_xy_m)  # type: ignore[union-attr]  # ready: a frame exists
        return graph.explored_share(start)

    def _scan_points(self, state: SharedState) -> np.ndarray:
        """The latest revolution's valid returns, robot frame, moved to where the robot is now,
        and the returns remembered inside the lidar's blind zone (:class:`BlindZoneMemory`).

        The memory takes in each new revolution, then SLAM's fixes of the odometry frame since
        the last call (:meth:`_take_fixes`): each revolution's returns end where SLAM has that
        revolution, so a slipping tyre's odometry does not smear them, and a revolution SLAM
        held back does not cost the memory what it held before.
        """
        scan = state.latest_scan
        if scan is None:
            return np.zeros((0, 2))
        history, odo = state.odometry_history, state.odometry
        changed = False
        if self._scan_cache is None or self._scan_cache[0] is not scan:
            lidar = self.params.lidar
            points = deskewed_points_robot(scan.angle_rad, scan.range_m, scan.valid, scan.time_s, history,
                                           lidar.min_range_m, lidar.max_range_m, lidar.mount_xy_m)
            self._scan_cache = (scan, points)
            if history is not None and len(history) > 0:
                then = history.pose_at(scan.end_time_s)
                self.blind_zone.add_scan(points, (float(then[0]), float(then[1]), float(then[2])), scan.end_time_s)
                changed = True
        if self._take_fixes(state) or changed:  # SLAM's fixes after the scan: they may be of this revolution
            state.blind_zone_points = self.blind_zone.snapshot()  # for the control loop's guard
        points = moved_since_scan(self._scan_cache[1], scan.end_time_s, state)
        if odo is None or len(self.blind_zone) == 0:
            return points
        return np.concatenate((points, self.blind_zone.points_robot((odo.x_m, odo.y_m, odo.theta_rad))))

    def _take_fixes(self, state: SharedState) -> bool:
        """SLAM's fixes of the odometry frame (``state.odometry_fixes``) not yet in the blind-zone memory,
        into it in order; whether there were any.

        While the robot is stopped the planner takes them every tick (:meth:`_plan_steps`); while it
        drives, here, after the newest revolution went in, so that its fix places it. Fixes can
        only be missed by a planner that held a goal for longer than they are kept (46 s) without
        driving: the memory then cannot tell where its returns are, and is forgotten.
        """
        fixes = state.odometry_fixes
        if not fixes or fixes[-1].serial <= self._fixes_seen:
            return False
        if fixes[0].serial > self._fixes_seen + 1:
            self.blind_zone.clear()
        for fix in fixes:
            if fix.serial > self._fixes_seen:
                self.blind_zone.fix(fix.revolution_end_s, fix.before, fix.after, fix.vouched)
        self._fixes_seen = fixes[-1].serial
        return True


def moved_since_scan(points_robot: np.ndarray, scan_time_s: float, state: SharedState) -> np.ndarray:
    """Robot-frame points seen at ``scan_time_s``, in the robot frame of the latest odometry.

    The odometry history gives the pose at the scan's end; the motion since then (a
    revolution takes 0.18 s, at 0.3 m/s that is 5 cm) is taken out so the points are
    where the walls are now relative to the robot. Without odometry they are used as is.
    """
    history, odo = state.odometry_history, state.odometry
    if history is None or odo is None or len(history) == 0:
        return points_robot
    then = history.pose_at(scan_time_s)
    pose_then = (float(then[0]), float(then[1]), float(then[2]))
    return reframe_points(points_robot, pose_then, (odo.x_m, odo.y_m, odo.theta_rad))
