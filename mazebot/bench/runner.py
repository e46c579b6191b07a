"""One benchmark run: the whole daemon on a simulated robot, on virtual time, measured.

The run uses ``main.run_daemon`` with the simulator's hardware builder, exactly as
``mazebot run --sim`` does, minus the web server; the benchmark adds two tasks of its
own: the driver (``--drive scripted`` follows a ground-truth tour) and a recorder that
samples the estimated pose (SLAM's, ``state.pose``) ten times a second with the true pose
at the instant the estimate describes: the simulated time shown by the encoder reading
behind it (``state.pose_time_s``; the simulator steps every ``[sim] step_period_s``, so
that is up to one step before the reading).
Metrics that need a part the daemon does not have yet are ``None`` (``null`` in
results.json), never guessed.

Map metrics compare SLAM's final grid with the world, after moving it into the world
frame with the true start pose (the map frame is the robot's start pose):

- ``coverage``: the share of the reachable free cells (:func:`mazebot.sim.raster.free_reachable`
  at the map's resolution) whose map cell is known free (three-state);
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
from typing import Any

import numpy as np

from mazebot.bench.fault_metrics import RECOVERY_WINDOW_S, FaultRecord, fault_metrics
from mazebot.bench.scripted_drive import ScriptedDriver, dfs_tour, straighten
from mazebot.bench.virtual_executor import CpuTimedExecutor
from mazebot.clock import RealClock
from mazebot.config import Config
from mazebot.errors import UsageError
from mazebot.main import Hardware, run_daemon
from mazebot.sim.backend import sim_hardware_builder
from mazebot.sim.faults import FaultInjector, FaultSpec
from mazebot.sim.virtual_time import SlowCpu, run_virtual
from mazebot.state import RunState, SharedState
from mazebot.tasks.supervisor import Supervisor

RECORD_PERIOD_S = 0.1
#: A loop closure this far from the true relative pose is counted as false (a maze cell is 0.3 m).
FALSE_CLOSURE_M = 0.1
FALSE_CLOSURE_RAD = 0.1
#: Cells of the map metrics' truth raster beyond the world's bounds on every side.
MARGIN_CELLS = 2


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


def _relative(base: tuple[float, float, float], poses: np.ndarray) -> np.ndarray:
    """Poses expressed in the frame of ``base`` (the robot's start: the map frame)."""
    bx, by, bt = base
    c, s = math.cos(bt), math.sin(bt)
    dx, dy = poses[:, 0] - bx, poses[:, 1] - by
    out = np.empty_like(poses)
    out[:, 0] = c * dx + s * dy
    out[:, 1] = -s * dx + c * dy
    out[:, 2] = np.remainder(poses[:, 2] - bt + np.pi, 2 * np.pi) - np.pi
    return out


#: How far (metres) the robot must be inside a cell before :func:`_revisits` counts an entry.
REVISIT_DEPTH_M = 0.03


def _revisits(layout: Any, xy: np.ndarray, depth_m: float = REVISIT_DEPTH_M) -> int:
    """Cell entries beyond the first visit of each cell, from the true trajectory.

    An entry counts once the robot's centre is more than ``depth_m`` inside the new cell
    (hysteresis): a robot following a corridor's centre line sways a centimetre or two,
    and where it passes close to a cell border (turning a corner, braking at a cell
    centre) every sway across the border would otherwise count as leaving and
    re-entering a cell, which is no back-tracking at all.
    """
    seen: set[tuple[int, int]] = set()
    last = None
    count = 0
    half_m = 0.5 * layout.cell_size_m
    for x, y in xy:
        cell = layout.cell_at(float(x), float(y))
        if cell is None or cell == last:
            continue
        cx, cy = layout.cell_center_m(cell)
        if half_m - max(abs(float(x) - cx), abs(float(y) - cy)) <= depth_m:
            continue  # at the border: not in the new cell yet
        if cell in seen:
            count += 1
        seen.add(cell)
        last = cell
    return count


def _to_world(start: tuple[float, float, float], xy: np.ndarray) -> np.ndarray:
    """Map-frame points (N, 2) in the world frame, the map frame being the start pose."""
    c, s = math.cos(start[2]), math.sin(start[2])
    return np.column_stack((start[0] + c * xy[:, 0] - s * xy[:, 1], start[1] + s * xy[:, 0] + c * xy[:, 1]))


def map_metrics(grid: Any, world: Any, start: tuple[float, float, float], footprint_radius_m: float) -> dict[str, Any]:
    """``coverage`` and ``map_f1`` (with precision and recall) of SLAM's grid against the world."""
    from scipy import ndimage

    from mazebot.sim.raster import free_reachable, true_occupancy

    if grid is None or grid.shape[0] == 0:
        return {"coverage": None, "map_f1": None, "map_precision": None, "map_recall": None}
    res = grid.resolution_m
    # the truth raster reaches MARGIN_CELLS beyond the world's bounds: a map cell on the outer
    # wall whose centre lies just outside them is within the one-cell tolerance, not off the grid
    bounds, bounds_origin = true_occupancy(world, res)
    bounds_shape = bounds.shape
    origin = (bounds_origin[0] - MARGIN_CELLS * res, bounds_origin[1] - MARGIN_CELLS * res)
    shape = (bounds_shape[0] + 2 * MARGIN_CELLS, bounds_shape[1] + 2 * MARGIN_CELLS)
    truth, origin = true_occupancy(world, res, origin, shape)
    reach, _ = free_reachable(world, res, footprint_radius_m, origin, truth.shape)
    rows, cols = truth.shape
    # coverage: look every reachable cell centre up in the map
    rr, cc = np.nonzero(reach)
    centres = np.column_stack((origin[0] + (cc + 0.5) * res, origin[1] + (rr + 0.5) * res))
    c, s = math.cos(start[2]), math.sin(start[2])
    dx, dy = centres[:, 0] - start[0], centres[:, 1] - start[1]
    in_map = np.column_stack((c * dx + s * dy, -s * dx + c * dy))
    mr, mc = grid.to_cell(in_map)
    inside = (mr >= 0) & (mr < grid.shape[0]) & (mc >= 0) & (mc < grid.shape[1])
    free = grid.known_free_mask()
    known = np.zeros(len(mr), dtype=bool)
    known[inside] = free[mr[inside], mc[inside]]
    coverage = float(known.sum() / max(1, len(known)))
    # walls: the map's occupied cells rasterized into the world grid
    er, ec = np.nonzero(grid.occupied_mask())
    est_xy = _to_world(start, grid.to_world(er, ec))
    wc = np.floor((est_xy[:, 0] - origin[0]) / res).astype(int)
    wr = np.floor((est_xy[:, 1] - origin[1]) / res).astype(int)
    on = (wr >= 0) & (wr < rows) & (wc >= 0) & (wc < cols)
    est = np.zeros_like(truth)
    est[wr[on], wc[on]] = True
    near = ndimage.generate_binary_structure(2, 2)  # one cell, diagonals included
    truth_near = ndimage.binary_dilation(truth, near)
    precision = float(truth_near[wr[on], wc[on]].sum() / max(1, len(er)))  # off-grid cells are false
    visible = truth & ndimage.binary_dilation(reach, near, iterations=2)
    recall = float((visible & ndimage.binary_dilation(est, near)).sum() / max(1, visible.sum()))
    f1 = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return {
        "coverage": round(coverage, 4),
        "map_f1": round(f1, 4),
        "map_precision": round(precision, 4),
        "map_recall": round(recall, 4),
    }


def false_closures(closures: list, trajectory: list[tuple[float, float, float, float]]) -> int:
    """Accepted loop closures whose relative pose disagrees with the true trajectory."""
    if not closures or len(trajectory) < 2:
        return 0
    traj = np.asarray(trajectory, dtype=float)
    t, th = traj[:, 0], np.unwrap(traj[:, 3])

    def true_pose(time_s: float) -> np.ndarray:
        return np.array([np.interp(time_s, t, traj[:, 1]), np.interp(time_s, t, traj[:, 2]), np.interp(time_s, t, th)])

    count = 0
    for old_s, new_s, z in closures:
        a, b = true_pose(old_s), true_pose(new_s)
        c, s = math.cos(a[2]), math.sin(a[2])
        d = b[:2] - a[:2]
        rel = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], math.remainder(b[2] - a[2], math.tau)])
        err_t = math.hypot(rel[0] - z[0], rel[1] - z[1])
        err_r = abs(math.remainder(rel[2] - z[2], math.tau))
        count += err_t > FALSE_CLOSURE_M or err_r > FALSE_CLOSURE_RAD
    return count


