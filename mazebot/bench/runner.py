"""One benchmark run: the whole daemon on a simulated robot, on virtual time, measured.

The run uses ``main.run_daemon`` with the simulator's hardware builder, exactly as
``mazebot run --sim`` does, minus the web server; the benchmark adds two tasks of its
own: the driver (``--drive scripted`` follows a ground-truth tour) and a recorder that
samples the true and the estimated pose ten times a second. Metrics that need a part
the daemon does not have yet are ``None`` (``null`` in results.json), never guessed.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import resource
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mazebot.bench.scripted_drive import ScriptedDriver, dfs_tour, straighten
from mazebot.clock import RealClock
from mazebot.config import Config
from mazebot.errors import UsageError
from mazebot.main import Hardware, run_daemon
from mazebot.sim.backend import sim_hardware_builder
from mazebot.sim.virtual_time import run_virtual
from mazebot.state import SharedState
from mazebot.tasks.supervisor import Supervisor

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

    @property
    def name(self) -> str:
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
    start_s: float = 0.0
    end_s: float = 0.0


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


def _revisits(layout: Any, xy: np.ndarray) -> int:
    """Cell entries beyond the first visit of each cell, from the true trajectory."""
    seen: set[tuple[int, int]] = set()
    last = None
    count = 0
    for x, y in xy:
        cell = layout.cell_at(float(x), float(y))
        if cell is None or cell == last:
            continue
        if cell in seen:
            count += 1
        seen.add(cell)
        last = cell
    return count


def run_one(config: Config, spec: RunSpec) -> tuple[dict[str, Any], RunRecord]:
    """Run one simulated mission and return its metrics and the raw record (for figures)."""
    if spec.drive != "scripted":
        raise UsageError(
            "--drive explore needs the autonomous planner, which mazebot does not have yet; use --drive scripted"
        )
    config = config.model_copy(deep=True)
    config.sim.seed = spec.seed
    config.daemon.exit_on_fault = True
    record = RunRecord()
    clock = RealClock()
    period_s = config.daemon.control_period_s

    def on_started(hardware: Hardware, state: SharedState, supervisor: Supervisor) -> None:
        robot = hardware.sim
        layout = robot.world.maze
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

        async def recorder() -> None:
            while True:
                record.times_s.append(clock.now_s() - record.start_s)
                record.true_poses.append(robot.physics.pose)
                p = state.pose
                record.est_poses.append((p.x_m, p.y_m, p.theta_rad))
                await clock.sleep(RECORD_PERIOD_S)

        async def drive_then_stop() -> None:
            with contextlib.suppress(TimeoutError):  # out of time: done stays False
                await asyncio.wait_for(driver.run(state, clock, period_s), spec.max_sim_s)
            record.end_s = clock.now_s()
            supervisor.request_stop("benchmark run finished")

        supervisor.start("bench-recorder", recorder)
        supervisor.start("bench-driver", drive_then_stop)

    builder = sim_hardware_builder(maze_path=spec.maze_path, seed=spec.seed if not spec.maze_path else None,
                                   size=spec.size if not spec.maze_path else None)
    wall0, cpu0 = time.perf_counter(), time.process_time()
    daemon = run_daemon(config, builder, serve_web=False, install_signal_handlers=False, on_started=on_started)
    exit_code = run_virtual(daemon) if spec.clock == "virtual" else asyncio.run(daemon)
    wall_s = time.perf_counter() - wall0
    cpu_s = time.process_time() - cpu0
    metrics = compute_metrics(spec, record, exit_code=exit_code, wall_s=wall_s, cpu_s=cpu_s)
    return metrics, record


def compute_metrics(spec: RunSpec, record: RunRecord, *, exit_code: int, wall_s: float, cpu_s: float) -> dict[str, Any]:
    """The per-run keys of results.json."""
    hw, state, driver = record.hardware, record.state, record.driver
    assert hw is not None and state is not None and driver is not None
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
    return {
        "maze": spec.name,
        "seed": spec.seed,
        "drive": spec.drive,
        "clock": spec.clock,
        "cells": int(layout.width * layout.height) if layout is not None else None,
        "done": bool(driver.done) and exit_code == 0,
        "exit_code": exit_code,
        "fault": None if fault is None else f"{fault.source}: {fault.message}",
        "time_s": round(time_s, 2),
        "wall_s": round(wall_s, 2),
        "realtime_factor": round(time_s / wall_s, 1) if wall_s > 0 else None,
        "path_m": round(path_m, 3),
        "avg_speed_mps": round(path_m / time_s, 3) if time_s > 0 else None,
        # the fraction of the reachable free area the map knows correctly: needs the map
        "coverage": None,
        "collisions": int(robot.physics.collisions),
        "revisits": _revisits(layout, truth[:, :2]) if layout is not None else None,
        "ate_rms_m": round(float(np.sqrt(np.mean(err_xy**2))), 4) if len(err_xy) else None,
        "ate_max_m": round(float(err_xy.max()), 4) if len(err_xy) else None,
        "heading_rms_deg": round(float(np.degrees(np.sqrt(np.mean(err_th**2)))), 3) if len(err_th) else None,
        "estimate": "odometry",  # what produced the pose estimate the ATE measures
        # walls of the estimated map against the true walls: needs the map
        "map_f1": None,
        # SLAM's per-scan time: needs SLAM
        "scan_ms_p50": None,
        "scan_ms_p99": None,
        # lateness of control ticks is only meaningful on the real clock
        "control_jitter_ms_p99": round(float(np.percentile(lateness, 99)), 3)
        if spec.clock == "real" and len(lateness)
        else None,
        "cpu_percent": round(100.0 * cpu_s / wall_s, 1) if wall_s > 0 else None,
        "rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1),
        "lidar_revolutions": state.sensors.lidar_revolutions,
        "lidar_bytes_dropped": state.sensors.lidar_bytes_dropped,
        "encoder_invalid_transitions": state.sensors.encoder_invalid_transitions,
    }
