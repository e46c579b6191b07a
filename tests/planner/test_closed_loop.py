"""Closed loop: explore a generated maze with the planner, DWA and wheel control on the simulated robot.

The SLAM stage is replaced by ground truth so this tests planning and control alone:
the pose is the simulator's true pose, and the map is the true occupancy raster revealed
cell by cell as the lidar would see it (every grid cell a ray crosses up to its hit, rays
shorter than the lidar's 0.15 m minimum range seeing nothing). Everything else is the
real chain at its real rates: lidar scan and planner at 5 Hz (map reveal, maze graph,
exploration, global path, then the DWA on the scan and map points), wheel PI at 20 Hz on
encoder-quantised wheel speeds, the safety layer in front of the motors, and the default
physics (unmatched motors, slip, deadband, motor lag) with one control period of
actuation latency.

Every test runs the daemon's own parts (:func:`run_daemon_exploration`): a
:class:`~mazebot.planner.pilot.Pilot` and a :class:`~mazebot.tasks.control_task.MotorControl`
built from a :class:`~mazebot.config.Config` as ``mazebot/main.py`` builds them, talking
through the shared state; a default changed in the config is what it drives with, and
what a test varies (the strategy, the mode) it sets in the config.

Run as a script to print the measured figures for a range of seeds::

    .venv/bin/python tests/planner/test_closed_loop.py --kind braided --seeds 1-30 [--strategy dfs] [--map grid]
        [--mode frontier] [--size 4]

(``--map grid`` builds the map with a real log-odds :class:`OccupancyGrid` from noisy
ranges instead of revealing the perfect one; ``--kind room`` is the room with cylinders.)
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from dataclasses import dataclass, field

import numpy as np
import pytest

from mazebot.config import Config
from mazebot.io.scan import Scan
from mazebot.planner.exploration import Explorer
from mazebot.planner.maze_graph import Direction, LinkState
from mazebot.planner.pilot import Pilot, PilotParams
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.physics import PhysicsParams, RobotPhysics
from mazebot.sim.raster import free_reachable, true_occupancy
from mazebot.sim.raycast import RayCaster
from mazebot.sim.room import make_room
from mazebot.sim.world import World, world_from_layout
from mazebot.slam.grid import OccupancyGrid
from mazebot.state import Pose2D, RunState, SharedState
from mazebot.tasks.control_task import MotorControl

pytestmark = pytest.mark.slow  # closed-loop runs of the simulated robot

RES_M = 0.02
LIDAR_MIN_M = Config().lidar.min_range_m  # the revealed map sees nothing closer, as the lidar
MISS_FREE_M = 4.0
PHYSICS_DT_S = 0.01


class RevealedMap:
    """The true occupancy of a world, known only where a simulated lidar has looked."""

    def __init__(self, world: World, resolution_m: float = RES_M, margin_m: float = 0.4) -> None:
        xmin, ymin, xmax, ymax = world.bounds_m
        self.resolution_m = resolution_m
        self.origin_m = (
            math.floor((xmin - margin_m) / resolution_m) * resolution_m,
            math.floor((ymin - margin_m) / resolution_m) * resolution_m,
        )
        shape = (
            math.ceil((ymax + margin_m - self.origin_m[1]) / resolution_m),
            math.ceil((xmax + margin_m - self.origin_m[0]) / resolution_m),
        )
        self.occupied, _ = true_occupancy(world, resolution_m, self.origin_m, shape)
        self.known = np.zeros(shape, dtype=bool)

    def reveal(self, xy_m: tuple[float, float], angles_world_rad: np.ndarray, ranges_m: np.ndarray) -> None:
        """Mark every cell along each valid ray, up to and including the cell it hits."""
        ok = (ranges_m >= LIDAR_MIN_M) & np.isfinite(ranges_m)
        reach = np.where(ok, ranges_m + 0.5 * self.resolution_m, 0.0)
        miss = ~np.isfinite(ranges_m)
        reach[miss] = MISS_FREE_M  # no return: free only this far (the SLAM grid's max_free_range_m)
        step = 0.5 * self.resolution_m
        counts = np.ceil(reach / step).astype(np.int64)
        ray = np.repeat(np.arange(counts.size), counts)
        k = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        d = k * step
        x = xy_m[0] + d * np.cos(angles_world_rad[ray])
        y = xy_m[1] + d * np.sin(angles_world_rad[ray])
        c = np.floor((x - self.origin_m[0]) / self.resolution_m).astype(np.int64)
        r = np.floor((y - self.origin_m[1]) / self.resolution_m).astype(np.int64)
        inside = (r >= 0) & (r < self.known.shape[0]) & (c >= 0) & (c < self.known.shape[1])
        self.known[r[inside], c[inside]] = True

    def three_state(self) -> np.ndarray:
        return np.where(self.known, np.where(self.occupied, 100, 0), -1).astype(np.int8)


class LidarMap:
    """A real log-odds :class:`OccupancyGrid` fed with noisy ranges from the true pose.

    Not a perfect map: walls are bands of cells that needed two hits, range noise (1 % of
    the range) blurs them and 2 % of the returns drop out, as with the emulated A1. It
    shows the graph builder and the frontier search on the kind of map SLAM publishes.
    """

    def __init__(self, rng: np.random.Generator, noise: float = 0.01, dropout: float = 0.02) -> None:
        self.grid = OccupancyGrid(resolution_m=RES_M, occupied_prob=0.75, max_free_range_m=MISS_FREE_M)
        self.rng, self.noise, self.dropout = rng, noise, dropout

    def reveal(self, xy_m: tuple[float, float], angles_world_rad: np.ndarray, ranges_m: np.ndarray) -> None:
        hit = np.isfinite(ranges_m)
        noisy = np.where(hit, ranges_m * (1.0 + self.noise * self.rng.standard_normal(ranges_m.size)), MISS_FREE_M)
        keep = (~hit | (noisy >= LIDAR_MIN_M)) & (self.rng.random(ranges_m.size) >= self.dropout)
        ends = np.column_stack((xy_m[0] + noisy * np.cos(angles_world_rad), xy_m[1] + noisy * np.sin(angles_world_rad)))
        self.grid.integrate(np.array([xy_m[0], xy_m[1], 0.0]), ends[keep], hit[keep])

    @property
    def origin_m(self) -> tuple[float, float]:
        return self.grid.origin_m

    def three_state(self) -> np.ndarray:
        return self.grid.three_state()


@dataclass
class RunResult:
    done: bool
    time_s: float
    path_m: float
    collisions: int
    safety_stops: int
    longest_still_s: float
    coverage: float
    explorer: Explorer
    final_xy_m: tuple[float, float]
    start_xy_m: tuple[float, float]
    statuses: dict[str, int] = field(default_factory=dict)
    fault: str | None = None  # the fault that ended the run, if one did

    @property
    def avg_speed_mps(self) -> float:
        return self.path_m / self.time_s if self.time_s > 0 else 0.0


@dataclass
class StillClock:
    """The longest time the robot stood still so far (the explorer should never hold it up for long)."""

    since_s: float = 0.0
    longest_s: float = 0.0

    def update(self, physics: RobotPhysics) -> None:
        body_v, body_w = physics.body_velocity
        if abs(body_v) > 0.01 or abs(body_w) > 0.05:
            self.since_s = physics.time_s
        self.longest_s = max(self.longest_s, physics.time_s - self.since_s)


def finished(
    world: World,
    physics: RobotPhysics,
    truth: RevealedMap,
    still: StillClock,
    *,
    done: bool,
    safety_stops: int,
    explorer: Explorer,
    statuses: dict[str, int],
    fault: str | None = None,
) -> RunResult:
    """The run's figures: the robot's, and the coverage measured on the revealed truth."""
    reachable, _ = free_reachable(world, RES_M, 0.09, truth.origin_m, truth.known.shape)
    return RunResult(
        done=done,
        time_s=physics.time_s,
        path_m=physics.odometer_m,
        collisions=physics.collisions,
        safety_stops=safety_stops,
        longest_still_s=still.longest_s,
        coverage=float((reachable & truth.known).sum() / reachable.sum()),
        explorer=explorer,
        final_xy_m=(physics.x_m, physics.y_m),
        start_xy_m=(world.start_pose[0], world.start_pose[1]),
        statuses=statuses,
        fault=fault,
    )


def run_daemon_exploration(
    world: World,
    seed: int = 0,
    time_limit_s: float = 300.0,
    config: Config | None = None,
    map_source: str = "truth",
    freeze_map_after_s: float | None = None,
) -> RunResult:
    """Drive the robot with the daemon's own planner and control, built from ``config`` as it builds them,
    until the run is done or the time limit; returns the figures.

    The planner is a :class:`Pilot` from :meth:`PilotParams.from_config` ticked at its
    configured rate, the wheels a :class:`MotorControl` (wheel PI, encoder speeds, safety
    layer) at the control period, and they talk through a :class:`SharedState` as the
    planner and control tasks do: pose, map and scan in, ``motion_command`` between them,
    ``run_state`` out. So a default the daemon uses is the one this run uses. SLAM is
    the same ground-truth stand-in (true pose; the revealed map, or a :class:`LidarMap`
    with ``map_source="grid"``); the throttles reach the motors after the configured
    actuation latency. From ``freeze_map_after_s`` on, the map no longer changes and every
    revolution counts as held back (SLAM distrusting the odometry: it localizes, paints
    nothing), as a run ends when it faults.
    """
    config = config if config is not None else Config()
    rng = np.random.default_rng(seed)
    physics = RobotPhysics(PhysicsParams(), world, world.start_pose, rng)
    truth = RevealedMap(world)
    planner_map: RevealedMap | LidarMap = truth if map_source == "truth" else LidarMap(np.random.default_rng(seed + 1))
    caster = RayCaster.for_world(world)
    angles = np.linspace(-math.pi, math.pi, 360, endpoint=False)

    pilot = Pilot(PilotParams.from_config(config))
    control = MotorControl.from_config(config)
    planner_every = round(pilot.params.period_s / PHYSICS_DT_S)
    control_every = round(control.period_s / PHYSICS_DT_S)
    pending = [(0.0, 0.0)] * round(config.control.actuation_latency_s / control.period_s)
    ticks_per_rev = config.encoders.ticks_per_rev
    lidar = config.lidar
    mount_xy = np.array([lidar.mount_x_m, lidar.mount_y_m])
    lidar_yaw_rad = math.radians(lidar.mount_yaw_deg)

    state = SharedState()
    state.run_state = RunState.EXPLORING
    state.started_at_s = 0.0
    state.slam.anchored = True  # the stand-in's map needs no anchoring at rest
    # what the pilot reads of the map is three_state(), origin_m and resolution_m: the grid's face
    state.map = planner_map.grid if isinstance(planner_map, LidarMap) else truth  # type: ignore[assignment]
    still = StillClock()
    statuses: dict[str, int] = {}
    step = 0
    while physics.time_s < time_limit_s and state.run_state not in (RunState.DONE, RunState.FAULT):
        now = physics.time_s
        frozen = freeze_map_after_s is not None and now >= freeze_map_after_s
        pose = physics.pose
        state.pose = Pose2D(*pose)
        if step % planner_every == 0:  # a revolution, then the planner task's tick on it
            c, s = math.cos(pose[2]), math.sin(pose[2])
            lidar_xy = np.array(pose[:2]) + np.array([[c, -s], [s, c]]) @ mount_xy
            ranges = caster.cast(lidar_xy, angles + pose[2] + lidar_yaw_rad, lidar.max_range_m)
            seen_from = (float(lidar_xy[0]), float(lidar_xy[1]))
            if not frozen:
                truth.reveal(seen_from, angles + pose[2] + lidar_yaw_rad, ranges)
                if planner_map is not truth:
                    planner_map.reveal(seen_from, angles + pose[2] + lidar_yaw_rad, ranges)
            state.slam.scans += 1
            state.slam.held_back += frozen
            hit = np.isfinite(ranges)
            state.latest_scan = Scan(
                angle_rad=angles.copy(),
                range_m=np.where(hit, ranges, 0.0),
                quality=np.where(hit, 15, 0).astype(np.uint8),
                time_s=np.full(angles.size, now),
                valid=hit,
                revolution=state.slam.scans,
            )
            pilot.tick(state, now)
            status = pilot.local.status.value
            statuses[status] = statuses.get(status, 0) + 1
        if step % control_every == 0:  # the control task's tick, on the encoders' latest counts
            left_rad, right_rad = physics.wheel_angle_rad
            state.wheel_ticks = (now, *(math.floor(a / math.tau * ticks_per_rev) for a in (left_rad, right_rad)))
            throttles = control.tick(state, now)
            state.throttles = throttles
            pending.append(throttles)
            physics.set_throttle(*pending.pop(0))
        physics.step(PHYSICS_DT_S)
        step += 1
        still.update(physics)

    done = state.run_state is RunState.DONE
    fault = state.active_fault
    return finished(
        world, physics, truth, still, done=done, safety_stops=control.safety.stops, explorer=pilot.explorer,
        statuses=statuses, fault=None if fault is None else f"{fault.source}: {fault.message}",
    )


def maze_world(seed: int, kind: str = "braided", size: int = 6) -> World:
    return world_from_layout(generate_maze(size, size, seed, kind), 0.012)  # type: ignore[arg-type]


def links_match_truth(result: RunResult, world: World) -> list[str]:
    """Every link of every maze cell as the graph sees it, against the true layout; the mismatches."""
    layout = world.maze
    assert layout is not None
    graph = result.explorer.graph
    wrong = []
    for col in range(layout.width):
        for row in range(layout.height):
            for side, direction in (("E", Direction.E), ("N", Direction.N), ("W", Direction.W), ("S", Direction.S)):
                want = LinkState.WALL if layout.has_wall((col, row), side) else LinkState.OPEN
                got = graph.link((col, row), direction)
                if got is not want:
                    wrong.append(f"cell {(col, row)} {side}: {got.name}, truth {want.name}")
    return wrong


@pytest.mark.parametrize(
    ("seed", "kind", "strategy", "map_source"),
    [(1, "braided", "nearest", "truth"), (2, "perfect", "nearest", "truth"), (3, "braided", "dfs", "grid")],
)
def test_explores_a_6x6_maze_and_returns_without_touching_a_wall(
    seed: int, kind: str, strategy: str, map_source: str
) -> None:
    """The daemon's pilot and motor control from the default config (only the strategy chosen here)."""
    world = maze_world(seed, kind)
    config = Config()
    config.planner.strategy = strategy  # type: ignore[assignment]
    result = run_daemon_exploration(world, seed=seed, time_limit_s=300.0, config=config, map_source=map_source)
    assert result.done, f"not done after {result.time_s:.0f} s: {result.statuses}"
    assert result.collisions == 0
    assert links_match_truth(result, world) == []  # every cell explored, every link right
    assert result.coverage >= 0.99
    # back at the start: inside the explorer's 6 cm arrival tolerance of the start cell's
    # centre (as the graph places it, within millimetres of the truth), still rolling to a stop
    assert math.dist(result.final_xy_m, result.start_xy_m) <= 0.07
    assert world.maze is not None and world.maze.cell_at(*result.final_xy_m) == world.maze.start_cell
    assert result.longest_still_s < 30.0
    assert result.explorer.mode == "maze"


