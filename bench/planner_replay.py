"""Replay what the explorer and the DWA saw in one simulated run, for repeatable planner timing.

The planner tick is a function of its inputs: the explorer's of the map, the pose and the
revolution count of each tick (and the local planner's "unreachable" reports), the DWA's
of the pose, the velocity, the obstacle points and the path. Capture them in one
virtual-time run of the whole daemon, then replay them as often as wanted, with any
version of the code on ``PYTHONPATH``::

    .venv/bin/python bench/planner_replay.py capture --seed 1 --out /tmp/planner1.pkl
    .venv/bin/python bench/planner_replay.py capture --maze $MAZEBOT_DATA/mazes/classic/shi2.txt --out /tmp/shi2.pkl
    .venv/bin/python bench/planner_replay.py replay /tmp/planner1.pkl [--repeat 3]

``replay`` prints the thread CPU per call (the minimum over ``--repeat`` passes) of the
explorer's half of a tick (its update and the pilot's coverage), of one DWA step (costmap
and plan) and of the maze graph's wall outlines, and a digest of each one's output
(goals, coverage and events; the DWA's choices and every rollout's score; the outline
points): two code versions that print the same digests decided the same.
"""

from __future__ import annotations

import argparse
import hashlib
import pickle
import time
from collections.abc import Generator
from typing import Any

import numpy as np

from mazebot.bench.runner import RunSpec, run_one
from mazebot.config import load_config
from mazebot.planner import dwa, exploration, pilot
from mazebot.planner.pilot import Pilot, PilotParams

#: DWA steps kept by a capture (a 6x6 run has about 300, a 16x16 contest maze about 1 500).
MAX_DWA_STEPS = 4000


def capture(seed: int, out: str, maze_path: str | None = None) -> None:
    events: list[tuple[Any, ...]] = []  # the explorer's, in order
    steps: list[dict[str, Any]] = []  # the DWA's inputs
    real_update = exploration.Explorer.update_steps
    real_unreachable = exploration.Explorer.report_unreachable
    real_new_explorer = pilot.Pilot._new_explorer
    real_plan = dwa.DynamicWindowPlanner.plan_steps

    def update_steps(self: Any, three: Any, origin: Any, resolution_m: float, pose: Any, revolutions: Any = None
                     ) -> Generator[None, None, Any]:
        events.append(("update", np.array(three, copy=True), tuple(origin), float(resolution_m),
                       tuple(float(v) for v in pose), revolutions))
        return (yield from real_update(self, three, origin, resolution_m, pose, revolutions))

    def report_unreachable(self: Any, now_s: float | None = None) -> None:
        events.append(("unreachable",))
        real_unreachable(self, now_s)

    def new_explorer(self: Any, start_xy_m: tuple[float, float]) -> Any:
        events.append(("new", tuple(start_xy_m)))
        return real_new_explorer(self, start_xy_m)

    def plan_steps(self: Any, pose: Any, velocity: Any, costmap: Any, path: Any, v_cap_mps: Any = None
                   ) -> Generator[None, None, Any]:
        if len(steps) < MAX_DWA_STEPS:
            steps.append({
                "pose": tuple(pose), "velocity": tuple(velocity), "scan": costmap.scan_points.copy(),
                "map": costmap.map_points.copy(), "map_radius_m": costmap.map_point_radius_m,
                "footprint_m": costmap.footprint_radius_m,
                "clearance_m": costmap.inflation_m - costmap.footprint_radius_m,
                "path": path.points.copy(), "progress_m": path.progress_m, "v_cap_mps": v_cap_mps,
            })
        return (yield from real_plan(self, pose, velocity, costmap, path, v_cap_mps))

    exploration.Explorer.update_steps = update_steps  # type: ignore[method-assign]
    exploration.Explorer.report_unreachable = report_unreachable  # type: ignore[method-assign]
    pilot.Pilot._new_explorer = new_explorer  # type: ignore[method-assign]
    dwa.DynamicWindowPlanner.plan_steps = plan_steps  # type: ignore[method-assign]
    spec = RunSpec(maze_path, None if maze_path else (6, 6), seed, "explore")
    metrics, _ = run_one(load_config(None), spec)
    print({k: metrics.get(k) for k in ("done", "coverage", "collisions", "ate_rms_m", "time_s")})
    with open(out, "wb") as f:
        pickle.dump({"explorer": events, "dwa": steps}, f)
    print(f"{sum(e[0] == 'update' for e in events)} explorer ticks, {len(steps)} DWA steps -> {out}")


