"""Time the per-scan SLAM building blocks on synthetic maze scans.

Run from the repository root::

    .venv/bin/python bench/slam_steps_bench.py            # 300 scans, seed 1
    .venv/bin/python bench/slam_steps_bench.py --scans 500 --seed 2 --maze 16 --keyframes 32

Each scan is one 360-sample revolution cast in a generated maze (1 ft cells, 12 mm
walls) while the robot drives at 0.3 m/s and turns at up to 1 rad/s, with 1 % range
noise and 2 % dropouts, like the simulator's A1M8. Per scan the bench times:

- ``prepare``: range gate, impulse rejection, de-skew with the true poses, voxel downsampling;
- ``icp``: the prepared scan against a local submap (``Target``, ~2000 points) built
  from ``--keyframes`` (16) keyframes within two cells, 1 cm voxels, started 4 cm / 3
  degrees off;
- ``grid``: integrating the scan's beams into a 2 cm occupancy grid covering the maze;
- ``total``: the three together (docs/design.md, "Budgets": median <= 5 ms on this machine).

``target`` (building the kd-tree and normals of a submap) is timed apart, outside
``total``: SLAM does it once per keyframe, not once per scan. The table prints median and p99 in milliseconds,
and the ICP's accuracy against the true poses so a fast-but-wrong change shows up.
Wall-clock times (``time.perf_counter``) are what the budget means; the CPU-time column
(``time.process_time``) is steadier when other processes share the machine.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import numpy as np

from mazebot.io.scan import Scan
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.raycast import RayCaster
from mazebot.sim.world import World, world_from_layout
from mazebot.slam.grid import OccupancyGrid
from mazebot.slam.icp import Target, match_scan
from mazebot.slam.preprocess import PrepareParams, prepare_scan

SAMPLES = 360
PERIOD_S = 1.0 / 5.5


def _arc(start: np.ndarray, speed_mps: float, yaw_rate_radps: float, t0_s: float):
    """``pose_at_time`` of a constant-velocity arc that is at ``start`` at ``t0_s``."""

    def pose_at(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        dt = np.asarray(t, dtype=np.float64) - t0_s
        th = start[2] + yaw_rate_radps * dt
        if abs(yaw_rate_radps) < 1e-9:
            return start[0] + speed_mps * dt * np.cos(th), start[1] + speed_mps * dt * np.sin(th), th
        r = speed_mps / yaw_rate_radps
        return start[0] + r * (np.sin(th) - np.sin(start[2])), start[1] - r * (np.cos(th) - np.cos(start[2])), th

    return pose_at


def _scan(caster: RayCaster, pose_at, t0_s: float, rng: np.random.Generator) -> Scan:
    """One revolution sampled along the motion, 1 % range noise, 2 % dropouts."""
    times = t0_s + (np.arange(SAMPLES) + 1) * (PERIOD_S / SAMPLES)
    angles = np.linspace(-np.pi, np.pi, SAMPLES, endpoint=False)
    x, y, th = pose_at(times)
    ranges = caster.cast(np.column_stack((x, y)), angles + th, max_range_m=12.0)
    ranges = ranges * (1.0 + 0.01 * rng.standard_normal(SAMPLES))
    valid = np.isfinite(ranges) & (rng.random(SAMPLES) > 0.02)
    return Scan(
        angles,
        np.where(valid, ranges, 0.0),
        np.where(valid, 47, 0).astype(np.uint8),
        times,
        valid,
    )


def _keyframes(world: World, caster: RayCaster, centre: np.ndarray, rng: np.random.Generator, count: int) -> list:
    """Prepared scans at ``count`` spots within two cells of ``centre``: the keyframes of SLAM's local map."""
    assert world.maze is not None
    keyframes = []
    cell = world.maze.cell_at(centre[0], centre[1]) or (0, 0)
    while len(keyframes) < count:
        col = int(np.clip(cell[0] + rng.integers(-2, 3), 0, world.maze.width - 1))
        row = int(np.clip(cell[1] + rng.integers(-2, 3), 0, world.maze.height - 1))
        x, y = world.maze.cell_center_m((col, row))
        pose = np.array([x + rng.uniform(-0.05, 0.05), y + rng.uniform(-0.05, 0.05), rng.uniform(-np.pi, np.pi)])
        prepared = prepare_scan(_scan(caster, _arc(pose, 0.0, 0.0, 0.0), 0.0, rng), None)
        keyframes.append((pose, prepared.points_full, prepared.sensor_xy))
    return keyframes


SUBMAP_VOXEL_M = 0.01


