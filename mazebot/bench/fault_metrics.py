"""What each injected fault did to a benchmark run, measured from the simulation's ground truth.

For every injection (:mod:`mazebot.sim.faults`):

- **detected in ms**: from the true injection time to the first ``/api/status`` fault or
  event of one of the fault's sources (the time the daemon said so);
- **motors zero in ms** (faults after which the robot cannot know where it is or what is
  ahead): from that detection to the first instant both throttles *at the fake motor
  HAT* are zero (the writes that reached it, not what the daemon thinks it wrote);
- **recovered**: after the fault ended, the run went on by itself (``daemon.auto_resume``,
  or a start pressed by the bench's user for a latched fault): no fault left, the run
  state moving again (or done), and the true robot drove on at least ``DROVE_ON_M``;
- **map intact**: the map as it was just before the fault against the final one: at
  least ``KEPT_SHARE`` of the walls it had are still walls (within ``KEPT_CELLS``: nothing
  lost), at least ``FREE_KEPT_SHARE`` of the space it knew free (``KEPT_CELLS`` away from
  any wall) has no wall in it now (nothing painted in at a wrong pose), and at least
  ``MIN_PRECISION`` of the final map's walls lie on true walls;
- **alive**: the daemon's exit code is 0 and none of its tasks has ended;
- **re-localized in s** (kidnap): until the estimated pose is within ``RELOC_M`` /
  ``RELOC_DEG`` of the true one and stays there for ``RELOC_HOLD_S``;
- **scanning again in s** (lidar replug): from the cable going back in to the first new
  revolution the daemon has.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import ndimage

from mazebot.bench.metrics import map_metrics, relative_poses
from mazebot.clock import Clock
from mazebot.io.motors import ThrottleWrite
from mazebot.sim.faults import DETECTED_MAX_MS, MOTORS_ZERO_MAX_MS
from mazebot.state import Event, RunState, SharedState

#: How long after the last fault ended the run goes on (the recovery must happen in it).
RECOVERY_WINDOW_S = 25.0
#: Longest a fault run lasts after its last fault was due (a deferred fault that never came).
MAX_AFTER_FAULT_S = 60.0
MONITOR_PERIOD_S = 0.02
DROVE_ON_M = 0.05
KEPT_SHARE = 0.95
KEPT_CELLS = 2
FREE_KEPT_SHARE = 0.99
MIN_PRECISION = 0.9
RELOC_M = 0.05
RELOC_DEG = 5.0
RELOC_HOLD_S = 1.0
#: The fault suite's targets (docs/design.md, "The fault suite's targets"); the first two are the
#: injector's too (a kidnapped robot is put down where it can roll on for that long).
RELOCALIZED_MAX_S = 10.0
SCANNING_AGAIN_MAX_S = 3.0


@dataclass
class FaultRecord:
    """The ground truth a fault run collects: injections, events, HAT writes, a state trace."""

    injector: Any  # mazebot.sim.faults.FaultInjector
    recovery_window_s: float = RECOVERY_WINDOW_S
    events: list[tuple[float, str, str]] = field(default_factory=list)  # (time, source, message)
    writes: list[tuple[float, int, float | None]] = field(default_factory=list)  # at the HAT
    trace: list[tuple[float, str, tuple[str, ...], float | None, float]] = field(default_factory=list)
    maps_before: dict[int, Any] = field(default_factory=dict)  # injection index -> grid copy
    final_map: Any = None
    alive: bool = False
    channels: tuple[int, int] = (1, 2)
    robot: Any = None

    def watch(self, robot: Any, state: SharedState, supervisor: Any, clock: Clock) -> None:
        """Tap the state's notes and the HAT's writes, and sample the run every 20 ms."""
        self.robot = robot
        motors = robot.config.motors
        self.channels = (motors.left_channel, motors.right_channel)

        def noted(event: Event) -> None:
            self.events.append((clock.now_s(), event.source, event.message))

        state.note_listeners += (noted,)

        def written(write: ThrottleWrite) -> None:  # only the writes that reached the HAT (not the failed ones)
            self.writes.append((clock.now_s(), write.channel, write.throttle))

        robot.kit.on_write += (written,)

        def before(injection: Any) -> None:
            k = self.injector.injections.index(injection)
            if state.map is not None:
                grid = copy.copy(state.map)
                grid.log_odds = state.map.log_odds.copy()
                self.maps_before[k] = grid

        self.injector.on_begin = before

        async def monitor() -> None:
            while True:
                scan = state.latest_scan
                self.trace.append((clock.now_s(), state.run_state.value, tuple(f.source for f in state.faults),
                                   None if scan is None else scan.end_time_s, robot.physics.odometer_m))
                await clock.sleep(MONITOR_PERIOD_S)

        supervisor.start("bench-fault-monitor", monitor)

    async def user(self, state: SharedState, clock: Clock) -> None:
        """The bench's user: presses start after a fault that needs it; ends the run after the recovery window."""
        injections = self.injector.injections
        last_due_s = clock.now_s() + max(i.spec.at_s for i in injections)
        pressed_s = -math.inf
        while True:
            await clock.sleep(0.2)
            now_s = clock.now_s()
            ends = [i.end_s for i in injections]
            ended = [e for e in ends if e is not None]
            if len(ended) == len(ends) and now_s >= max(ended) + self.recovery_window_s:
                return
            if now_s >= last_due_s + MAX_AFTER_FAULT_S:
                return
            ended = [e for e in ends if e is not None]
            active = any(i.begin_s is not None and i.end_s is None for i in injections)
            latched_only = state.run_state is RunState.FAULT and all(f.latched for f in state.faults)
            if ended and not active and now_s >= max(ended) + 1.0 and now_s - pressed_s >= 2.0 and (
                state.run_state is RunState.STOPPED or latched_only
            ):
                state.commands.put_nowait("start")  # as the user would, once the cause is gone
                pressed_s = now_s

    def finish(self, state: SharedState, supervisor: Any, clock: Clock) -> None:
        self.final_map = state.map
        self.alive = all(not t.done() for name, t in supervisor.tasks.items() if not name.startswith("bench-"))