@pytest.mark.parametrize("map_source", ["truth", "grid"])
def test_explores_a_room_with_cylinders_by_frontiers(map_source: str) -> None:
    """The daemon's pilot and motor control from the default config: no maze in sight, so frontiers (auto mode)."""
    world = make_room(width_m=2.0, height_m=1.2, cylinders=4, seed=0, footprint_radius_m=0.09)
    result = run_daemon_exploration(world, seed=0, time_limit_s=300.0, config=Config(), map_source=map_source)
    assert result.explorer.mode == "frontier"
    assert result.done
    assert result.collisions == 0
    assert result.coverage >= 0.97
    assert math.dist(result.final_xy_m, result.start_xy_m) <= 0.07


@pytest.mark.parametrize(("size", "seed", "map_source"), [(3, 1, "grid"), (4, 3, "truth")])
def test_frontier_mode_maps_a_1ft_corridor_maze_without_the_cell_graph(size: int, seed: int, map_source: str) -> None:
    """Grid frontiers alone (no maze graph, no lattice) in corridors barely wider than the inflated robot.

    4x4 seed 3 has a side passage first seen in the shadow of a wall end: looking along
    the shadow's edge from where it was cast resolves nothing, and a goal there used to
    hold the robot until it was blacklisted.
    """
    world = maze_world(seed, "braided", size)
    config = Config()
    config.planner.mode = "frontier"
    result = run_daemon_exploration(world, seed=seed, time_limit_s=150.0, config=config, map_source=map_source)
    assert result.explorer.mode == "frontier"
    assert result.done, f"not done after {result.time_s:.0f} s: {result.explorer.events}"
    assert result.collisions == 0
    assert result.coverage >= 0.98
    assert math.dist(result.final_xy_m, result.start_xy_m) <= 0.07
    assert not [e for e in result.explorer.events if e.startswith("blacklisted")]  # every goal it chose saw something


