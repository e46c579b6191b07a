"""Recording a run: taps on the devices, SLAM's steps, and a task for pose, map and state.

What goes into the file, and from where:

- every lidar revolution (``/scan`` for Foxglove, ``/mazebot/scan_raw`` exact), from a
  tap on the lidar's ``scans()`` stream, before the lidar task sees it;
- every encoder reading (``/mazebot/encoders``), from a tap on ``encoders.read()``, with
  the time the odometry task stamps it with;
- every motor command (``/mazebot/motors``), from a tap on ``motors.set()``/``stop()``;
- SLAM's steps (``/mazebot/slam``), from listeners on the Slam's taps
  (:class:`~mazebot.slam.slam.SlamTaps`, :meth:`RecordingTap.watch_slam`);
- pose estimates (``/pose``) at ``[record] pose_hz``, with the frame tree of the same instant
  (``/tf``: ``map -> odom -> base_link -> laser``, REP 105) and the dead-reckoned pose
  (``/odom``), so one Foxglove 3D panel shows scan, pose and map together; the map (``/map``) every
  ``map_period_s`` when it changed, run-state changes and faults (``/mazebot/run_state``,
  ``/log``), by :func:`run`, which polls the shared state;
- the daemon's log lines (``/log``), from a logging handler.

Every tap only enqueues (:meth:`McapRecorder.put` never blocks); the taps keep the
devices' interfaces, so the tasks do not know they are recorded. Message times are the
daemon clock's seconds shifted to the Unix epoch at start-up, so Foxglove shows wall
time; the payloads keep the clock's own seconds, which replay uses.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import AsyncIterator, Callable
from typing import Any

from mazebot.clock import Clock
from mazebot.hardware import Hardware, Lidar, Motors
from mazebot.io.scan import Scan
from mazebot.record.schemas import transform_chain
from mazebot.record.writer import McapRecorder
from mazebot.slam.slam import Slam, SlamApplied, SlamUpdated
from mazebot.state import OdometryStep, RunState, SharedState


class RecordingTap:
    """Stamps and enqueues messages for one recorder; shared by all the taps of a run."""

    def __init__(self, recorder: McapRecorder, clock: Clock) -> None:
        self.recorder = recorder
        self.clock = clock
        self.epoch_offset_s = time.time() - clock.now_s()

    def put(self, topic: str, message: Any, time_s: float | None = None) -> None:
        t = self.clock.now_s() if time_s is None else time_s
        self.recorder.put(topic, round((t + self.epoch_offset_s) * 1e9), message)

    # -- SLAM's taps -------------------------------------------------------------------

    def watch_slam(self, slam: Slam) -> None:
        """Record SLAM's steps: each update, each final job handed out, each loop-closure result merged."""
        slam.taps.on_update += (self.slam_updated,)
        slam.taps.on_final_job += (self.slam_final,)
        slam.taps.on_apply += (self.slam_applied,)

    def slam_updated(self, seen: SlamUpdated) -> None:
        latest = getattr(seen.odometry, "latest", None)
        self.put(
            "/mazebot/slam",
            {
                "kind": "update",
                "scan_end_time_s": seen.scan.end_time_s,
                "odometry_latest_s": None if latest is None else float(latest[0]),
                "scans": seen.slam.scans,
            },
        )

    def slam_final(self, slam: Slam) -> None:
        self.put("/mazebot/slam", {"kind": "final", "scans": slam.scans})

    def slam_applied(self, applied: SlamApplied) -> None:
        self.put("/mazebot/slam", {"kind": "apply", "scans": applied.slam.scans, "rebuilt": bool(applied.rebuilt)})


class LidarTap:
    """The lidar driver, with every revolution recorded as it is handed on."""

    def __init__(self, lidar: Lidar, tap: RecordingTap) -> None:
        self._lidar = lidar
        self._tap = tap

    async def scans(self) -> AsyncIterator[Scan]:
        async for scan in self._lidar.scans():
            self._tap.put("/scan", scan, scan.end_time_s)
            self._tap.put("/mazebot/scan_raw", scan, scan.end_time_s)
            yield scan

    def __getattr__(self, name: str) -> Any:
        return getattr(self._lidar, name)


def encoder_recorder(tap: RecordingTap) -> Callable[[OdometryStep], None]:
    """A listener for ``SharedState.odometry_listeners`` that records every encoder reading.

    Each reading is written at its own time with the time the odometry dated its pose by
    (``pose_time_s``; absent from older recordings, where it was the reading's time), so a
    replay builds the same odometry history as the live run.
    """

    def record(step: OdometryStep) -> None:
        tap.put(
            "/mazebot/encoders",
            {
                "time_s": step.reading_time_s,
                "pose_time_s": step.pose_time_s,
                "left_ticks": step.left_ticks,
                "right_ticks": step.right_ticks,
                "invalid_transitions": step.invalid_transitions,
            },
            step.reading_time_s,
        )

    return record


