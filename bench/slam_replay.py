"""Replay the scans and odometry SLAM saw in one simulated run, for repeatable SLAM timing.

A virtual-time run of the whole daemon is a function of its seed, except where SLAM's
loop-closure jobs land (they run in an executor, on the wall clock). To time SLAM alone
and to check that a speed-up leaves its output unchanged, capture what SLAM was given in
one run, then replay it as often as wanted with every loop-closure job run and applied
at once after the update that made it::

    .venv/bin/python bench/slam_replay.py capture --seed 2 --out /tmp/seed2.pkl
    .venv/bin/python bench/slam_replay.py replay /tmp/seed2.pkl [--repeat 3]

A capture also keeps the run's true poses: ``replay`` then prints the live estimate's
error against them (ATE RMS / max, heading RMS, as ``mazebot bench`` computes them).
``--latency-s 1.0`` merges each loop-closure job a simulated second after it was made,
as the bench's virtual-time runs do (the replay then gives the captured run's ATE), and
``--set slam.KEY=VALUE`` tries another setting on the same data.

``replay`` prints the thread CPU of the per-scan updates and of the loop-closure jobs
(total and median, the minimum over ``--repeat`` passes) and a digest of SLAM's output
(keyframe poses, closures, the grid's log odds): two code versions that print the same
digest computed the same map.
"""

from __future__ import annotations

import argparse
import hashlib
import math
import pickle
import statistics
import time
import tomllib
from typing import Any

import numpy as np

from mazebot.bench.cli import SIM_S_PER_CELL
from mazebot.bench.metrics import relative_poses
from mazebot.bench.runner import RunSpec, run_one
from mazebot.config import load_config, parse_config
from mazebot.slam.ekf import OdometryHistory
from mazebot.slam.slam import Slam, SlamParams, SlamUpdated


