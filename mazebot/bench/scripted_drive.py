"""A ground-truth route through every cell of a maze, and a driver that follows it.

``--drive scripted`` measures SLAM without the planner: the route is a depth-first
tour of the true maze (every reachable cell, back-tracking through dead ends, ending
back at the start), and the driver steers along it with the TRUE pose. It commands
throttles through the daemon's control task, so the motor driver, the simulated
motors and the encoders all work as in a real run; only the decision of where to go
is borrowed from ground truth.
"""

from __future__ import annotations

import math

from mazebot.clock import Clock
from mazebot.sim.physics import RobotPhysics
from mazebot.sim.world import MazeLayout
from mazebot.state import RunState, SharedState

Cell = tuple[int, int]


def dfs_tour(layout: MazeLayout, start: Cell | None = None) -> list[Cell]:
    """Cells in the order a depth-first walk visits them, back-tracking included.

    Consecutive cells are always neighbours, and the tour returns to ``start``.
    """
    start = start or layout.start_cell
    tour = [start]
    seen = {start}
    stack: list[tuple[Cell, list[Cell]]] = [(start, sorted(layout.neighbours(start)))]
    while stack:
        _, todo = stack[-1]
        nxt = next((n for n in todo if n not in seen), None)
        if nxt is None:
            stack.pop()
            if stack:
                tour.append(stack[-1][0])
            continue
        todo.remove(nxt)
        seen.add(nxt)
        tour.append(nxt)
        stack.append((nxt, sorted(layout.neighbours(nxt))))
    return tour


def straighten(tour: list[Cell]) -> list[Cell]:
    """Drop the cells in the middle of straight runs: the driver goes through them."""
    if len(tour) < 3:
        return list(tour)
    out = [tour[0]]
    for prev, cell, nxt in zip(tour, tour[1:], tour[2:], strict=False):
        if (cell[0] - prev[0], cell[1] - prev[1]) != (nxt[0] - cell[0], nxt[1] - cell[1]):
            out.append(cell)
    out.append(tour[-1])
    return out


class ScriptedDriver:
    """Follows waypoints with the true pose: turn in place, then drive with heading hold.

    Speeds are the config's limits; throttles are wheel speed over the full-throttle
    speed plus the motor deadband (a feed-forward, no feedback from the encoders).
    """

    def __init__(
        self,
        waypoints_m: list[tuple[float, float]],
        physics: RobotPhysics,
        *,
        speed_mps: float,
        yaw_rate_radps: float,
        track_width_m: float,
        full_throttle_mps: float,
        deadband: float,
        tolerance_m: float = 0.03,
    ) -> None:
        self.waypoints_m = waypoints_m
        self.physics = physics
        self.speed_mps = speed_mps
        self.yaw_rate_radps = yaw_rate_radps
        self.track_width_m = track_width_m
        self.full_throttle_mps = full_throttle_mps
        self.deadband = deadband
        self.tolerance_m = tolerance_m
        self.index = 0
        self.done = False

    def _throttle(self, wheel_mps: float) -> float:
        if abs(wheel_mps) < 1e-4:
            return 0.0
        t = wheel_mps / self.full_throttle_mps
        return math.copysign(min(1.0, abs(t) * (1 - self.deadband) + self.deadband), t)

    def command(self) -> tuple[float, float]:
        """(left, right) throttle for the current true pose."""
        x, y, th = self.physics.pose
        while self.index < len(self.waypoints_m):
            gx, gy = self.waypoints_m[self.index]
            dist = math.hypot(gx - x, gy - y)
            if dist > self.tolerance_m:
                break
            self.index += 1
        else:
            self.done = True
            return 0.0, 0.0
        err = math.remainder(math.atan2(gy - y, gx - x) - th, math.tau)
        if abs(err) > math.radians(25):
            v, w = 0.0, math.copysign(self.yaw_rate_radps * min(1.0, abs(err) / 0.6 + 0.3), err)
        else:
            v = self.speed_mps * min(1.0, dist / 0.15 + 0.3)
            w = max(-self.yaw_rate_radps, min(self.yaw_rate_radps, 3.0 * err))
        half = 0.5 * self.track_width_m * w
        return self._throttle(v - half), self._throttle(v + half)

    async def run(self, state: SharedState, clock: Clock, period_s: float) -> None:
        """Drive until the tour ends, then leave the robot stopped and DONE."""
        while not state.slam.anchored:  # as the planner does: SLAM takes its anchor at rest first
            await clock.sleep(period_s)
        state.run_state = RunState.EXPLORING
        state.begin_run(clock.now_s())
        while not self.done:
            if state.run_state is not RunState.EXPLORING:
                return
            left, right = self.command()
            state.throttle_command = (left, right, clock.now_s())
            await clock.sleep(period_s)
        state.throttle_command = None
        state.run_state = RunState.DONE