class MotorsTap:
    """The motor driver, with every command recorded (a stop is 0, 0)."""

    def __init__(self, motors: Motors, tap: RecordingTap) -> None:
        self._motors = motors
        self._tap = tap

    def set(self, left: float, right: float) -> None:
        self._motors.set(left, right)
        self._record(float(left), float(right))

    def stop(self) -> None:
        self._motors.stop()
        self._record(0.0, 0.0)

    def _record(self, left: float, right: float) -> None:
        now_s = self._tap.clock.now_s()
        self._tap.put("/mazebot/motors", {"time_s": now_s, "left": left, "right": right}, now_s)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._motors, name)


def tap_hardware(hardware: Hardware, tap: RecordingTap) -> Hardware:
    """The same hardware with its lidar and motors recorded (the encoders: :func:`encoder_recorder`)."""
    return dataclasses.replace(
        hardware,
        lidar=LidarTap(hardware.lidar, tap),
        motors=MotorsTap(hardware.motors, tap),
    )


class LogTap(logging.Handler):
    """Log records of the ``mazebot`` logger as ``foxglove.Log`` messages (any thread may log)."""

    def __init__(self, tap: RecordingTap) -> None:
        super().__init__(logging.INFO)
        self._tap = tap

    def emit(self, record: logging.LogRecord) -> None:
        if record.name.startswith("mazebot.record"):
            return  # the recorder's own complaints must not feed it
        if getattr(record, "secret", False):
            return  # a line carrying a secret (the first-start PIN) never goes into a file
        entry = (record.levelname, record.name, record.getMessage(), record.pathname, record.lineno)
        self._tap.recorder.put("/log", int(record.created * 1e9), entry)


def publish_stats(state: SharedState, recorder: McapRecorder) -> None:
    stats, out = recorder.stats, state.record
    out.path = str(recorder.path)
    out.messages = stats.written
    out.dropped = stats.dropped
    out.files = stats.files
    out.error = stats.error
    out.writer_cpu_s = round(stats.writer_cpu_s, 3)


def put_pose(state: SharedState, tap: RecordingTap, lidar_mount_xy_m: tuple[float, float]) -> None:
    """``/pose``, and ``/odom`` with ``/tf`` once odometry runs, all stamped with the time the pose is true
    at (``state.pose_time_s``: the stamp of the newest encoder edge counted, as lgpio gives it on the
    robot), not the time of the reading, which under a starved CPU comes tens of milliseconds later."""
    p, time_s = state.pose, state.pose_time_s
    pose = (p.x_m, p.y_m, p.theta_rad)
    tap.put("/pose", pose, time_s)
    odo = state.odometry
    if odo is None:
        return
    odometry = (odo.x_m, odo.y_m, odo.theta_rad)
    tap.put("/odom", odometry, time_s)
    for transform in transform_chain(pose, odometry, lidar_mount_xy_m):
        tap.put("/tf", transform, time_s)


async def run(
    state: SharedState,
    tap: RecordingTap,
    pose_hz: float,
    map_period_s: float,
    lidar_mount_xy_m: tuple[float, float] = (0.0, 0.0),
) -> None:
    """Record pose, frames, map, run-state changes and faults from the shared state, for ever."""
    clock = tap.clock
    period_s = 1.0 / pose_hz
    last_state: RunState | None = None
    faults_recorded: set[int] = set()  # ids of the Fault objects already written
    next_map_s = clock.now_s()
    last_map: tuple[int, int, tuple[int, int]] | None = None
    last_pose_time: float | None = None
    while True:
        now_s = clock.now_s()
        if state.pose_time_s is not None and state.pose_time_s != last_pose_time:
            last_pose_time = state.pose_time_s
            put_pose(state, tap, lidar_mount_xy_m)
        if state.run_state is not last_state:
            last_state = state.run_state
            tap.put("/mazebot/run_state", {"time_s": now_s, "state": last_state.value})
            tap.put("/log", ("INFO", "mazebot.state", f"run state: {last_state.value}", "", 0))
        for fault in state.faults:
            if id(fault) not in faults_recorded:
                tap.put("/log", ("ERROR", f"mazebot.{fault.source}", fault.message, "", 0), fault.time_s)
        faults_recorded = {id(f) for f in state.faults}
        grid = state.map
        if grid is not None and now_s >= next_map_s:
            three = grid.three_state()
            signature = (grid.generation, int(three.sum()), grid.shape)
            if signature != last_map:  # unchanged maps are not written again
                last_map = signature
                tap.put("/map", (three, grid.resolution_m, grid.origin_m))
            next_map_s = now_s + map_period_s
        publish_stats(state, tap.recorder)
        await clock.sleep(period_s)