def _instrument(
    spec: RunSpec, injector: FaultInjector | None, record: RunRecord
) -> Callable[[Any, Executor], Executor] | None:
    """The ``run_daemon`` hook: on virtual time the lost-robot search takes its CPU time
    (:mod:`mazebot.bench.virtual_executor`); the fault injector reaches SLAM and its executor."""
    if spec.clock != "virtual":
        return injector.instrument if injector is not None else None

    def instrument(slam: Any, executor: Executor) -> Executor:
        timed = record.executor = CpuTimedExecutor(executor, asyncio.get_running_loop())
        return injector.instrument(slam, timed) if injector is not None else timed

    return instrument


def run_one(config: Config, spec: RunSpec) -> tuple[dict[str, Any], RunRecord]:
    """Run one simulated mission and return its metrics and the raw record (for figures)."""
    if spec.drive not in ("scripted", "explore"):
        raise UsageError(f"--drive must be scripted or explore, got {spec.drive!r}")
    config = config.model_copy(deep=True)
    config.sim.seed = spec.seed
    config.sim.world = spec.world  # type: ignore[assignment]
    config.daemon.exit_on_fault = not spec.faults
    if spec.faults:  # the run must survive them and go on by itself once they clear
        config.daemon.auto_resume = True
    record = RunRecord()
    clock = RealClock()
    period_s = config.daemon.control_period_s
    injector = FaultInjector(list(spec.faults), None, clock, seed=spec.seed) if spec.faults else None
    if injector is not None:
        record.faults = FaultRecord(injector, recovery_window_s=spec.recovery_window_s)

    def on_started(hardware: Hardware, state: SharedState, supervisor: Supervisor) -> None:
        robot = hardware.sim
        layout = robot.world.maze
        driver: ScriptedDriver | None = None
        if spec.drive == "scripted":
            if layout is None:
                raise UsageError(f"--drive scripted needs a maze world, {robot.world.name} has no cells")
            tour = straighten(dfs_tour(layout))
            driver = ScriptedDriver(
                [layout.cell_center_m(c) for c in tour[1:]],
                robot.physics,
                speed_mps=config.drive.max_speed_mps * 0.8,
                yaw_rate_radps=config.drive.max_yaw_rate_radps * 0.8,
                track_width_m=config.drive.track_width_m,
                full_throttle_mps=config.drive.max_wheel_speed_mps,
                deadband=config.sim.deadband,
            )
        record.hardware, record.state, record.driver = hardware, state, driver
        record.start_s = clock.now_s()

        # Which simulated instant each encoder reading shows: the simulator steps every
        # [sim] step_period_s, so a reading can be up to one step older than the clock.
        readings: deque[tuple[float, float]] = deque(maxlen=64)  # (clock time, sim time)
        read_encoders = hardware.encoders.read

        def read_and_note() -> Any:
            reading = read_encoders()
            readings.append((clock.now_s(), robot.time_s if robot.time_s is not None else clock.now_s()))
            return reading

        hardware.encoders.read = read_and_note
        if injector is not None:
            injector.ctx.robot = robot
            assert record.faults is not None
            record.faults.watch(robot, state, supervisor, clock)
            supervisor.start("bench-faults", injector.run)

        def sim_time_of(pose_s: float) -> float:
            for clock_s, sim_s in reversed(readings):
                if clock_s <= pose_s:
                    return sim_s - clock_s + pose_s
            return pose_s

        async def recorder() -> None:
            while True:
                # the estimate against the truth at the instant it describes: state.pose is
                # SLAM's correction composed with the odometry reading of state.pose_time_s, and
                # that reading shows the simulated world as it was at its last step
                now_s = clock.now_s()
                pose_s = state.pose_time_s if state.pose_time_s is not None else now_s
                x, y, th = robot.poses.at(np.array([min(sim_time_of(pose_s), now_s)]))
                record.times_s.append(pose_s - record.start_s)
                record.true_poses.append((float(x[0]), float(y[0]), float(th[0])))
                p = state.pose
                record.est_poses.append((p.x_m, p.y_m, p.theta_rad))
                await clock.sleep(RECORD_PERIOD_S)

        async def explore() -> None:
            """Press start as the user would, then wait for the planner to say done."""
            await clock.sleep(1.0)  # the lidar spins up and SLAM publishes its first map
            state.commands.put_nowait("start")
            if record.faults is not None:
                await record.faults.user(state, clock)
                record.done = state.run_state is RunState.DONE
                return
            while state.run_state not in (RunState.DONE, RunState.FAULT):
                await clock.sleep(0.2)
            record.done = state.run_state is RunState.DONE

        async def drive_then_stop() -> None:
            run = driver.run(state, clock, period_s) if driver is not None else explore()
            with contextlib.suppress(TimeoutError):  # out of time: done stays False
                await asyncio.wait_for(run, spec.max_sim_s)
            if driver is not None:
                record.done = driver.done
            record.end_s = clock.now_s()
            if record.faults is not None:
                record.faults.finish(state, supervisor, clock)
            supervisor.request_stop("benchmark run finished")

        supervisor.start("bench-recorder", recorder)
        supervisor.start("bench-driver", drive_then_stop)

    builder = sim_hardware_builder(maze_path=spec.maze_path, seed=spec.seed if not spec.maze_path else None,
                                   size=spec.size if not spec.maze_path else None)
    wall0, cpu0 = time.perf_counter(), time.process_time()
    session = None
    if spec.record_path:
        from pathlib import Path

        from mazebot.persist.session import RunSession

        session = RunSession(record_path=Path(spec.record_path))
    daemon = run_daemon(
        config, builder, serve_web=False, install_signal_handlers=False, on_started=on_started, session=session,
        autonomous=spec.drive == "explore", instrument=_instrument(spec, injector, record),
    )
    if spec.slow is not None and spec.clock != "virtual":
        raise UsageError("a slowed CPU is emulated on the virtual clock only; use --clock virtual")
    exit_code = run_virtual(daemon, slow=spec.slow) if spec.clock == "virtual" else asyncio.run(daemon)
    wall_s = time.perf_counter() - wall0
    cpu_s = time.process_time() - cpu0
    metrics = compute_metrics(spec, record, exit_code=exit_code, wall_s=wall_s, cpu_s=cpu_s)
    return metrics, record


