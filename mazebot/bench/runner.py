"""One benchmark run: the whole daemon on a simulated robot, on virtual time, measured.

The run uses ``main.run_daemon`` with the simulator's hardware builder, exactly as
``mazebot run --sim`` does, minus the web server; the benchmark adds two tasks of its
own: the driver (``--drive scripted`` follows a ground-truth tour) and a recorder that
samples the estimated pose (SLAM's, ``state.pose``) ten times a second with the true pose
at the instant the estimate describes: the simulated time shown by the encoder reading
behind it (``state.pose_time_s``; the simulator steps every ``[sim] step_period_s``, so
that is up to one step before the reading).
``ate_turn_about_start_deg`` and ``ate_rms_turned_back_m`` split the ATE: the turn about the
start that best fits the whole estimate to the truth, and the RMS left without it
(:func:`mazebot.bench.metrics.turn_about_start`).
Metrics that need a part the daemon does not have yet are ``None`` (``null`` in
results.json), never guessed.

Map metrics compare SLAM's final grid with the world, after moving it into the world
frame with the true start pose (the map frame is the robot's start pose):

- ``coverage``: the share of the reachable free cells (:func:`mazebot.sim.raster.free_reachable`
  at the map's resolution) whose map cell is known free (three-state); ``uncovered_occupied`` and
  ``uncovered_unknown`` the shares whose map cell is occupied (painted wrong) or unknown (unseen);
- ``map_f1``: F1 of the map's occupied cells against the true occupancy with a one-cell
  tolerance: precision = share of occupied map cells within one cell of a true wall
  cell, recall = share of true wall cells next to the reachable area (walls the lidar
  can see) within one cell of an occupied map cell;
- ``false_loop_closures``: accepted loop closures whose measured relative pose is more
  than ``FALSE_CLOSURE_M`` or ``FALSE_CLOSURE_RAD`` off the true one.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import resource
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from mazebot.bench.fault_metrics import RECOVERY_WINDOW_S, FaultRecord, fault_metrics
from mazebot.bench.metrics import (
    count_revisits,
    false_closures,
    map_metrics,
    relative_poses,
    turn_about_start,
)
from mazebot.bench.scripted_drive import ScriptedDriver, dfs_tour, straighten
from mazebot.bench.virtual_executor import CpuTimedExecutor
from mazebot.clock import RealClock
from mazebot.config import Config
from mazebot.errors import UsageError
from mazebot.io.encoders import EncoderReading
from mazebot.main import Hardware, run_daemon
from mazebot.sim.backend import sim_hardware_builder, simulated_robot
from mazebot.sim.faults import FaultInjector, FaultSpec
from mazebot.sim.virtual_time import SlowCpu, run_virtual
from mazebot.state import RunState, SharedState
from mazebot.tasks.supervisor import Supervisor

if TYPE_CHECKING:  # the daemon imports SLAM when it builds it
    from mazebot.slam.slam import Slam

RECORD_PERIOD_S = 0.1


@dataclass(frozen=True)
class RunSpec:
    """What to run: a maze file or a generated maze, a seed, a way of driving."""

    maze_path: str | None
    size: tuple[int, int] | None
    seed: int
    drive: str = "scripted"  # "scripted" or "explore"
    max_sim_s: float = 900.0
    clock: str = "virtual"  # "virtual" or "real"
    world: str = "maze"  # "maze" (a file or generated) or "room" (the room with cylinders)
    record_path: str | None = None  # record the run to this MCAP file (mazebot.record)
    faults: tuple[FaultSpec, ...] = ()  # injected into the simulated world (mazebot.sim.faults)
    recovery_window_s: float = RECOVERY_WINDOW_S  # a fault run goes on this long after its last fault
    slow: SlowCpu | None = None  # virtual time only: behave like a slower computer (mazebot.sim.virtual_time)

    @property
    def name(self) -> str:
        if self.world == "room":
            return "room"
        if self.maze_path:
            from pathlib import Path

            return Path(self.maze_path).stem
        w, h = self.size or (0, 0)
        return f"generated-{w}x{h}"


@dataclass
class RunRecord:
    """Everything measured during one run, before it is turned into metrics."""

    times_s: list[float] = field(default_factory=list)
    true_poses: list[tuple[float, float, float]] = field(default_factory=list)
    est_poses: list[tuple[float, float, float]] = field(default_factory=list)
    hardware: Hardware | None = None
    state: SharedState | None = None
    driver: ScriptedDriver | None = None
    done: bool = False  # the tour ended (scripted) or the planner reached DONE (explore)
    start_s: float = 0.0
    end_s: float = 0.0
    faults: FaultRecord | None = None  # what was injected and what happened (fault runs)
    executor: CpuTimedExecutor | None = None  # virtual time: how long the loop waited for the worker




def _instrument(
    spec: RunSpec, injector: FaultInjector | None, record: RunRecord, watch_slam: Callable[[Slam], None] | None = None
) -> Callable[[Slam, Executor], Executor] | None:
    """The ``run_daemon`` hook: on virtual time the lost-robot search takes its CPU time
    (:mod:`mazebot.bench.virtual_executor`); the fault injector reaches SLAM and its executor;
    ``watch_slam`` is shown the daemon's Slam before its first revolution (to listen on its taps)."""
    if spec.clock != "virtual" and watch_slam is None:
        return injector.instrument if injector is not None else None

    def instrument(slam: Slam, executor: Executor) -> Executor:
        if watch_slam is not None:
            watch_slam(slam)
        if spec.clock == "virtual":
            executor = record.executor = CpuTimedExecutor(executor, asyncio.get_running_loop())
        return injector.instrument(slam, executor) if injector is not None else executor

    return instrument