def _throttles_at(writes: list[tuple[float, int, float | None]], channels: tuple[int, int], t: float) -> list:
    now: dict[int, float | None] = {c: None for c in channels}
    for time_s, channel, throttle in writes:
        if time_s > t:
            break
        if channel in now:
            now[channel] = throttle
    return [now[c] for c in channels]


def motors_zero_after(
    writes: list[tuple[float, int, float | None]], channels: tuple[int, int], t: float
) -> float | None:
    """Seconds from ``t`` until both HAT channels are at zero (0 or coasting); None if never."""
    now = dict(zip(channels, _throttles_at(writes, channels, t), strict=True))
    if all(not v for v in now.values()):
        return 0.0
    for time_s, channel, throttle in writes:
        if time_s <= t or channel not in now:
            continue
        now[channel] = throttle
        if all(not v for v in now.values()):
            return time_s - t
    return None


def walls_kept(before: Any, after: Any, cells: int = KEPT_CELLS) -> float | None:
    """Share of the walls of ``before`` that ``after`` still has within ``cells`` cells."""
    if before is None or after is None:
        return None
    rows, cols = np.nonzero(before.occupied_mask())
    if rows.size == 0:
        return 1.0
    r, c = after.to_cell(before.to_world(rows, cols))
    walls = ndimage.binary_dilation(after.occupied_mask(), iterations=cells)
    inside = (r >= 0) & (r < walls.shape[0]) & (c >= 0) & (c < walls.shape[1])
    found = np.zeros(rows.size, dtype=bool)
    found[inside] = walls[r[inside], c[inside]]
    return float(found.mean())


def free_kept(before: Any, after: Any, cells: int = KEPT_CELLS) -> float | None:
    """Share of the space ``before`` knew free, ``cells`` away from its walls, that ``after`` has no wall in."""
    if before is None or after is None:
        return None
    free = ndimage.binary_erosion(before.known_free_mask(), iterations=cells)
    free &= ~ndimage.binary_dilation(before.occupied_mask(), iterations=cells)
    rows, cols = np.nonzero(free)
    if rows.size == 0:
        return 1.0
    r, c = after.to_cell(before.to_world(rows, cols))
    walls = after.occupied_mask()
    inside = (r >= 0) & (r < walls.shape[0]) & (c >= 0) & (c < walls.shape[1])
    wall = np.zeros(rows.size, dtype=bool)
    wall[inside] = walls[r[inside], c[inside]]
    return float(1.0 - wall.mean())


def _first_relocalized(record: Any, begin_rel_s: float) -> float | None:
    if not record.true_poses:
        return None
    times = np.asarray(record.times_s, dtype=float)
    truth = relative_poses(tuple(record.true_poses[0]), np.asarray(record.true_poses, dtype=float))
    est = np.asarray(record.est_poses, dtype=float)
    err_xy = np.hypot(est[:, 0] - truth[:, 0], est[:, 1] - truth[:, 1])
    err_th = np.degrees(np.abs(np.remainder(est[:, 2] - truth[:, 2] + np.pi, 2 * np.pi) - np.pi))
    good = (err_xy < RELOC_M) & (err_th < RELOC_DEG)
    for k in np.flatnonzero((times >= begin_rel_s + 0.1) & good):
        hold = (times >= times[k]) & (times <= times[k] + RELOC_HOLD_S)
        if times[-1] >= times[k] + RELOC_HOLD_S and good[hold].all():
            return float(times[k] - begin_rel_s)
    return None


