"""Where the map's walls are too wide: which reachable free cells a real run misses, and why.

Runs one benchmark mission (the whole daemon, virtual time), keeps SLAM's keyframes,
and compares maps with the truth raster the ``coverage`` metric uses
(:func:`mazebot.sim.raster.free_reachable`):

- the final live map (what ``coverage`` scores);
- the keyframes rebuilt at SLAM's own final poses (the map after a loop closure);
- the same after the rotation and translation that fit SLAM's keyframe positions best
  to the truth: what is lost between this and the previous line is the map's global
  placement (a rotation of the whole map about the start), not its sharpness;
- the keyframes rebuilt at the *true* poses: whatever is still missed there is the
  grid's inverse sensor model (range noise, hit/miss balance), not pose error.

For each map it prints coverage, the missed cells by distance of their centre to the
nearest wall surface and by map state, and F1. ``--dump FILE`` keeps the run (keyframes,
true trajectory, world) for ``--load FILE`` so grid settings can be tried without
re-running the simulator.

    .venv/bin/python tools/map_sharpness.py --seed 20 --drive explore --dump /tmp/seed20.pkl
    .venv/bin/python tools/map_sharpness.py --load /tmp/seed20.pkl
"""

from __future__ import annotations

import argparse
import itertools
import math
from typing import Any

import numpy as np
from kept_run import add_keep_options, kept_or_new

from mazebot.bench.runner import RunSpec, map_metrics, run_one
from mazebot.config import load_config
from mazebot.sim.raster import free_reachable, true_occupancy
from mazebot.sim.raycast import distance_to_obstacles
from mazebot.slam.slam import GridParams, Slam, SlamUpdated


def run_and_capture(seed: int, drive: str, size: int, config_path: str | None = None) -> dict[str, Any]:
    """One mission; returns the keyframes, the true trajectory, the world and the final grid."""
    captured: list[Slam] = []
    scans: list[dict[str, Any]] = []

    def updated(seen: SlamUpdated) -> None:
        out, m = seen.update, seen.update.match
        scans.append({
            "time_s": out.time_s, "pose": out.pose.copy(), "matched": out.matched,
            "match_pose": None if m is None else m.pose.copy(),
            "fitness": None if m is None else m.fitness, "rmse_m": None if m is None else m.rmse_m,
            "converged": None if m is None else m.converged,
            "offset_s": seen.slam.time_offset.offset_s, "keyframe": out.keyframe,
        })

    def watch(slam: Slam) -> None:
        slam.taps.on_update += (updated,)
        captured.append(slam)

    config = load_config(config_path)
    metrics, record = run_one(config, RunSpec(None, (size, size), seed, drive), watch_slam=watch)
    slam = captured[-1]
    robot = record.hardware.sim
    keyframes = [
        {
            "time_s": kf.time_s,
            "pose": kf.pose.copy(),
            "ray_ends": kf.ray_ends.copy(),
            "ray_hit": kf.ray_hit.copy(),
            "sensor_xy": kf.sensor_xy.copy(),
        }
        for kf in slam.keyframes
    ]
    truth = np.asarray(record.true_poses, dtype=float).reshape(-1, 3)
    return {
        "metrics": metrics,
        "scans": scans,
        "keyframes": keyframes,
        "trajectory": np.asarray(robot.trajectory, dtype=float),
        "start": tuple(truth[0]),
        "world": robot.world,
        "grid": record.state.map,
        "footprint_m": robot.config.robot.footprint_radius_m,
    }


def true_keyframe_poses(run: dict[str, Any], shift_s: float = 0.0) -> np.ndarray:
    """Each keyframe's true pose in the map frame (the robot's start pose), ``shift_s`` after its stamp."""
    traj = run["trajectory"]
    t, th = traj[:, 0], np.unwrap(traj[:, 3])
    times = np.array([kf["time_s"] for kf in run["keyframes"]]) + shift_s
    x, y, a = np.interp(times, t, traj[:, 1]), np.interp(times, t, traj[:, 2]), np.interp(times, t, th)
    bx, by, bt = run["start"]
    c, s = math.cos(bt), math.sin(bt)
    dx, dy = x - bx, y - by
    return np.column_stack((c * dx + s * dy, -s * dx + c * dy, np.remainder(a - bt + np.pi, 2 * np.pi) - np.pi))