def run_one(
    config: Config, spec: RunSpec, *, watch_slam: Callable[[Slam], None] | None = None
) -> tuple[dict[str, Any], RunRecord]:
    """Run one simulated mission and return its metrics and the raw record (for figures).

    ``watch_slam`` is called with the daemon's Slam once it is built, before its first
    revolution: tools and tests listen on its taps there (:class:`mazebot.slam.slam.SlamTaps`).
    """
    if spec.drive not in ("scripted", "explore"):
        raise UsageError(f"--drive must be scripted or explore, got {spec.drive!r}")
    if spec.slow is not None and spec.clock != "virtual":
        raise UsageError("a slowed CPU is emulated on the virtual clock only; use --clock virtual")
    harness = BenchHarness(_run_config(config, spec), spec)
    builder = sim_hardware_builder(maze_path=spec.maze_path, seed=spec.seed if not spec.maze_path else None,
                                   size=spec.size if not spec.maze_path else None)
    wall0, cpu0 = time.perf_counter(), time.process_time()
    session = None
    if spec.record_path:
        from pathlib import Path

        from mazebot.run_session import RunSession

        session = RunSession(record_path=Path(spec.record_path))
    daemon = run_daemon(
        harness.config, builder, serve_web=False, install_signal_handlers=False, on_started=harness.on_started,
        session=session, autonomous=spec.drive == "explore",
        instrument=_instrument(spec, harness.injector, harness.record, watch_slam),
    )
    exit_code = run_virtual(daemon, slow=spec.slow) if spec.clock == "virtual" else asyncio.run(daemon)
    wall_s = time.perf_counter() - wall0
    cpu_s = time.process_time() - cpu0
    metrics = compute_metrics(spec, harness.record, exit_code=exit_code, wall_s=wall_s, cpu_s=cpu_s)
    return metrics, harness.record


def _run_config(config: Config, spec: RunSpec) -> Config:
    """The configuration of one run: the spec's seed and world; a fault run survives its faults."""
    config = config.model_copy(deep=True)
    config.sim.seed = spec.seed
    config.sim.world = spec.world  # type: ignore[assignment]
    config.daemon.exit_on_fault = not spec.faults
    if spec.faults:  # the run must survive them and go on by itself once they clear
        config.daemon.auto_resume = True
    return config


