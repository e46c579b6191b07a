"""Foxglove live: what changed in the shared state, sent to the SDK's server (``[foxglove]``).

Polls like the recorder (:mod:`mazebot.tasks.record_task`) at ``[foxglove] pose_hz``: a new
revolution, a new pose (with ``/odom`` and the ``/tf`` chain of the same reading), a new
plan, run-state changes, motor throttles
and tick totals; and every ``map_period_s`` the map, the plan and the goal again, so a client
that subscribes late has them within that time (the SDK keeps no last message per channel).
Each send returns at once when nobody is subscribed
(:class:`~mazebot.record.foxglove_live.FoxgloveLive`); the protobuf encoding and the
sockets are the SDK's Rust threads' work.
"""

from __future__ import annotations

import time

from mazebot.clock import Clock
from mazebot.record.foxglove_live import FoxgloveLive
from mazebot.record.schemas import MAP_FRAME, ODOM_FRAME, transform_chain
from mazebot.state import RunState, SharedState


async def run(
    state: SharedState,
    live: FoxgloveLive,
    clock: Clock,
    pose_hz: float,
    map_period_s: float,
    lidar_mount_xy_m: tuple[float, float] = (0.0, 0.0),
) -> None:
    """Send the shared state's news to Foxglove, for ever."""
    epoch_offset_s = time.time() - clock.now_s()  # the clock's seconds as Unix time, like the recording
    period_s = 1.0 / pose_hz
    meter = state.cpu.part("foxglove live")
    last_scan = last_pose_time = last_path = last_goal = None
    last_state: RunState | None = None
    last_throttles: tuple[float, float] | None = None
    last_ticks: tuple[int, int] | None = None
    next_map_s = clock.now_s()
    while True:
        with meter.measure():
            now_s = clock.now_s()
            epoch_s = now_s + epoch_offset_s
            scan = state.latest_scan
            if scan is not None and scan is not last_scan:
                last_scan = scan
                live.scan(scan, scan.end_time_s + epoch_offset_s)
            if state.pose_time_s is not None and state.pose_time_s != last_pose_time:
                last_pose_time = state.pose_time_s
                t_s = state.pose_time_s + epoch_offset_s
                p = state.pose
                pose = (p.x_m, p.y_m, p.theta_rad)
                live.pose("/pose", MAP_FRAME, pose, t_s)
                odo = state.odometry
                if odo is not None:
                    odometry = (odo.x_m, odo.y_m, odo.theta_rad)
                    live.pose("/odom", ODOM_FRAME, odometry, t_s)
                    live.transforms(transform_chain(pose, odometry, lidar_mount_xy_m), t_s)
            if state.path is not last_path:
                last_path = state.path
                live.path(state.path, epoch_s)
            if state.goal != last_goal:
                last_goal = state.goal
                if state.goal is not None:
                    live.pose("/goal", MAP_FRAME, (float(state.goal[0]), float(state.goal[1]), 0.0), epoch_s)
            if state.run_state is not last_state:
                last_state = state.run_state
                live.json("/mazebot/run_state", {"time_s": now_s, "state": last_state.value}, epoch_s)
            if state.throttles != last_throttles:
                last_throttles = state.throttles
                left, right = state.throttles
                live.json("/mazebot/motors", {"time_s": now_s, "left": left, "right": right}, epoch_s)
            sensors = state.sensors
            ticks = (sensors.encoder_ticks_left, sensors.encoder_ticks_right)
            if ticks != last_ticks:
                last_ticks = ticks
                live.json(
                    "/mazebot/encoders",
                    {"time_s": now_s, "left_ticks": ticks[0], "right_ticks": ticks[1],
                     "invalid_transitions": sensors.encoder_invalid_transitions},
                    epoch_s,
                )
            if now_s >= next_map_s:
                next_map_s = now_s + map_period_s
                grid = state.map
                if grid is not None and live.map_wanted:
                    live.grid(grid.three_state(), grid.resolution_m, grid.origin_m, epoch_s)
                last_path = last_goal = None  # sent again on the next tick
        await clock.sleep(period_s)