@pytest.mark.parametrize("stand_still_revolutions", [45, 30])
def test_a_robot_whose_map_stops_changing_never_stands_for_ever(stand_still_revolutions: int) -> None:
    """SLAM that paints no revolution (held back: the odometry distrusted) freezes the explorer's clocks.

    The explorer counts a target's dwell and progress in *painted* revolutions; with none
    painted, a robot standing at an unresolved target waited for ever (two bench runs of
    the cheap robot sat 850 s in ``returning``). The pilot's own count of revolutions stood
    gives the goal up, backs off, and at worst stops with a fault that says why. Without
    it (``stand_still_revolutions`` 2000) this run stood 192 of its 200 s at one place.
    """
    world = maze_world(1, "braided", 4)
    config = Config()
    config.planner.stand_still_revolutions = stand_still_revolutions
    result = run_daemon_exploration(world, seed=1, time_limit_s=240.0, config=config, freeze_map_after_s=5.0)
    ended = result.done or (result.fault is not None and result.fault.startswith("planner: stood still"))
    assert ended, f"neither done nor stopped with a reason after {result.time_s:.0f} s: {result.explorer.events}"
    assert result.time_s < 240.0
    # a step each stand_still_revolutions (5 revolutions a second here), three steps at most
    assert result.longest_still_s < 3 * stand_still_revolutions / 5.0 + 5.0
    assert result.collisions == 0


