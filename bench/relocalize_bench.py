"""Time the lost-robot guard: its check of every revolution, and a search for a kidnapped robot.

Run from the repository root::

    .venv/bin/python bench/relocalize_bench.py

SLAM maps the start cell of a generated 6x6 maze while the robot turns on the spot
(22 revolutions, 0.5 % range noise), then the robot is put down 0.2 m away, turned
by 20°, and the odometry knows nothing of it. Timed, in thread CPU time:

- ``check``: :meth:`LocalizationGuard.check` of one revolution (de-skew by the odometry,
  look-up of each checked hit's neighbourhood in the grid): paid on every revolution;
- ``search``: :func:`search_pose` (correlative grid, then ICP of the best few): paid
  only when the robot is lost, in the SLAM executor.

The search's error against the true pose is printed too, so a fast but wrong change shows.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from mazebot.geometry import compose, relative_pose, wrap_angle
from mazebot.io.scan import Scan
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.raycast import cast_rays
from mazebot.sim.world import world_from_layout
from mazebot.slam.ekf import OdometryHistory
from mazebot.slam.relocalize import LocalizationGuard, search_pose
from mazebot.slam.slam import Slam, SlamParams

PERIOD_S = 1 / 5.5


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checks", type=int, default=500)
    parser.add_argument("--searches", type=int, default=10)
    args = parser.parse_args()
    world = world_from_layout(generate_maze(6, 6, seed=3, kind="braided"), 0.012)
    start = np.asarray(world.start_pose)

    def scan_at(pose: np.ndarray, t0_s: float, seed: int) -> Scan:
        n = 360
        times = t0_s + (np.arange(n) + 1) * (PERIOD_S / n)
        angles = np.linspace(-np.pi, np.pi, n, endpoint=False)
        ranges = cast_rays(np.tile(pose[:2], (n, 1)), angles + pose[2], world.segments, world.circles, 12.0)
        ranges = ranges * (1 + 0.005 * np.random.default_rng(seed).standard_normal(n))
        valid = np.isfinite(ranges)
        return Scan(angles, np.where(valid, ranges, 0.0), np.where(valid, 47, 0).astype(np.uint8), times, valid)

    slam = Slam(SlamParams(), background=False, record_trajectory=False)
    history = OdometryHistory(horizon_s=60.0)
    history.append(0.0, 0.0, 0.0, 0.0)
    t = 0.0
    for k in range(22):
        scan = scan_at(compose(start, np.array([0.0, 0.0, 0.05 * k])), t, k)
        t += PERIOD_S
        history.append(t, 0.0, 0.0, 0.05 * k)
        slam.update(scan, history)
    heading = 0.05 * 21
    here = compose(start, np.array([0.0, 0.0, heading]))
    kidnapped = compose(here, np.array([0.2 * math.cos(-heading), 0.2 * math.sin(-heading), math.radians(20)]))
    scan = scan_at(kidnapped, t, 99)
    history.append(t + PERIOD_S, 0.0, 0.0, heading)
    guard = LocalizationGuard()
    checks = []
    for _ in range(args.checks):
        t0 = time.thread_time()
        guard.check(slam, scan, history)
        checks.append(time.thread_time() - t0)
    searches = []
    for _ in range(args.searches):
        t0 = time.thread_time()
        found = search_pose(slam, scan, history, guard.guess, guard.params)
        searches.append(time.thread_time() - t0)
    truth = relative_pose(start, kidnapped)
    assert found.pose is not None, "the search found nothing"
    err_m = math.hypot(*(found.pose[:2] - truth[:2]))
    err_deg = abs(math.degrees(wrap_angle(found.pose[2] - truth[2])))
    print("| step | median ms | p99 ms |")
    print("|---|---:|---:|")
    for name, values in (("check (every revolution)", checks), ("search (when lost)", searches)):
        print(f"| {name} | {1e3 * np.median(values):.2f} | {1e3 * np.percentile(values, 99):.2f} |")
    print(f"\nsearch error against the true pose: {1e3 * err_m:.1f} mm, {err_deg:.2f}°; "
          f"contradiction at the odometry's pose {100 * guard.last_fit.contradiction:.0f} %")


if __name__ == "__main__":
    main()
