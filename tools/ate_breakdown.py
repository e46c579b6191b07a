"""Where a scripted tour's ATE comes from: late corrections, a turned map, or drift baked into the graph.

Runs one benchmark mission (the whole daemon, virtual time) with a SLAM that records
every scan's filter pose and every merged loop-closure job, then compares with the truth:

- the **live** estimate (what the bench's ``ate_rms_m`` scores, 10 Hz);
- the **final optimized** trajectory (every scan's pose relative to its keyframe, on the
  keyframes' final poses): if it is as far off as the live estimate, the error is not
  late loop closures but in the pose graph itself;
- the final trajectory after the **rigid** fit (rotation + translation) and the
  **similarity** fit (plus scale) to the truth: what a turned or scaled map explains;
- the **anchor**: keyframe 0's averaged wall direction (the truth is 0 for a start on
  the grid) against the keyframes' mean heading error (the map turns with the anchor);
- a timeline (live and final error, merges, closures per 50 s) and the largest jumps of
  the filter pose at a merge.

``--dump FILE`` keeps the run for ``--load FILE``.

    .venv/bin/python tools/ate_breakdown.py --size 16 --seed 13 --dump /tmp/s13.pkl
"""

from __future__ import annotations

import argparse
import math
from typing import Any

import numpy as np
from kept_run import add_keep_options, kept_or_new

from mazebot.bench.runner import RunSpec, run_one
from mazebot.config import load_config
from mazebot.slam.slam import Slam, SlamApplied, SlamUpdated


def run_and_capture(seed: int, size: int, maze: str | None) -> dict[str, Any]:
    """One scripted mission; returns the truth, the live estimate, per-scan poses, merges, keyframes."""
    captured: list[Slam] = []
    scans: list[tuple[float, np.ndarray]] = []
    merges: list[dict[str, Any]] = []
    last_pose: list[np.ndarray] = []  # the filter's pose after the last update or merge

    def updated(seen: SlamUpdated) -> None:
        scans.append((seen.update.time_s, seen.update.pose.copy()))
        last_pose[:] = [seen.update.pose.copy()]

    def applied(seen: SlamApplied) -> None:
        after = seen.slam.pose
        jump_m = float(np.hypot(*(after - last_pose[0])[:2])) if last_pose else 0.0
        last_pose[:] = [after]
        merges.append({"time_s": scans[-1][0] if scans else 0.0, "jump_m": jump_m,
                       "accepted": sum(v.accepted for v in seen.result.verdicts)})

    def watch(slam: Slam) -> None:
        slam.record_trajectory = True  # the final trajectory follows the optimized keyframes
        slam.taps.on_update += (updated,)
        slam.taps.on_apply += (applied,)
        captured.append(slam)

    spec = RunSpec(maze, None if maze else (size, size), seed, "scripted",
                   max_sim_s=3600.0 if maze else max(900.0, 14.0 * size * size))
    metrics, record = run_one(load_config(None), spec, watch_slam=watch)
    slam = captured[-1]
    final_t, final_poses = slam.trajectory()
    return {
        "metrics": metrics,
        "start_s": record.start_s,
        "live_t": np.asarray(record.times_s), "live_true": np.asarray(record.true_poses),
        "live_est": np.asarray(record.est_poses),
        "trajectory": np.asarray(record.hardware.sim.trajectory, dtype=float),
        "final_t": final_t, "final": final_poses,
        "keyframe_t": np.array([kf.time_s for kf in slam.keyframes]), "keyframes": slam.keyframe_poses(),
        "merges": merges, "anchor_wall_rad": slam.anchor_wall_rad,
    }


def _wrap(a: np.ndarray) -> np.ndarray:
    return np.remainder(a + np.pi, 2 * np.pi) - np.pi


def _in_start_frame(start: np.ndarray, poses: np.ndarray) -> np.ndarray:
    c, s = math.cos(start[2]), math.sin(start[2])
    d = poses[:, :2] - start[:2]
    return np.column_stack((c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], _wrap(poses[:, 2] - start[2])))


def truth_at(run: dict[str, Any], times_s: np.ndarray) -> np.ndarray:
    """True poses (map frame: the true start pose) at the given times."""
    traj = run["trajectory"]
    t, th = traj[:, 0], np.unwrap(traj[:, 3])
    poses = np.column_stack([np.interp(times_s, t, traj[:, k]) for k in (1, 2)] + [np.interp(times_s, t, th)])
    return _in_start_frame(run["live_true"][0], poses)


def best_shift_s(run: dict[str, Any], times_s: np.ndarray, poses: np.ndarray) -> float:
    """The time shift of the truth that best explains the headings (a pose's stamp is a label, see map_sharpness)."""
    shifts = np.arange(-0.03, 0.03, 0.0005)
    return float(min(shifts, key=lambda s: float(np.var(_wrap(poses[:, 2] - truth_at(run, times_s + s)[:, 2])))))