def fault_metrics(record: Any, exit_code: int) -> list[dict[str, Any]]:
    """One row per injection (see the module docstring)."""
    faults: FaultRecord = record.faults
    robot = faults.robot
    start_true = tuple(record.true_poses[0]) if record.true_poses else robot.world.start_pose
    footprint_m = robot.config.robot.footprint_radius_m
    final = faults.final_map
    after = map_metrics(final, robot.world, start_true, footprint_m)
    rows = []
    for k, inj in enumerate(faults.injector.injections):
        kind = inj.kind
        row: dict[str, Any] = {"fault": kind.name, "what": kind.what, "at_s": inj.spec.at_s, "detail": inj.detail,
                               "must_stop": kind.must_stop}
        if inj.begin_s is None:
            row.update(injected=False, passed=False)
            rows.append(row)
            continue
        begin_s = inj.begin_s
        end_s = inj.end_s if inj.end_s is not None else begin_s
        row["injected_s"] = round(begin_s - record.start_s, 3)
        detection = next(((t, s, m) for t, s, m in faults.events if t >= begin_s and s in kind.sources), None)
        detected_s = None if detection is None else detection[0]
        row["detected_ms"] = None if detected_s is None else round(1000 * (detected_s - begin_s), 1)
        row["detected_by"] = None if detection is None else f"{detection[1]}: {detection[2]}"
        zero_s = None
        if kind.must_stop and detected_s is not None:
            zero_s = motors_zero_after(faults.writes, faults.channels, detected_s)
        row["motors_zero_ms"] = None if zero_s is None else round(1000 * zero_s, 1)
        # recovery: no fault, moving again (or done), and the true robot drove on
        recovered_at = None
        since_s = max(end_s, detected_s if detected_s is not None else end_s) + MONITOR_PERIOD_S
        for t, run_state, sources, _, odometer in faults.trace:
            if t >= since_s and not sources and run_state in ("exploring", "returning", "done"):
                recovered_at = (t, run_state, odometer)
                break
        drove_on = False
        if recovered_at is not None:
            final_odometer = faults.trace[-1][4]
            drove_on = recovered_at[1] == "done" or final_odometer - recovered_at[2] >= DROVE_ON_M
        row["recovered"] = recovered_at is not None and drove_on
        row["recovered_after_s"] = None if recovered_at is None else round(recovered_at[0] - end_s, 2)
        before = faults.maps_before.get(k)
        kept = walls_kept(before, final)
        prior = map_metrics(before, robot.world, start_true, footprint_m) if before is not None else None
        clean = free_kept(before, final)
        row["walls_kept"] = None if kept is None else round(kept, 4)
        row["free_kept"] = None if clean is None else round(clean, 4)
        row["map_precision_before"] = None if prior is None else prior["map_precision"]
        row["map_precision_after"] = after["map_precision"]
        row["map_intact"] = (
            kept is not None and kept >= KEPT_SHARE and clean is not None and clean >= FREE_KEPT_SHARE
            and after["map_precision"] is not None and after["map_precision"] >= MIN_PRECISION
        )
        row["alive"] = exit_code == 0 and faults.alive
        if kind.name == "kidnap":
            reloc = _first_relocalized(record, begin_s - record.start_s)
            row["relocalized_s"] = None if reloc is None else round(reloc, 2)
        if kind.name == "lidar-unplug":
            again = next((t for t, _, _, end, _ in faults.trace if end is not None and end > end_s), None)
            row["scanning_again_s"] = None if again is None else round(again - end_s, 2)
        row["passed"] = passed(row)
        rows.append(row)
    return rows


def passed(row: dict[str, Any]) -> bool:
    """Every target of the fault suite met for this fault."""
    ok = row.get("detected_ms") is not None and row["detected_ms"] <= DETECTED_MAX_MS
    if row.get("must_stop"):
        ok &= row.get("motors_zero_ms") is not None and row["motors_zero_ms"] <= MOTORS_ZERO_MAX_MS
    ok &= bool(row.get("recovered")) and bool(row.get("map_intact")) and bool(row.get("alive"))
    if "relocalized_s" in row:
        ok &= row["relocalized_s"] is not None and row["relocalized_s"] <= RELOCALIZED_MAX_S
    if "scanning_again_s" in row:
        ok &= row["scanning_again_s"] is not None and row["scanning_again_s"] <= SCANNING_AGAIN_MAX_S
    return bool(ok)

