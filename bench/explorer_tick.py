"""CPU time of the explorer's half of a planner tick (graph update, goal choice, route).

Run from the repository root::

    .venv/bin/python bench/explorer_tick.py --maze $MAZEBOT_DATA/mazes/training/test-zigzag-a.txt

The map is the maze's perfect three-state grid (2 cm, walls occupied, the reachable
inside free) with its east half hidden, so there is something left to explore and the
explorer does all of its work each tick: re-reads every link of the graph, searches
routes from the robot, breaks ties with more searches, and plans the route to the
target. The robot stands at the start. Printed: the median and p90 CPU time
(``time.process_time``) of :meth:`Explorer.update` over ``--ticks`` ticks, in several
rounds; compare two versions by running the script of each with ``PYTHONPATH``.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import numpy as np
from scipy import ndimage

from mazebot.planner.exploration import Explorer
from mazebot.sim.maze_file import parse_maze
from mazebot.sim.raster import true_occupancy
from mazebot.sim.world import world_from_layout

RES_M = 0.02
CELL_M = 0.3048


def half_known_map(maze_text: str) -> tuple[np.ndarray, tuple[float, float], tuple[float, float, float]]:
    """The perfect map of a maze with its east half unknown; grid, origin and the start pose."""
    world = world_from_layout(parse_maze(maze_text, CELL_M), 0.012)
    xmin, ymin, xmax, ymax = world.bounds_m
    margin_m = 0.3
    origin = (math.floor((xmin - margin_m) / RES_M) * RES_M, math.floor((ymin - margin_m) / RES_M) * RES_M)
    shape = (math.ceil((ymax + margin_m - origin[1]) / RES_M), math.ceil((xmax + margin_m - origin[0]) / RES_M))
    occupied, _ = true_occupancy(world, RES_M, origin, shape)
    labels, _ = ndimage.label(~occupied)
    x0, y0, _ = world.start_pose
    grid = np.full(shape, -1, dtype=np.int8)
    grid[labels == labels[int((y0 - origin[1]) / RES_M), int((x0 - origin[0]) / RES_M)]] = 0
    grid[occupied] = 100
    grid[:, shape[1] // 2 :] = -1
    return grid, origin, world.start_pose


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--maze", required=True, help="a maze text file")
    parser.add_argument("--ticks", type=int, default=50, help="explorer updates per round (default 50)")
    parser.add_argument("--rounds", type=int, default=5, help="rounds (default 5)")
    args = parser.parse_args()
    with open(args.maze, encoding="utf-8") as f:
        grid, origin, pose = half_known_map(f.read())
    samples_ms: list[float] = []
    for _ in range(args.rounds):
        explorer = Explorer(start_xy_m=pose[:2])
        explorer.update(grid, origin, RES_M, pose, 0.0)  # the first tick estimates the frame
        for k in range(args.ticks):
            cpu0 = time.process_time()
            explorer.update(grid, origin, RES_M, pose, 0.2 * (k + 1))
            samples_ms.append((time.process_time() - cpu0) * 1e3)
    samples_ms.sort()
    p90 = samples_ms[min(len(samples_ms) - 1, int(0.9 * len(samples_ms)))]
    print(f"explorer update CPU: median {statistics.median(samples_ms):.2f} ms, p90 {p90:.2f} ms "
          f"({len(samples_ms)} ticks)")


if __name__ == "__main__":
    main()
