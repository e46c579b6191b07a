"""Replay: a recording's sensor streams through the same SLAM, step for step.

The recorded revolutions (``/mazebot/scan_raw``, bit-exact) and encoder readings
(``/mazebot/encoders``) go through the daemon's own code: the readings through
:class:`~mazebot.slam.odometry.DiffDriveOdometry` into an
:class:`~mazebot.slam.ekf.OdometryHistory`, exactly as the odometry task does, and the
revolutions into :class:`mazebot.slam.slam.Slam`, built from the configuration stored
in the recording.

When the recording has SLAM's steps (``/mazebot/slam``), replay takes the very same
steps: the revolutions the live SLAM processed (not those it dropped), each when the
odometry had reached the same reading, and each loop-closure result merged after the
same number of scans as live (the job itself is computed at once, in this thread,
from the same snapshot); the end-of-exploration job (``Slam.final_job``) is asked for
at the same step as live. The replayed map is then the live map. Without steps (a
recording of sensors only) every revolution is processed as soon as the odometry
covers it and loop closures are merged at once.

Nothing depends on the wall clock or on thread timing, so replaying a file twice gives
identical output files.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mazebot.config import Config, config_from_json
from mazebot.errors import ConfigError
from mazebot.io.scan import Scan
from mazebot.record.reader import RecordedMessage, Recording, RecordingError
from mazebot.record.schemas import scan_from_json
from mazebot.slam.ekf import OdometryHistory
from mazebot.slam.g2o import format_g2o
from mazebot.slam.map_export import write_map_png, write_ros_map
from mazebot.slam.odometry import DiffDriveOdometry
from mazebot.slam.slam import LoopClosureJob, LoopClosureResult, Slam, SlamParams

TOPICS = ("/mazebot/scan_raw", "/mazebot/encoders", "/mazebot/slam")


@dataclass
class ReplayResult:
    """The SLAM after the replay, and what happened on the way."""

    slam: Slam
    config: Config
    mode: str  # "steps" (the live SLAM's own steps) or "sensors" (every revolution)
    updates: int = 0
    applied: int = 0
    missing_scans: int = 0  # steps whose revolution is not in the file (recorder drops)
    odometry_mismatches: int = 0  # steps whose odometry did not reach the recorded reading
    stats: dict[str, Any] = field(default_factory=dict)


def recorded_config(recording: Recording) -> Config:
    try:
        return config_from_json(recording.metadata["config"], str(recording.path))
    except (KeyError, ValueError, ConfigError) as exc:
        raise RecordingError(f"{recording.path}: the recorded configuration cannot be read ({exc})") from None


def _run_now(job: LoopClosureJob) -> Future[LoopClosureResult]:
    """A loop-closure job computed at once, in this thread (offline replay)."""
    done: Future[LoopClosureResult] = Future()
    done.set_result(job.run())
    return done


class Replayer:
    """Replay's steps, one recorded message at a time: offline, and behind the web page.

    ``submit`` starts a loop-closure job and returns its future (default: computed at once;
    the served replay hands it to an executor, as the daemon does). A step that merges a
    job's result waits for it: :meth:`waits_for` says which future a message needs first.

    Example::

        replayer = Replayer(Recording.open("run.mcap"))
        for msg in replayer.recording.messages(TOPICS):
            replayer.feed(msg)
        replayer.slam.grid            # the map, as live
    """

    def __init__(
        self,
        recording: Recording,
        *,
        submit: Callable[[LoopClosureJob], Future[LoopClosureResult]] = _run_now,
    ) -> None:
        self.recording = recording
        self.config = config = recorded_config(recording)
        params = SlamParams.from_config(config.slam, config.lidar, config.planner)
        self.slam = Slam(params, background=True, record_trajectory=True)
        drive = config.drive
        self.odometry = DiffDriveOdometry(
            config.encoders.ticks_per_rev, drive.wheel_diameter_m, drive.track_width_m, drive.wheel_diameter_ratio,
            math.radians(drive.gearbox_backlash_deg),
        )
        self.history = OdometryHistory(config.slam.odometry_history_s)
        self.steps = recording.message_counts.get("/mazebot/slam", 0) > 0
        self.result = ReplayResult(self.slam, config, "steps" if self.steps else "sensors")
        self._submit = submit
        self._pending: dict[float, Scan] = {}  # revolutions waiting for SLAM, by end time
        self._held: list[Future[LoopClosureResult]] = []  # jobs waiting for the step that merged them live

    def waits_for(self, msg: RecordedMessage) -> Future[LoopClosureResult] | None:
        """The job whose result ``msg`` merges, if it is a merge step and one is held."""
        if self._held and msg.topic == "/mazebot/slam" and msg.data.get("kind") == "apply":
            return self._held[0]
        return None

    def feed(self, msg: RecordedMessage) -> list[tuple[str, Any]]:
        """Take one message; what SLAM did: ``("update", SlamUpdate)`` / ``("apply", rebuilt)``."""
        done: list[tuple[str, Any]] = []
        data = msg.data
        if msg.topic == "/mazebot/encoders":
            self.odometry.update(int(data["left_ticks"]), int(data["right_ticks"]))
            pose = self.odometry.pose
            # the time the live odometry dated this pose by; None: it added nothing to the history
            pose_s = data["pose_time_s"] if "pose_time_s" in data else data["time_s"]
            if pose_s is not None:
                self.history.append(float(pose_s), pose.x_m, pose.y_m, pose.theta_rad)
            if not self.steps:
                latest = self.history.latest
                for end_s in sorted(self._pending):
                    if latest is not None and latest[0] >= end_s:
                        self._process(self._pending.pop(end_s), done)
        elif msg.topic == "/mazebot/scan_raw":
            scan = scan_from_json(data)
            self._pending[scan.end_time_s] = scan
        elif msg.topic != "/mazebot/slam":
            pass
        elif data.get("kind") == "update":
            end_s = float(data["scan_end_time_s"])
            pending = self._pending.pop(end_s, None)
            for older in [t for t in self._pending if t < end_s]:  # dropped by the live SLAM
                del self._pending[older]
            if pending is None:
                self.result.missing_scans += 1
                return done
            scan = pending
            latest = self.history.latest
            expected = data.get("odometry_latest_s")
            if expected is not None and (latest is None or latest[0] != expected):
                self.result.odometry_mismatches += 1
            self._process(scan, done)
        elif data.get("kind") == "final":  # the exploration ended: Slam.final_job, as live
            job = self.slam.final_job()
            if job is not None:
                self._held.append(self._submit(job))
        elif data.get("kind") == "apply" and self._held:
            self._apply(self._held.pop(0).result(), done)
        return done

    def _process(self, scan: Scan, done: list[tuple[str, Any]]) -> None:
        update = self.slam.update(scan, self.history)
        self.result.updates += 1
        done.append(("update", update))
        if update.loop_job is not None:
            job = self._submit(update.loop_job)
            if self.steps:
                self._held.append(job)
            else:
                self._apply(job.result(), done)

    def _apply(self, job_result: LoopClosureResult, done: list[tuple[str, Any]]) -> None:
        rebuilt = self.slam.apply(job_result)
        self.result.applied += 1
        done.append(("apply", rebuilt))

    def finish(self) -> ReplayResult:
        """The result, with its summary."""
        result, slam = self.result, self.slam
        result.stats = {
            "mode": result.mode,
            "updates": result.updates,
            "loop_closure_results_applied": result.applied,
            "keyframes": len(slam.keyframes),
            "loop_closures": len(slam.closures),
            "missing_scans": result.missing_scans,
            "odometry_mismatches": result.odometry_mismatches,
            "recorded_dropped": int(self.recording.recorder_stats.get("dropped", 0) or 0),
        }
        return result


class Pace:
    """How long to wait before a message so that a replay keeps ``speed`` times the recorded pace.

    ``wait_s(log_time_ns, now_s)``: seconds until the message is due (<= 0: now), counted from the
    first message's log time and ``started_s``, the clock reading when the replay started.
    """

    def __init__(self, speed: float, started_s: float) -> None:
        self.speed, self.started_s = speed, started_s
        self.first_log_ns: int | None = None

    def wait_s(self, log_time_ns: int, now_s: float) -> float:
        if self.first_log_ns is None:
            self.first_log_ns = log_time_ns
        return (log_time_ns - self.first_log_ns) / 1e9 / self.speed - (now_s - self.started_s)


def replay(
    recording: Recording,
    *,
    speed: float | None = None,
    on_update: Callable[[Slam], None] | None = None,
    sleep: Callable[[float], None] = time.sleep,
) -> ReplayResult:
    """Run the recording through SLAM; ``speed`` paces it (1.0 = as recorded), None = as fast as possible."""
    replayer = Replayer(recording)
    pace = None if speed is None else Pace(speed, time.monotonic())
    for msg in recording.messages(TOPICS):
        if pace is not None and (due_s := pace.wait_s(msg.log_time_ns, time.monotonic())) > 0:
            sleep(due_s)
        if replayer.feed(msg) and on_update is not None:
            on_update(replayer.slam)
    return replayer.finish()


def write_outputs(result: ReplayResult, out_dir: Path) -> dict[str, Path]:
    """``map.pgm``/``map.yaml``/``map.png``, ``trajectory.txt``, ``graph.g2o``, ``summary.json``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    slam = result.slam
    pgm, yaml = write_ros_map(slam.grid, out_dir / "map")
    png = write_map_png(slam.grid.three_state(), out_dir / "map.png")
    times, poses = slam.trajectory()
    lines = [f"{t!r} {p[0]!r} {p[1]!r} {p[2]!r}\n" for t, p in zip(times.tolist(), poses.tolist(), strict=True)]
    trajectory = out_dir / "trajectory.txt"
    trajectory.write_text("".join(lines), encoding="utf-8")
    graph = out_dir / "graph.g2o"
    graph.write_text("".join(format_g2o(slam.graph)), encoding="utf-8")
    summary = out_dir / "summary.json"
    occupied = int(np.count_nonzero(slam.grid.occupied_mask()))
    summary.write_text(json.dumps({**result.stats, "occupied_cells": occupied}, indent=2) + "\n", encoding="utf-8")
    return {"pgm": pgm, "yaml": yaml, "png": png, "trajectory": trajectory, "graph": graph, "summary": summary}


def occupied_iou(a: Any, b: Any) -> float:
    """IoU of the occupied cells of two grids, compared at the same world coordinates."""
    res = a.resolution_m
    if abs(res - b.resolution_m) > 1e-12:
        raise ValueError("grids of different resolutions")
    ra, ca = np.nonzero(a.occupied_mask())
    rb, cb = np.nonzero(b.occupied_mask())
    oa = np.round(np.array(a.origin_m) / res).astype(int)
    ob = np.round(np.array(b.origin_m) / res).astype(int)
    sa = {(int(r + oa[1]), int(c + oa[0])) for r, c in zip(ra, ca, strict=True)}
    sb = {(int(r + ob[1]), int(c + ob[0])) for r, c in zip(rb, cb, strict=True)}
    union = sa | sb
    return 1.0 if not union else len(sa & sb) / len(union)