def stamp_shift_s(run: dict[str, Any]) -> float:
    """The time shift of the truth that best explains the keyframes' headings (least heading variance).

    A keyframe's pose belongs to the instant its de-skewed points show, which differs from
    its stamp by the lidar/odometry time offsets (the simulated encoders lag the world by
    up to one simulator step); in turns that shows as a heading error proportional to the
    turn rate, which says nothing about the map.
    """
    est = np.array([kf["pose"] for kf in run["keyframes"]])
    best = (math.inf, 0.0)
    for shift in np.arange(-0.03, 0.03, 0.0005):
        err = np.remainder(est[:, 2] - true_keyframe_poses(run, shift)[:, 2] + np.pi, 2 * np.pi) - np.pi
        best = min(best, (float(np.var(err)), float(shift)))
    return best[1]


def rigid_fit(est: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, float]:
    """``est`` moved by the rotation and translation that fit its positions best to ``truth`` (Kabsch)."""
    a, b = est[:, :2], truth[:, :2]
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ma).T @ (b - mb))
    rot = vt.T @ u.T
    angle = math.atan2(rot[1, 0], rot[0, 0])
    out = est.copy()
    out[:, :2] = (rot @ (a - ma).T).T + mb
    out[:, 2] += angle
    return out, angle


def rebuild(run: dict[str, Any], poses: np.ndarray, grid_params: GridParams) -> Any:
    grid = grid_params.new_grid()
    rays = []
    for kf, pose in zip(run["keyframes"], poses, strict=True):
        ends = kf["ray_ends"].astype(np.float64)
        rays.append((pose, ends, kf["ray_hit"], np.broadcast_to(kf["sensor_xy"], ends.shape)))
    grid.rebuild(rays)
    return grid


def missed_cells(run: dict[str, Any], grid: Any) -> None:
    """Print the reachable free cells the map does not know as free, by wall distance and state."""
    world, start = run["world"], run["start"]
    res = grid.resolution_m
    truth, origin = true_occupancy(world, res)
    reach, _ = free_reachable(world, res, run["footprint_m"], origin, truth.shape)
    rr, cc = np.nonzero(reach)
    centres = np.column_stack((origin[0] + (cc + 0.5) * res, origin[1] + (rr + 0.5) * res))
    c, s = math.cos(start[2]), math.sin(start[2])
    dx, dy = centres[:, 0] - start[0], centres[:, 1] - start[1]
    mr, mc = grid.to_cell(np.column_stack((c * dx + s * dy, -s * dx + c * dy)))
    inside = (mr >= 0) & (mr < grid.shape[0]) & (mc >= 0) & (mc < grid.shape[1])
    state = np.full(len(mr), -1, dtype=int)
    state[inside] = grid.three_state()[mr[inside], mc[inside]]
    dist = distance_to_obstacles(centres, world)
    miss = state != 0
    print(f"  reachable {len(state)}, missed {int(miss.sum())} "
          f"(occupied {int((state == 100).sum())}, unknown {int((state == -1).sum())})")
    # the cells touching a wall, by the gap between the cell's edge and the face (centre distance - half a cell)
    band = dist < res
    gaps_mm = np.round((dist[band] - res / 2) * 1000).astype(int)
    for gap in np.unique(gaps_mm):
        at = gaps_mm == gap
        if at.sum() >= 20:
            missed = int(miss[band][at].sum())
            print(f"  face {gap} mm behind the cell edge: {int(at.sum()):4d} cells, missed {missed:4d}")
    edges = [0.0, 0.01, 0.02, 0.03, 0.04, 0.06, 1.0]
    for lo, hi in itertools.pairwise(edges):
        band = (dist >= lo) & (dist < hi)
        print(f"  centre {lo * 100:.0f}-{hi * 100:.0f} cm from a wall: {int(band.sum()):5d} cells, "
              f"missed {int((band & miss).sum()):4d} (occupied {int((band & (state == 100)).sum())}, "
              f"unknown {int((band & (state == -1)).sum())})")


