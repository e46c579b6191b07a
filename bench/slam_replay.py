"""Replay the scans and odometry SLAM saw in one simulated run, for repeatable SLAM timing.

A virtual-time run of the whole daemon is a function of its seed, except where SLAM's
loop-closure jobs land (they run in an executor, on the wall clock). To time SLAM alone
and to check that a speed-up leaves its output unchanged, capture what SLAM was given in
one run, then replay it as often as wanted with every loop-closure job run and applied
at once after the update that made it::

    .venv/bin/python bench/slam_replay.py capture --seed 2 --out /tmp/seed2.pkl
    .venv/bin/python bench/slam_replay.py replay /tmp/seed2.pkl [--repeat 3]

``replay`` prints the thread CPU of the per-scan updates and of the loop-closure jobs
(total and median, the minimum over ``--repeat`` passes) and a digest of SLAM's output
(keyframe poses, closures, the grid's log odds): two code versions that print the same
digest computed the same map.
"""

from __future__ import annotations

import argparse
import hashlib
import pickle
import statistics
import time
from typing import Any

import numpy as np

from mazebot.bench.runner import RunSpec, run_one
from mazebot.config import load_config
from mazebot.slam import slam as slam_module
from mazebot.slam.slam import Slam, SlamParams


class FrozenOdometry:
    """The odometry history as it was when SLAM asked for it (the same interpolation)."""

    def __init__(self, live: np.ndarray) -> None:
        self.live = live

    def at(self, times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t, live = self.live[:, 0], self.live
        times = np.asarray(times_s, dtype=np.float64)
        return np.interp(times, t, live[:, 1]), np.interp(times, t, live[:, 2]), np.interp(times, t, live[:, 3])


def capture(seed: int, size: int, out: str) -> None:
    config = load_config(None)
    frames: list[tuple[Any, np.ndarray]] = []
    real_update = slam_module.Slam.update_steps  # what the SLAM task calls

    def update(self: Slam, scan: Any, odometry: Any, **kwargs: Any) -> Any:
        frames.append((scan, odometry._buf[odometry._start : odometry._end].copy()))
        return (yield from real_update(self, scan, odometry, **kwargs))

    slam_module.Slam.update_steps = update  # type: ignore[method-assign]
    try:
        metrics, _ = run_one(config, RunSpec(None, (size, size), seed, "scripted"))
    finally:
        slam_module.Slam.update_steps = real_update  # type: ignore[method-assign]
    with open(out, "wb") as f:
        pickle.dump({"seed": seed, "size": size, "frames": frames}, f)
    print(f"{len(frames)} scans over {metrics['time_s']:.1f} s simulated written to {out}")


def replay_once(frames: list[tuple[Any, np.ndarray]]) -> tuple[list[float], list[float], Slam]:
    params = SlamParams.from_config(load_config(None).slam, load_config(None).lidar)
    slam = Slam(params, background=True, record_trajectory=False)
    update_s, job_s = [], []
    for scan, live in frames:
        start = time.thread_time()
        update = slam.update(scan, FrozenOdometry(live))
        update_s.append(time.thread_time() - start)
        if update.loop_job is not None:
            start = time.thread_time()
            result = update.loop_job.run()
            slam.apply(result)
            job_s.append(time.thread_time() - start)
    return update_s, job_s, slam


def digest(slam: Slam) -> str:
    h = hashlib.sha256()
    h.update(np.round(slam.keyframe_poses(), 9).tobytes())
    h.update(repr([(c.old, c.new) for c in slam.closures]).encode())
    h.update(slam.grid.log_odds.tobytes())
    return h.hexdigest()[:16]


def replay(path: str, repeat: int) -> None:
    with open(path, "rb") as f:
        data = pickle.load(f)
    best_update, best_job = float("inf"), float("inf")
    for _ in range(repeat):
        update_s, job_s, slam = replay_once(data["frames"])
        if sum(update_s) + sum(job_s) < best_update + best_job:
            best_update, best_job = sum(update_s), sum(job_s)
            medians = (statistics.median(update_s) * 1e3, statistics.median(job_s) * 1e3 if job_s else 0.0)
            jobs = len(job_s)
    print(
        f"seed {data['seed']}: {len(data['frames'])} scans, updates {best_update:.2f} s CPU "
        f"(median {medians[0]:.2f} ms), {jobs} loop-closure jobs {best_job:.2f} s CPU (median {medians[1]:.1f} ms); "
        f"{len(slam.keyframes)} keyframes, {len(slam.closures)} closures, digest {digest(slam)}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    cap = sub.add_parser("capture", help="run a scripted tour and save what SLAM was given")
    cap.add_argument("--seed", type=int, default=2)
    cap.add_argument("--size", type=int, default=6, help="maze cells per side (default 6)")
    cap.add_argument("--out", required=True)
    rep = sub.add_parser("replay", help="run SLAM over a capture")
    rep.add_argument("path")
    rep.add_argument("--repeat", type=int, default=1, help="passes; the fastest is printed")
    args = parser.parse_args()
    if args.command == "capture":
        capture(args.seed, args.size, args.out)
    else:
        replay(args.path, args.repeat)


if __name__ == "__main__":
    main()