class FrozenOdometry:
    """The odometry history as it was when SLAM asked for it (the same interpolation)."""

    def __init__(self, live: np.ndarray) -> None:
        self.live = live

    def at(self, times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t, live = self.live[:, 0], self.live
        times = np.asarray(times_s, dtype=np.float64)
        return np.interp(times, t, live[:, 1]), np.interp(times, t, live[:, 2]), np.interp(times, t, live[:, 3])


def capture(seed: int, size: int, out: str, drive: str = "scripted") -> None:
    config = load_config(None)
    max_sim_s = max(900.0, SIM_S_PER_CELL * size * size)  # as ``mazebot bench --size``
    frames: list[tuple[Any, np.ndarray]] = []

    def captured(seen: SlamUpdated) -> None:
        # SLAM reads the odometry (up to the revolution's end) in its first stage; the history
        # as it stands when the update ends interpolates those times the same way
        assert isinstance(seen.odometry, OdometryHistory)
        frames.append((seen.scan, seen.odometry.since(-math.inf)))

    def watch(slam: Slam) -> None:
        slam.taps.on_update += (captured,)

    spec = RunSpec(None, (size, size), seed, drive, max_sim_s=max_sim_s)
    metrics, record = run_one(config, spec, watch_slam=watch)
    true_poses = np.asarray(record.true_poses, dtype=float).reshape(-1, 3)
    truth = {  # the true poses in the map frame (the start's), on the daemon's clock
        "times_s": np.asarray(record.times_s, dtype=float) + record.start_s,
        "poses": relative_poses(tuple(true_poses[0]), true_poses),
    }
    keys = ("done", "time_s", "ate_rms_m", "ate_max_m", "heading_rms_deg", "map_f1", "loop_closures")
    bench = {key: metrics[key] for key in keys}
    with open(out, "wb") as f:
        pickle.dump({"seed": seed, "size": size, "frames": frames, "truth": truth, "bench": bench}, f)
    print(f"{len(frames)} scans over {metrics['time_s']:.1f} s simulated written to {out}; the run's {bench}")


def replay_once(
    frames: list[tuple[Any, np.ndarray]], config: Any, latency_s: float = 0.0
) -> tuple[list[float], list[float], Slam, np.ndarray]:
    """SLAM over the frames; each loop-closure job merged ``latency_s`` after the update that made it.

    Returns the per-scan and per-job thread CPU, the SLAM, and its live estimates
    ``(time_s, x, y, theta)`` after every update (what the daemon publishes).
    """
    params = SlamParams.from_config(config.slam, config.lidar, config.planner)
    slam = Slam(params, background=True, record_trajectory=False)
    update_s, job_s, estimates = [], [], []
    pending: tuple[float, Any] | None = None  # (merge time, result) of the job in flight
    for scan, live in frames:
        if pending is not None and scan.end_time_s >= pending[0]:
            slam.apply(pending[1])
            pending = None
        start = time.thread_time()
        update = slam.update(scan, FrozenOdometry(live))
        update_s.append(time.thread_time() - start)
        estimates.append((update.time_s, *update.pose))
        if update.loop_job is not None:
            start = time.thread_time()
            result = update.loop_job.run()
            job_s.append(time.thread_time() - start)
            if latency_s > 0:
                pending = (update.time_s + latency_s, result)
            else:
                slam.apply(result)
    return update_s, job_s, slam, np.asarray(estimates, dtype=float).reshape(-1, 4)


def trajectory_error(estimates: np.ndarray, truth: dict[str, np.ndarray]) -> dict[str, float]:
    """ATE RMS / max (m) and heading RMS (degrees) of the live estimates against the true poses."""
    t = truth["times_s"]
    true = truth["poses"]
    inside = (estimates[:, 0] >= t[0]) & (estimates[:, 0] <= t[-1])
    est = estimates[inside]
    x = np.interp(est[:, 0], t, true[:, 0])
    y = np.interp(est[:, 0], t, true[:, 1])
    th = np.interp(est[:, 0], t, np.unwrap(true[:, 2]))
    err = np.hypot(est[:, 1] - x, est[:, 2] - y)
    err_th = np.remainder(est[:, 3] - th + np.pi, 2 * np.pi) - np.pi
    return {
        "ate_rms_mm": float(np.sqrt(np.mean(err**2)) * 1e3),
        "ate_max_mm": float(err.max() * 1e3),
        "heading_rms_deg": float(np.degrees(np.sqrt(np.mean(err_th**2)))),
    }


def digest(slam: Slam) -> str:
    h = hashlib.sha256()
    h.update(np.round(slam.keyframe_poses(), 9).tobytes())
    h.update(repr([(c.old, c.new) for c in slam.closures]).encode())
    h.update(slam.grid.log_odds.tobytes())
    return h.hexdigest()[:16]


def configured(settings: list[str]) -> Any:
    """The default config with ``section.key=value`` settings (TOML values, nested sections dotted) applied."""
    data: dict[str, Any] = {}
    for setting in settings:
        name, _, text = setting.partition("=")
        *path, key = name.split(".")
        if not path or not text:
            raise SystemExit(f"--set wants section.key=value, got {setting!r}")
        table = data
        for part in path:
            table = table.setdefault(part, {})
        table[key] = tomllib.loads(f"v = {text}")["v"]
    return parse_config(data, "--set")


def replay(path: str, repeat: int, latency_s: float, settings: list[str]) -> None:
    with open(path, "rb") as f:
        data = pickle.load(f)
    config = configured(settings)
    best_update, best_job = float("inf"), float("inf")
    for _ in range(repeat):
        update_s, job_s, slam, estimates = replay_once(data["frames"], config, latency_s)
        if sum(update_s) + sum(job_s) < best_update + best_job:
            best_update, best_job = sum(update_s), sum(job_s)
            medians = (statistics.median(update_s) * 1e3, statistics.median(job_s) * 1e3 if job_s else 0.0)
            jobs = len(job_s)
    print(
        f"seed {data['seed']}: {len(data['frames'])} scans, updates {best_update:.2f} s CPU "
        f"(median {medians[0]:.2f} ms), {jobs} loop-closure jobs {best_job:.2f} s CPU (median {medians[1]:.1f} ms); "
        f"{len(slam.keyframes)} keyframes, {len(slam.closures)} closures, digest {digest(slam)}"
    )
    if "truth" in data:
        error = trajectory_error(estimates, data["truth"])
        print(
            f"  live estimate against the truth: ATE RMS {error['ate_rms_mm']:.1f} mm, "
            f"max {error['ate_max_mm']:.1f} mm, heading RMS {error['heading_rms_deg']:.3f} deg "
            f"(the captured run's bench figures: {data['bench']})"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    cap = sub.add_parser("capture", help="run a scripted tour (or an exploration) and save what SLAM was given")
    cap.add_argument("--seed", type=int, default=2)
    cap.add_argument("--size", type=int, default=6, help="maze cells per side (default 6)")
    cap.add_argument("--drive", choices=("scripted", "explore"), default="scripted",
                     help="the scripted tour (default) or an exploration, as the daemon's quota bench drives")
    cap.add_argument("--out", required=True)
    rep = sub.add_parser("replay", help="run SLAM over a capture")
    rep.add_argument("path")
    rep.add_argument("--repeat", type=int, default=1, help="passes; the fastest is printed")
    rep.add_argument("--latency-s", type=float, default=0.0,
                     help="merge each loop-closure job this long (scan time) after it was made; "
                     "0: at once (the digest's reference); the daemon's bench uses 1.0")
    rep.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                     help="a config value for the replayed SLAM (TOML syntax), e.g. slam.keyframes.submap_keyframes=30")
    args = parser.parse_args()
    if args.command == "capture":
        capture(args.seed, args.size, args.out, args.drive)
    else:
        replay(args.path, args.repeat, args.latency_s, args.set)


if __name__ == "__main__":
    main()
