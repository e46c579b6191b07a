"""Thread CPU of one correlative search (table + branch and bound), with the settings SLAM uses.

Three cases, each over many scans, the guess off by up to the window:

- ``maze``: the ``[slam]`` defaults (3 cm table, ±0.12 m / ±20°, points within 4 m), a
  simulated A1 revolution in a generated 6×6 maze against the true walls seen from a
  nearby pose (one revolution's worth of points, as the local submap has);
- ``laser``: :func:`mazebot.slam.slam_cli.laser_log_params`' sequential search (5 cm, ±0.5 m
  / ±30°, 10 m) on Intel-log scans against the six scans before them;
- ``loop``: the same logs' loop-closure window (±1.5 m / ±0.2 rad, five levels).

Prints the median and 90th percentile of each part (thread CPU, ms) and the median table
lookups (what the search did, whatever the CPU). Run:
``MAZEBOT_DATA=/work/shared/data .venv/bin/python bench/correlative_cost.py``.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from mazebot.config import load_config
from mazebot.geometry import transform_points as transform
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.raycast import cast_rays
from mazebot.sim.world import world_from_layout
from mazebot.slam.carmen import read_carmen
from mazebot.slam.correlative import CorrelativeParams, LikelihoodTable, correlative_match, select_points
from mazebot.slam.slam import SlamParams
from mazebot.slam.slam_cli import laser_log_params


def _measure(name: str, s: CorrelativeParams, pairs: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> None:
    rng = np.random.default_rng(0)
    tables, searches, lookups = [], [], []
    for reference_xy, source_xy, truth in pairs:
        guess = truth + np.array([*rng.uniform(-s.window_xy_m, s.window_xy_m, 2),
                                  rng.uniform(-s.window_theta_rad, s.window_theta_rad)])
        c0 = time.thread_time()
        crop = (guess[:2], s.max_range_m + s.window_xy_m + 3.0 * s.sigma_m + 0.5)
        table = LikelihoodTable(reference_xy, s.resolution_m, s.sigma_m, s.levels, crop=crop)
        c1 = time.thread_time()
        found = correlative_match(table, select_points(source_xy, None, s), guess, s.window_xy_m, s.window_theta_rad)
        c2 = time.thread_time()
        tables.append(c1 - c0)
        searches.append(c2 - c1)
        lookups.append(found.lookups)
    total = np.array(tables) + np.array(searches)
    print(f"{name}: {len(pairs)} calls; table {1e3 * np.median(tables):.2f} ms, "
          f"search {1e3 * np.median(searches):.2f} ms, total median {1e3 * np.median(total):.2f} ms "
          f"(p90 {1e3 * np.percentile(total, 90):.2f}); "
          f"lookups median {int(np.median(lookups))}")


def maze_pairs(count: int = 40) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    world = world_from_layout(generate_maze(6, 6, seed=3, kind="braided"), 0.012)
    assert world.maze is not None
    rng = np.random.default_rng(1)
    angles = np.linspace(-np.pi, np.pi, 400, endpoint=False)
    out = []
    for _ in range(count):
        cell = (int(rng.integers(world.maze.width)), int(rng.integers(world.maze.height)))
        x, y = world.maze.cell_center_m(cell)
        ref_pose = np.array([x, y, rng.uniform(-np.pi, np.pi)])
        truth = ref_pose + np.array([0.03, -0.02, 0.1])
        scans = []
        for pose in (ref_pose, truth):
            r = cast_rays(pose[:2], angles + pose[2], world.segments, world.circles, 12.0)
            r = r * (1.0 + 0.01 * rng.standard_normal(r.shape))
            ok = np.isfinite(r) & (r > 0.15)
            scans.append(np.column_stack((r[ok] * np.cos(angles[ok]), r[ok] * np.sin(angles[ok]))))
        out.append((transform(ref_pose, scans[0]), scans[1], truth))
    return out


def intel_pairs(path: Path) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    lasers = read_carmen(path).lasers
    out = []
    for k in range(20, len(lasers) - 1, 20):
        reference = np.vstack([transform(r.pose, r.points_xy(30.0)) for r in lasers[k - 5 : k + 1]])
        out.append((reference, lasers[k + 1].points_xy(30.0), lasers[k + 1].pose))
    return out


def main() -> None:
    config = load_config(None)
    maze = SlamParams.from_config(config.slam, config.lidar)
    assert maze.correlative is not None and maze.loop.search is not None
    _measure("maze sequential", maze.correlative, maze_pairs())
    _measure("maze loop closure", maze.loop.search, maze_pairs())
    log = Path(os.environ.get("MAZEBOT_DATA", "data")) / "carmen" / "intel.gfs.log"
    if not log.is_file():
        print(f"{log} not found: laser-log figures skipped")
        return
    laser = laser_log_params(maze)
    assert laser.correlative is not None and laser.loop.search is not None
    pairs = intel_pairs(log)
    _measure("laser log sequential", laser.correlative, pairs)
    _measure("laser log loop closure", laser.loop.search, pairs)


if __name__ == "__main__":
    main()