class BenchHarness:
    """What the benchmark adds to the daemon for one run: a driver, a recorder, the fault injector.

    :meth:`on_started` is ``run_daemon``'s hook: it gets the opened (simulated) hardware and
    starts :meth:`recorder` and :meth:`drive_then_stop` under the daemon's supervisor. The
    driver is the scripted tour (:meth:`drive_scripted`) or the user pressing start
    (:meth:`explore`); either way the run stops itself when it is done or out of time.
    """

    def __init__(self, config: Config, spec: RunSpec) -> None:
        self.config, self.spec = config, spec
        self.record = RunRecord()
        self.clock = RealClock()
        self.injector = FaultInjector(list(spec.faults), None, self.clock, seed=spec.seed) if spec.faults else None
        if self.injector is not None:
            self.record.faults = FaultRecord(self.injector, recovery_window_s=spec.recovery_window_s)
        #: which simulated instant each encoder reading shows: (clock time, sim time)
        self.readings: deque[tuple[float, float]] = deque(maxlen=64)

    def on_started(self, hardware: Hardware, state: SharedState, supervisor: Supervisor) -> None:
        """The daemon is up: the harness's tasks start beside its own."""
        self.hardware, self.state, self.supervisor = hardware, state, supervisor
        self.robot = robot = simulated_robot(hardware)
        driver = self._scripted_driver() if self.spec.drive == "scripted" else None
        self.record.hardware, self.record.state, self.record.driver = hardware, state, driver
        self.record.start_s = self.clock.now_s()
        self._tap_encoders()
        if self.injector is not None:
            self.injector.ctx.robot = robot
            assert self.record.faults is not None
            self.record.faults.watch(robot, state, supervisor, self.clock)
            supervisor.start("bench-faults", self.injector.run)
        supervisor.start("bench-recorder", self.recorder)
        supervisor.start("bench-driver", self.drive_then_stop)

    def _scripted_driver(self) -> ScriptedDriver:
        """A ground-truth depth-first tour of the maze's cells at 80 % of the drive's limits."""
        config, robot = self.config, self.robot
        layout = robot.world.maze
        if layout is None:
            raise UsageError(f"--drive scripted needs a maze world, {robot.world.name} has no cells")
        tour = straighten(dfs_tour(layout))
        return ScriptedDriver(
            [layout.cell_center_m(c) for c in tour[1:]],
            robot.physics,
            speed_mps=config.drive.max_speed_mps * 0.8,
            yaw_rate_radps=config.drive.max_yaw_rate_radps * 0.8,
            track_width_m=config.drive.track_width_m,
            full_throttle_mps=config.drive.max_wheel_speed_mps,
            deadband=config.sim.deadband,
        )

    def _tap_encoders(self) -> None:
        """Note the simulated instant of each encoder reading: the simulator steps every
        ``[sim] step_period_s``, so a reading can be up to one step older than the clock."""
        robot, clock = self.robot, self.clock
        if robot.encoders is None:
            raise RuntimeError("the simulated robot has no encoders to tap (mazebot.sim.backend sets them)")

        def note(reading: EncoderReading) -> None:
            self.readings.append((clock.now_s(), robot.time_s if robot.time_s is not None else clock.now_s()))

        robot.encoders.on_read += (note,)

    def sim_time_of(self, pose_s: float) -> float:
        """The simulated instant the encoder reading of clock time ``pose_s`` showed."""
        for clock_s, sim_s in reversed(self.readings):
            if clock_s <= pose_s:
                return sim_s - clock_s + pose_s
        return pose_s

    async def recorder(self) -> None:
        """The estimated and the true pose, every ``RECORD_PERIOD_S``."""
        state, record, clock = self.state, self.record, self.clock
        while True:
            # the estimate against the truth at the instant it describes: state.pose is
            # SLAM's correction composed with the odometry reading of state.pose_time_s, and
            # that reading shows the simulated world as it was at its last step
            now_s = clock.now_s()
            pose_s = state.pose_time_s if state.pose_time_s is not None else now_s
            x, y, th = self.robot.poses.at(np.array([min(self.sim_time_of(pose_s), now_s)]))
            record.times_s.append(pose_s - record.start_s)
            record.true_poses.append((float(x[0]), float(y[0]), float(th[0])))
            p = state.pose
            record.est_poses.append((p.x_m, p.y_m, p.theta_rad))
            await clock.sleep(RECORD_PERIOD_S)

    async def explore(self) -> None:
        """Press start as the user would, then wait for the planner to say done."""
        state, record, clock = self.state, self.record, self.clock
        await clock.sleep(1.0)  # the lidar spins up and SLAM publishes its first map
        state.commands.put_nowait("start")
        if record.faults is not None:
            await record.faults.user(state, clock)
            record.done = state.run_state is RunState.DONE
            return
        while state.run_state not in (RunState.DONE, RunState.FAULT):
            await clock.sleep(0.2)
        record.done = state.run_state is RunState.DONE

    async def drive_then_stop(self) -> None:
        """Drive (or explore) until done or ``max_sim_s``, then stop the daemon."""
        driver, record = self.record.driver, self.record
        period_s = self.config.daemon.control_period_s
        run = driver.run(self.state, self.clock, period_s) if driver is not None else self.explore()
        with contextlib.suppress(TimeoutError):  # out of time: done stays False
            await asyncio.wait_for(run, self.spec.max_sim_s)
        if driver is not None:
            record.done = driver.done
        record.end_s = self.clock.now_s()
        if record.faults is not None:
            record.faults.finish(self.state, self.supervisor, self.clock)
        self.supervisor.request_stop("benchmark run finished")