def _explorer_pass(pilot_: Pilot, events: list[tuple[Any, ...]]) -> tuple[float, float, int, str, str]:
    """(CPU s of the explorer's halves, CPU s of the wall outlines, ticks, goal digest, outline digest)."""
    goals, walls = hashlib.sha256(), hashlib.sha256()
    cpu_s = walls_s = 0.0
    ticks = 0
    explorer = None
    for event in events:
        if event[0] == "new":
            explorer = pilot_.explorer = pilot_._new_explorer(event[1])
            continue
        assert explorer is not None
        if event[0] == "unreachable":
            explorer.report_unreachable()
            continue
        _, three, origin, resolution_m, pose, revolutions = event
        start_s = time.thread_time()
        goal = explorer.update(three, origin, resolution_m, pose, revolutions)
        coverage = pilot_._coverage()
        cpu_s += time.thread_time() - start_s
        ticks += 1
        shown = None if goal is None else (goal.phase, goal.target_m, [tuple(map(float, w)) for w in goal.waypoints_m],
                                           goal.reason)
        goals.update(repr((shown, coverage, list(explorer.events))).encode())
        explorer.events.clear()
        start_s = time.thread_time()
        points = explorer.graph.wall_points_m(pose[:2], pilot_.params.planner.map_window_m)
        walls_s += time.thread_time() - start_s
        walls.update(np.ascontiguousarray(points).tobytes())
    return cpu_s, walls_s, ticks, goals.hexdigest()[:16], walls.hexdigest()[:16]


def _dwa_pass(pilot_: Pilot, steps: list[dict[str, Any]]) -> tuple[float, str]:
    """(CPU s of the DWA steps, digest of their choices and scores)."""
    planner = pilot_.local.dwa
    digest = hashlib.sha256()
    cpu_s = 0.0
    for s in steps:
        start_s = time.thread_time()
        costmap = dwa.LocalCostmap(s["scan"], s["map"], s["map_radius_m"], s["footprint_m"], s["clearance_m"])
        path = dwa.PathTrack(s["path"])
        path.progress_m = s["progress_m"]
        choice = planner.plan(s["pose"], s["velocity"], costmap, path, s["v_cap_mps"])
        cpu_s += time.thread_time() - start_s
        r = choice.rollouts
        digest.update(repr((choice.v_mps, choice.w_radps, choice.blocked)).encode())
        for a in (r.v_mps, r.w_radps, r.admissible, r.score, r.free_m):
            digest.update(np.ascontiguousarray(a).tobytes())
    return cpu_s, digest.hexdigest()[:16]


def replay(path: str, repeat: int) -> None:
    with open(path, "rb") as f:
        data = pickle.load(f)
    pilot_ = Pilot(PilotParams.from_config(load_config(None)))
    best: dict[str, float] = {}
    digests: set[tuple[str, ...]] = set()

    def keep(name: str, value: float) -> None:
        best[name] = min(best.get(name, float("inf")), value)

    ticks = 0
    for _ in range(repeat):
        cpu_s, walls_s, ticks, goals, walls = _explorer_pass(pilot_, data["explorer"])
        dwa_s, choices = _dwa_pass(pilot_, data["dwa"])
        keep("explorer", cpu_s / max(ticks, 1))
        keep("walls", walls_s / max(ticks, 1))
        keep("dwa", dwa_s / max(len(data["dwa"]), 1))
        digests.add((goals, walls, choices))
    (goals, walls, choices), = digests  # every pass decides the same
    print(f"explorer half of a tick: {best['explorer'] * 1e3:.3f} ms ({ticks} ticks), digest {goals}")
    print(f"wall outlines: {best['walls'] * 1e3:.3f} ms a call, digest {walls}")
    print(f"DWA step: {best['dwa'] * 1e3:.3f} ms ({len(data['dwa'])} steps), digest {choices}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    cap = sub.add_parser("capture", help="run a simulated exploration and keep the planner's inputs")
    cap.add_argument("--seed", type=int, default=1)
    cap.add_argument("--maze", default=None, help="a maze file (default: the generated 6x6 maze of --seed)")
    cap.add_argument("--out", required=True)
    rep = sub.add_parser("replay", help="replay a capture: CPU per call and digests of the outputs")
    rep.add_argument("capture")
    rep.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    if args.command == "capture":
        capture(args.seed, args.out, args.maze)
    else:
        replay(args.capture, args.repeat)


if __name__ == "__main__":
    main()