def fit(est: np.ndarray, truth: np.ndarray, scale: bool) -> tuple[np.ndarray, float, float]:
    """``est`` positions after the best rotation + translation (and scale) onto ``truth``; angle (deg), scale."""
    a, b = est[:, :2], truth[:, :2]
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    u, sv, vt = np.linalg.svd((a - ma).T @ (b - mb))
    rot = vt.T @ u.T
    k = float(sv.sum() / np.sum((a - ma) ** 2)) if scale else 1.0
    return k * (rot @ (a - ma).T).T + mb, math.degrees(math.atan2(rot[1, 0], rot[0, 0])), k


def _line(name: str, err_m: np.ndarray) -> str:
    return f"{name}: RMS {1e3 * math.sqrt(float(np.mean(err_m**2))):.1f} mm, max {1e3 * float(err_m.max()):.1f} mm"


def report(run: dict[str, Any]) -> None:
    m = run["metrics"]
    print(f"run: ATE RMS {m['ate_rms_m']} max {m['ate_max_m']}, heading RMS {m['heading_rms_deg']}, "
          f"F1 {m['map_f1']}, closures {m['loop_closures']}, keyframes {m['keyframes']}")
    live = np.hypot(*(run["live_est"][:, :2] - _in_start_frame(run["live_true"][0], run["live_true"])[:, :2]).T)
    print(_line("live estimate", live))
    ft, fp = run["final_t"], run["final"]
    shift = best_shift_s(run, ft, fp)
    truth = truth_at(run, ft + shift)
    final = np.hypot(*(fp[:, :2] - truth[:, :2]).T)
    print(_line(f"final optimized trajectory (truth {1e3 * shift:.1f} ms after the stamps)", final))
    rigid, angle, _ = fit(fp, truth, scale=False)
    print(_line(f"  after a rigid fit ({angle:+.3f} deg)", np.hypot(*(rigid - truth[:, :2]).T)))
    similar, angle, k = fit(fp, truth, scale=True)
    print(_line(f"  after a similarity fit ({angle:+.3f} deg, scale {k:.5f})", np.hypot(*(similar - truth[:, :2]).T)))
    kt, kp = run["keyframe_t"], run["keyframes"]
    heading = np.degrees(_wrap(kp[:, 2] - truth_at(run, kt + best_shift_s(run, kt, kp))[:, 2]))
    anchor = run["anchor_wall_rad"]
    anchor_deg = math.degrees(float(_wrap(np.array(4.0 * anchor))) / 4.0) if anchor is not None else float("nan")
    print(f"anchor wall direction {anchor_deg:+.3f} deg (truth 0 for a start on the grid); keyframes' mean heading "
          f"error {heading.mean():+.3f} deg, RMS {math.sqrt(float(np.mean(heading**2))):.3f} deg")
    t0, lt = run["start_s"], run["live_t"]
    merge_t = np.array([g["time_s"] for g in run["merges"]]) - t0
    accepted = np.array([g["accepted"] for g in run["merges"]])
    print("timeline (simulated s): live RMS / max, final RMS (mm), merges, closures")
    for b0 in np.arange(0.0, float(lt.max()), 50.0):
        sel, fsel = (lt >= b0) & (lt < b0 + 50), (ft - t0 >= b0) & (ft - t0 < b0 + 50)
        msel = (merge_t >= b0) & (merge_t < b0 + 50)
        if sel.any():
            frms = 1e3 * math.sqrt(float(np.mean(final[fsel] ** 2))) if fsel.any() else float("nan")
            lrms = 1e3 * math.sqrt(float(np.mean(live[sel] ** 2)))
            print(f"  {b0:6.0f}-{b0 + 50:<6.0f} {lrms:5.1f} / {1e3 * float(live[sel].max()):5.1f}   {frms:5.1f}   "
                  f"{int(msel.sum()):3d} {int(accepted[msel].sum()):4d}")
    jumps = np.array([g["jump_m"] for g in run["merges"]])
    if len(jumps):
        print(f"filter pose moved by a merge: median {1e3 * np.median(jumps):.2f} mm, max {1e3 * jumps.max():.1f} mm, "
              f"{int((jumps > 0.005).sum())} of {len(jumps)} merges over 5 mm")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=13)
    ap.add_argument("--size", type=int, default=16, help="generated maze cells per side")
    ap.add_argument("--maze", help="a maze file instead of a generated maze")
    add_keep_options(ap)
    args = ap.parse_args()
    run = kept_or_new(args, lambda: run_and_capture(args.seed, args.size, args.maze))
    report(run)


if __name__ == "__main__":
    main()