def compute_metrics(spec: RunSpec, record: RunRecord, *, exit_code: int, wall_s: float, cpu_s: float) -> dict[str, Any]:
    """The per-run keys of results.json."""
    hw, state = record.hardware, record.state
    assert hw is not None and state is not None
    robot = hw.sim
    layout = robot.world.maze
    truth = np.asarray(record.true_poses, dtype=float).reshape(-1, 3)
    est = np.asarray(record.est_poses, dtype=float).reshape(-1, 3)
    start = tuple(truth[0]) if len(truth) else robot.world.start_pose
    truth_rel = _relative(start, truth) if len(truth) else truth
    err_xy = np.hypot(*(est[:, :2] - truth_rel[:, :2]).T) if len(truth) else np.zeros(0)
    err_th = np.remainder(est[:, 2] - truth_rel[:, 2] + np.pi, 2 * np.pi) - np.pi if len(truth) else np.zeros(0)
    time_s = record.end_s - record.start_s
    path_m = robot.physics.odometer_m
    lateness = np.asarray(state.control_lateness_ms, dtype=float)
    fault = state.active_fault
    scan_ms = np.asarray(state.scan_ms, dtype=float)
    maps = map_metrics(state.map, robot.world, start, robot.config.robot.footprint_radius_m)
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
        "collisions": int(robot.physics.collisions),
        "revisits": _revisits(layout, truth[:, :2]) if layout is not None else None,
        # the back-tracking a depth-first tour of every cell (and back to the start) cannot
        # avoid: its cell entries beyond the first; ``revisits`` above it is the excess
        "revisits_dfs": len(dfs_tour(layout)) - len(set(dfs_tour(layout))) if layout is not None else None,
        "ate_rms_m": round(float(np.sqrt(np.mean(err_xy**2))), 4) if len(err_xy) else None,
        "ate_max_m": round(float(err_xy.max()), 4) if len(err_xy) else None,
        "heading_rms_deg": round(float(np.degrees(np.sqrt(np.mean(err_th**2)))), 3) if len(err_th) else None,
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