def test_a_table_leg_that_closes_a_corridor_is_gone_round_and_the_robot_comes_home() -> None:
    """A 4 cm leg on the centre line of the corridor between cells (1, 1) and (1, 2) of a braided 4x4 maze.

    The link stays open on the map (the leg stands 6 cm off the boundary line), but no lane is left
    for the body (0.126 m either side of the leg for a 0.2 m robot with the DWA's margin). The
    maze has another way round (through (1, 0), (2, 0), ... (1, 3)). Without the closed passage the
    planner sent the robot at the leg again and again: it stood there until the stand-still watch
    stopped it with a fault, not done, half the maze unseen.
    """
    world = maze_world(2, "braided", 4)
    assert world.maze is not None
    x, y = world.maze.cell_center_m((1, 2))
    leg = (x, y - (world.maze.cell_size_m / 2 - 0.06), 0.02)
    world = dataclasses.replace(world, circles=np.array([leg]))
    result = run_daemon_exploration(world, seed=2, time_limit_s=240.0, config=Config())
    assert result.done, f"not done after {result.time_s:.0f} s: {result.fault}"
    assert result.collisions == 0
    assert result.coverage >= 0.98
    assert math.dist(result.final_xy_m, result.start_xy_m) <= 0.07
    assert [p.link for p in result.explorer.closed_passages] == [((1, 1), Direction.N)]  # where the leg stands