def compute_metrics(spec: RunSpec, record: RunRecord, *, exit_code: int, wall_s: float, cpu_s: float) -> dict[str, Any]:
    """The per-run keys of results.json."""
    hw, state = record.hardware, record.state
    assert hw is not None and state is not None
    robot = simulated_robot(hw)
    layout = robot.world.maze
    truth = np.asarray(record.true_poses, dtype=float).reshape(-1, 3)
    est = np.asarray(record.est_poses, dtype=float).reshape(-1, 3)
    start = tuple(truth[0]) if len(truth) else robot.world.start_pose
    truth_rel = relative_poses(start, truth) if len(truth) else truth
    err_xy = np.hypot(*(est[:, :2] - truth_rel[:, :2]).T) if len(truth) else np.zeros(0)
    err_th = np.remainder(est[:, 2] - truth_rel[:, 2] + np.pi, 2 * np.pi) - np.pi if len(truth) else np.zeros(0)
    time_s = record.end_s - record.start_s
    path_m = robot.physics.odometer_m
    lateness = np.asarray(state.control_lateness_ms, dtype=float)
    fault = state.active_fault
    scan_ms = np.asarray(state.scan_ms, dtype=float)
    maps = map_metrics(state.map, robot.world, start, robot.config.robot.footprint_radius_m)
    turn = turn_about_start(est[:, :2], truth_rel[:, :2]) if len(truth) else None
    slam = state.slam
    return {
        "maze": spec.name,
        "seed": spec.seed,
        "drive": spec.drive,
        "clock": spec.clock,
        "cells": int(layout.width * layout.height) if layout is not None else None,
        "done": record.done and exit_code == 0,
        "exit_code": exit_code,
        "fault": None if fault is None else f"{fault.source}: {fault.message}",
        "time_s": round(time_s, 2),
        "wall_s": round(wall_s, 2),
        "realtime_factor": round(time_s / wall_s, 1) if wall_s > 0 else None,
        "path_m": round(path_m, 3),
        "avg_speed_mps": round(path_m / time_s, 3) if time_s > 0 else None,
        # the fraction of the reachable free area the map knows as free
        "coverage": maps["coverage"],
        # the reachable free space the coverage misses: on cells the map holds occupied, or unknown
        "uncovered_occupied": maps["uncovered_occupied"],
        "uncovered_unknown": maps["uncovered_unknown"],
        "collisions": int(robot.physics.collisions),
        "revisits": count_revisits(layout, truth[:, :2]) if layout is not None else None,
        # the back-tracking a depth-first tour of every cell (and back to the start) cannot
        # avoid: its cell entries beyond the first; ``revisits`` above it is the excess
        "revisits_dfs": len(dfs_tour(layout)) - len(set(dfs_tour(layout))) if layout is not None else None,
        "ate_rms_m": round(float(np.sqrt(np.mean(err_xy**2))), 4) if len(err_xy) else None,
        "ate_max_m": round(float(err_xy.max()), 4) if len(err_xy) else None,
        "heading_rms_deg": round(float(np.degrees(np.sqrt(np.mean(err_th**2)))), 3) if len(err_th) else None,
        # the ATE split: the estimate's turn about the start as a whole, and the RMS left without it
        "ate_turn_about_start_deg": round(math.degrees(turn[0]), 3) if turn is not None else None,
        "ate_rms_turned_back_m": round(turn[1], 4) if turn is not None else None,
        "estimate": "slam",  # what produced the pose estimate the ATE measures
        # walls of the estimated map against the true walls (one-cell tolerance)
        "map_f1": maps["map_f1"],
        "map_precision": maps["map_precision"],
        "map_recall": maps["map_recall"],
        # SLAM's CPU time per scan (filter + ICP + grid; loop closure runs in an executor)
        "scan_ms_p50": round(float(np.percentile(scan_ms, 50)), 3) if len(scan_ms) else None,
        "scan_ms_p99": round(float(np.percentile(scan_ms, 99)), 3) if len(scan_ms) else None,
        "slam_scans": slam.scans,
        "slam_scans_dropped": slam.scans_dropped,
        "keyframes": slam.keyframes,
        "loop_closures": slam.loop_closures,
        "loop_closures_rejected": slam.loop_closures_rejected,
        "false_loop_closures": false_closures(slam.closures, robot.trajectory),
        "map_rebuilds": slam.map_rebuilds,
        # lateness of control ticks is only meaningful on the real clock
        "control_jitter_ms_p99": round(float(np.percentile(lateness, 99)), 3)
        if spec.clock == "real" and len(lateness)
        else None,
        "cpu_percent": round(100.0 * cpu_s / wall_s, 1) if wall_s > 0 else None,
        "rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1),
        "lidar_revolutions": state.sensors.lidar_revolutions,
        "lidar_bytes_dropped": state.sensors.lidar_bytes_dropped,
        "encoder_invalid_transitions": state.sensors.encoder_invalid_transitions,
        # injected faults, measured from the simulation's ground truth (mazebot.bench.fault_metrics)
        "faults": fault_metrics(record, exit_code) if record.faults is not None else None,
        # CPU per part of the daemon over the run (mazebot.cpu_budget): ms per robot-second, ms per call
        "cpu_budget": state.cpu.table(time_s),
    }