def _stats(values_ms: list[float]) -> tuple[float, float]:
    ordered = sorted(values_ms)
    return statistics.median(ordered), ordered[min(len(ordered) - 1, math.ceil(0.99 * len(ordered)) - 1)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, default=300, help="scans to time (default 300)")
    parser.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    parser.add_argument("--maze", type=int, default=8, help="maze side in cells (default 8)")
    parser.add_argument("--keyframes", type=int, default=16, help="keyframes in the local submap (default 16)")
    args = parser.parse_args(argv)

    rng = np.random.default_rng(args.seed)
    world = world_from_layout(generate_maze(args.maze, args.maze, seed=args.seed, kind="braided"), 0.012)
    assert world.maze is not None
    caster = RayCaster.for_world(world)
    params = PrepareParams()
    grid = OccupancyGrid(resolution_m=0.02)
    xmin, ymin, xmax, ymax = world.bounds_m
    grid.integrate(np.array([xmin, ymin]), np.array([[xmax, ymax]]), np.array([True]))  # allocate once
    times: dict[str, list[float]] = {"prepare": [], "icp": [], "grid": [], "total": [], "target": []}
    cpu: dict[str, list[float]] = {name: [] for name in times}
    err_mm, err_deg, points, submap_points, iterations = [], [], [], [], []

    for i in range(args.scans):
        x, y = world.maze.cell_center_m((int(rng.integers(world.maze.width)), int(rng.integers(world.maze.height))))
        start = np.array([x + rng.uniform(-0.05, 0.05), y + rng.uniform(-0.05, 0.05), rng.uniform(-np.pi, np.pi)])
        pose_at = _arc(start, 0.3, rng.uniform(-1.0, 1.0), 0.0)
        scan = _scan(caster, pose_at, 0.0, rng)
        end = np.array([float(v[0]) for v in pose_at(np.array([scan.end_time_s]))])
        # the local map around this pose (SLAM rebuilds it once per keyframe, not per scan)
        keyframes = _keyframes(world, caster, end, rng, args.keyframes)
        t, c = time.perf_counter(), time.process_time()
        local = Target.from_scans(keyframes, voxel_size_m=SUBMAP_VOXEL_M)
        times["target"].append((time.perf_counter() - t) * 1e3)
        cpu["target"].append((time.process_time() - c) * 1e3)
        submap_points.append(len(local))
        guess = end + np.array([0.04 * math.cos(i), 0.04 * math.sin(i), math.radians(3.0)])

        t0, c0 = time.perf_counter(), time.process_time()
        prepared = prepare_scan(scan, pose_at, params)
        t1, c1 = time.perf_counter(), time.process_time()
        result = match_scan(local, prepared.points_match, guess, sensor_xy=prepared.sensor_xy)
        t2, c2 = time.perf_counter(), time.process_time()
        beams = prepared.beams_world(result.pose)
        grid.integrate(beams.sensor_pose, beams.endpoints, beams.hit, beams.origins)
        t3, c3 = time.perf_counter(), time.process_time()

        for name, a, b, ca, cb in (("prepare", t0, t1, c0, c1), ("icp", t1, t2, c1, c2), ("grid", t2, t3, c2, c3)):
            times[name].append((b - a) * 1e3)
            cpu[name].append((cb - ca) * 1e3)
        times["total"].append((t3 - t0) * 1e3)
        cpu["total"].append((c3 - c0) * 1e3)
        iterations.append(result.iterations)
        points.append((len(scan), prepared.points_full.shape[0], prepared.points_match.shape[0]))
        err_mm.append(1e3 * float(np.hypot(*(result.pose[:2] - end[:2]))))
        err_deg.append(abs(math.degrees(math.remainder(result.pose[2] - end[2], math.tau))))

    pts = np.array(points)
    print(f"slam steps bench: {args.scans} scans, {args.maze}x{args.maze} maze, seed {args.seed}")
    print(
        f"scan: {pts[:, 0].mean():.0f} samples, {pts[:, 1].mean():.0f} kept, {pts[:, 2].mean():.0f} for matching; "
        f"submap {np.mean(submap_points):.0f} points"
    )
    print(f"{'step':<10}{'median ms':>11}{'p99 ms':>9}{'cpu median ms':>15}")
    for name in ("prepare", "icp", "grid", "total", "target"):
        med, p99 = _stats(times[name])
        print(f"{name:<10}{med:>11.2f}{p99:>9.2f}{statistics.median(cpu[name]):>15.2f}")
    print(
        f"icp error vs truth: median {statistics.median(err_mm):.1f} mm, p99 {np.percentile(err_mm, 99):.1f} mm, "
        f"median {statistics.median(err_deg):.2f} deg; {statistics.median(iterations):.0f} iterations (median)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