def main(argv: list[str]) -> None:
    """Print the figures of one run per seed and a summary (see the module docstring)."""
    parser = argparse.ArgumentParser(description="closed-loop exploration figures (simulated, true pose)")
    parser.add_argument("--kind", default="braided", choices=["braided", "perfect", "rooms", "room"])
    parser.add_argument("--strategy", default="nearest", choices=["nearest", "dfs"])
    parser.add_argument("--map", dest="map_source", default="truth", choices=["truth", "grid"])
    parser.add_argument("--mode", default="auto", choices=["auto", "maze", "frontier"])
    parser.add_argument("--size", type=int, default=6, help="maze cells per side")
    parser.add_argument("--seeds", default="1-3", help="first-last (inclusive)")
    args = parser.parse_args(argv)
    first, _, last = args.seeds.partition("-")
    rows = []
    for seed in range(int(first), int(last or first) + 1):
        if args.kind == "room":
            world = make_room(2.0, 1.2, cylinders=4, seed=seed, footprint_radius_m=0.09)
        else:
            world = maze_world(seed, args.kind, args.size)
        config = Config()
        config.planner.strategy, config.planner.mode = args.strategy, args.mode
        r = run_daemon_exploration(world, seed=seed, config=config, map_source=args.map_source)
        wrong = len(links_match_truth(r, world)) if world.maze is not None else 0
        rows.append((r.done, r.time_s, r.path_m, r.collisions, r.coverage, wrong, r.longest_still_s))
        print(
            f"seed {seed} {args.kind}: done={r.done} time={r.time_s:.1f} s path={r.path_m:.2f} m "
            f"avg={r.avg_speed_mps:.3f} m/s collisions={r.collisions} coverage={r.coverage:.3f} "
            f"wrong_links={wrong} longest_still={r.longest_still_s:.1f} s safety_stops={r.safety_stops}",
            flush=True,
        )
    times = sorted(row[1] for row in rows)
    print(
        f"{args.kind} {args.strategy} {args.map_source}: done {sum(row[0] for row in rows)}/{len(rows)}, "
        f"time median {times[len(times) // 2]:.1f} s max {times[-1]:.1f} s, "
        f"path median {sorted(row[2] for row in rows)[len(rows) // 2]:.2f} m, "
        f"collisions {sum(row[3] for row in rows)}, coverage min {min(row[4] for row in rows):.3f}, "
        f"wrong links {sum(row[5] for row in rows)}, longest still {max(row[6] for row in rows):.1f} s"
    )


if __name__ == "__main__":
    main(sys.argv[1:])
