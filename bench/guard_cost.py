"""Thread CPU of one emergency-stop check (``CollisionGuard.check``) on revolutions of a 16×16 maze.

Usage: ``python bench/guard_cost.py [--poses 300] [--commands 20] [--maze FILE]``; to time
another copy of the code, put it first on ``PYTHONPATH`` (the script imports whichever
``mazebot`` comes first).

The control loop calls the guard every control tick (20 Hz; on the Pi in the control
process) with the latest revolution's returns and the command about to be applied. The
scenes: robot poses drawn in the free space of a contest maze (alljapan-015 by default),
from 0.095 m off a wall (the footprint plus half the side margin) to a cell's centre, any
heading; a revolution of 360 returns from each (an A1 in standard mode: ~2000 samples/s at
5.5 rev/s), ray cast, 3 mm of range noise, the A1's 0.15 m minimum range. Each pose is
checked against ``--commands`` commands drawn like the planner's: DWA arcs forwards (60 %),
turns in place (15 %), the recovery's straight back-off (10 %) and tight arcs forwards or
back (15 %). Each call is timed alone (``time.thread_time_ns``); the median and p99 per call
and the share of calls that stopped are printed. The guard is the control loop's, built
from the default configuration.
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np

from mazebot.config import Config
from mazebot.sim.maze_file import read_maze_layout
from mazebot.sim.raycast import RayCaster, distance_to_obstacles
from mazebot.sim.world import world_from_layout
from mazebot.tasks.control_task import MotorControl


def commands(rng: np.random.Generator, n: int) -> list[tuple[float, float]]:
    """``n`` body velocities (v m/s, w rad/s) drawn like the planner's mix (see the module docstring)."""
    out = []
    for kind in rng.choice(4, size=n, p=(0.6, 0.15, 0.1, 0.15)):
        if kind == 0:
            out.append((float(rng.uniform(0.03, 0.3)), float(rng.uniform(-1.2, 1.2))))
        elif kind == 1:
            out.append((0.0, float(rng.choice((-1.0, 1.0)) * rng.uniform(0.4, 1.2))))
        elif kind == 2:
            out.append((-0.06, 0.0))
        else:
            out.append((float(rng.choice((-1.0, 1.0)) * rng.uniform(0.01, 0.1)), float(rng.choice((-1.2, 1.2)))))
    return out


def main() -> None:
    data = os.environ.get("MAZEBOT_DATA", "/work/shared/data")
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--maze", default=f"{data}/mazes/classic/alljapan-015-1994-frsh.txt")
    parser.add_argument("--poses", type=int, default=300)
    parser.add_argument("--commands", type=int, default=20)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()

    config = Config()
    guard = MotorControl.from_config(config).safety.guard
    world = world_from_layout(read_maze_layout(args.maze))
    caster = RayCaster.for_world(world)
    rng = np.random.default_rng(args.seed)
    x0, y0, x1, y1 = world.bounds_m
    angles = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    lo, hi = config.lidar.min_range_m, config.lidar.max_range_m
    half_cell = 0.5 * 0.3048
    scenes = []
    while len(scenes) < args.poses:
        xy = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
        clear = float(distance_to_obstacles(xy[None, :], world)[0])
        if not guard.footprint_radius_m + 0.005 <= clear <= half_cell:
            continue
        heading = float(rng.uniform(-math.pi, math.pi))
        ranges = caster.cast(xy, angles + heading, hi) + rng.normal(0.0, 0.003, angles.size)
        ok = np.isfinite(ranges) & (ranges >= lo) & (ranges <= hi)
        points = np.column_stack((ranges[ok] * np.cos(angles[ok]), ranges[ok] * np.sin(angles[ok])))
        scenes.append(points)

    times_ns, stops = [], 0
    for points in scenes:
        for v, w in commands(rng, args.commands):
            start = time.thread_time_ns()
            verdict = guard.check(points, v, w)
            times_ns.append(time.thread_time_ns() - start)
            stops += verdict.stop
    t = np.array(times_ns) / 1e3
    print(f"{len(t)} calls on {len(scenes)} revolutions of {np.mean([len(s) for s in scenes]):.0f} returns: "
          f"median {np.median(t):.1f} µs, p99 {np.percentile(t, 99):.1f} µs, mean {t.mean():.1f} µs a call; "
          f"{stops} stopped ({100 * stops / len(t):.1f} %)")


if __name__ == "__main__":
    main()