def report(run: dict[str, Any], name: str, grid: Any) -> None:
    m = map_metrics(grid, run["world"], run["start"], run["footprint_m"])
    print(f"{name}: coverage {m['coverage']}, F1 {m['map_f1']} (precision {m['map_precision']}, "
          f"recall {m['map_recall']})")
    missed_cells(run, grid)


def perfect_map(run: dict[str, Any], resolution_m: float = 0.02) -> Any:
    """The truth raster drawn in the map's own lattice: what a flawless SLAM would hand the metric.

    The map frame is the start pose, whose heading is a multiple of 90° in these worlds,
    so the map's cells are squares of the world lattice through the start position.
    """
    from mazebot.slam.grid import OccupancyGrid

    world, (sx, sy, st) = run["world"], run["start"]
    xmin, ymin, xmax, ymax = world.bounds_m
    ox = sx + math.floor((xmin - sx) / resolution_m) * resolution_m
    oy = sy + math.floor((ymin - sy) / resolution_m) * resolution_m
    shape = (math.ceil((ymax - oy) / resolution_m) + 1, math.ceil((xmax - ox) / resolution_m) + 1)
    truth, _ = true_occupancy(world, resolution_m, (ox, oy), shape)
    rows, cols = np.indices(shape)
    centres = np.column_stack((ox + (cols.ravel() + 0.5) * resolution_m, oy + (rows.ravel() + 0.5) * resolution_m))
    c, s = math.cos(st), math.sin(st)
    d = centres - np.array([sx, sy])
    in_map = np.column_stack((c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]))
    grid = OccupancyGrid(resolution_m=resolution_m)
    grid._ensure_contains(in_map)  # sized to the whole world
    r, q = grid.to_cell(in_map)
    grid.log_odds[...] = grid.l_min
    grid.log_odds[r, q] = np.where(truth.ravel(), grid.l_max, grid.l_min)
    return grid


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=20)
    ap.add_argument("--size", type=int, default=6)
    ap.add_argument("--drive", choices=("explore", "scripted"), default="explore")
    ap.add_argument("--config", help="config file (default: the usual search)")
    add_keep_options(ap)
    args = ap.parse_args()
    run = kept_or_new(args, lambda: run_and_capture(args.seed, args.drive, args.size, args.config))
    m = run["metrics"]
    print(f"run: coverage {m['coverage']}, F1 {m['map_f1']}, ATE rms {m['ate_rms_m']} max {m['ate_max_m']}, "
          f"keyframes {len(run['keyframes'])}")
    params = GridParams()
    report(run, "perfect map (the truth in the map's lattice)", perfect_map(run))
    report(run, "final live map", run["grid"])
    slam_poses = np.array([kf["pose"] for kf in run["keyframes"]])
    shift = stamp_shift_s(run)
    true_poses = true_keyframe_poses(run, shift)
    fitted, angle = rigid_fit(slam_poses, true_poses)
    for name, poses in (("as estimated", slam_poses), (f"after a rigid fit ({math.degrees(angle):.3f} deg)", fitted)):
        err = np.hypot(*(poses[:, :2] - true_poses[:, :2]).T)
        head = np.degrees(np.remainder(poses[:, 2] - true_poses[:, 2] + np.pi, 2 * np.pi) - np.pi)
        print(f"keyframe poses {name}: rms {np.sqrt(np.mean(err**2)):.4f} m, max {err.max():.4f} m, "
              f"heading rms {np.sqrt(np.mean(head**2)):.3f} deg (truth {shift * 1e3:.1f} ms after the stamps)")
    report(run, "keyframes at SLAM poses", rebuild(run, slam_poses, params))
    report(run, "keyframes at SLAM poses after the rigid fit", rebuild(run, fitted, params))
    report(run, "keyframes at true poses", rebuild(run, true_poses, params))

if __name__ == "__main__":
    main()
