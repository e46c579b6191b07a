"""Pose-graph optimization benchmark: mazebot's optimizer against GTSAM on the same g2o files.

Run from the repository root::

    .venv/bin/python bench/posegraph_bench.py --runs 5

Each graph in ``../shared/data/posegraphs/`` is read once, then optimized ``--runs`` times
from its original initial guess (first pose fixed, Levenberg–Marquardt unless
``--method gn``). The time is the wall-clock time of ``PoseGraph.optimize`` (structure
analysis, ordering, every linearization and factorization; reading the file is not
included), reported as the median over the runs, with the fastest run and the median
CPU time of the process (all threads; less sensitive to other load on the machine). The
GTSAM reference (chi2, iterations, seconds, GTSAM 4.3 LM on this machine) is read from
the table in ``../shared/data/README.md``; ``ratio`` is our median wall-clock seconds
divided by GTSAM's (below 1 is faster). Prints a markdown table.

A second table compares plain LM with LM after ``initialize="orientations"`` (headings,
then positions, by linear least squares; see ``mazebot.slam.posegraph``) from poor
initial guesses, the case plain LM can stall in a worse local minimum:

- ``file``: the graph's own initial guess;
- ``odometry+noise``: the odometry edges ``i -> i+1`` composed from the first pose, with
  Gaussian noise of ``--heading-noise`` rad added to every step's rotation (seeded);
- ``scrambled``: every position at the origin, every heading uniform in [-π, π)
  (seeded); the first pose is kept.

Both runs of a pair start from the same poses; ``chi2 init`` is the cost after the
initialization, ``s`` includes it. ``--iterations`` caps that table's runs (default
50, the optimizer's default); ``--tables`` picks the tables to print::

    .venv/bin/python bench/posegraph_bench.py --runs 5 --tables init --iterations 1000
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mazebot.geometry import wrap_angle
from mazebot.slam.g2o import read_g2o
from mazebot.slam.posegraph import OptimizeResult, PoseGraph

DATA_DIR = Path(os.environ.get("MAZEBOT_DATA", Path(__file__).resolve().parents[1] / ".." / "shared" / "data"))
GRAPHS = ("input_M3500_g2o", "input_MITb_g2o")

#: a row of the README's GTSAM table: | graph | poses | chi2 after | iterations | seconds |
_README_ROW = re.compile(r"^\|\s*(\S+)\s*\|\s*(\d+)\s*\|\s*([\d.]+)\s*\|\s*(\d+)\s*\|\s*([\d.]+)\s*\|\s*$")


@dataclass(frozen=True)
class Reference:
    chi2: float
    iterations: int
    seconds: float


def gtsam_references(readme: Path) -> dict[str, Reference]:
    """GTSAM's results per graph name, from the data README's table."""
    references = {}
    for line in readme.read_text(encoding="utf-8").splitlines():
        match = _README_ROW.match(line.strip())
        if match:
            name, _, chi2, iterations, seconds = match.groups()
            references[name] = Reference(float(chi2), int(iterations), float(seconds))
    return references


def timed_runs(
    graph: PoseGraph, start: np.ndarray, runs: int, method: str, initialize: str = "none", max_iterations: int = 50
) -> tuple[OptimizeResult, list[float], list[float]]:
    """Optimize ``runs`` times from ``start``: (last result, wall-clock seconds, CPU seconds)."""
    seconds = []
    cpu_seconds = []
    result = None
    for _ in range(runs):
        graph.vertices = start
        start_s = time.perf_counter()
        start_cpu_s = time.process_time()
        result = graph.optimize(max_iterations=max_iterations, method=method, initialize=initialize)  # type: ignore[arg-type]
        cpu_seconds.append(time.process_time() - start_cpu_s)
        seconds.append(time.perf_counter() - start_s)
    assert result is not None
    return result, seconds, cpu_seconds


def bench_graph(path: Path, runs: int, method: str) -> dict[str, float | int | bool]:
    graph = read_g2o(path)
    result, seconds, cpu_seconds = timed_runs(graph, graph.vertices.copy(), runs, method)
    return {
        "poses": len(graph),
        "edges": graph.edge_count,
        "chi2_before": result.chi2_before,
        "chi2_after": result.chi2_after,
        "iterations": result.iterations,
        "linear_solves": result.linear_solves,
        "converged": result.converged,
        "median_s": statistics.median(seconds),
        "min_s": min(seconds),
        "cpu_s": statistics.median(cpu_seconds),
    }


def odometry_guess(graph: PoseGraph, heading_noise_rad: float, seed: int) -> np.ndarray:
    """Poses from composing the odometry edges ``i -> i+1`` (or ``i+1 -> i``, inverted) from the
    first pose, each step's rotation perturbed by N(0, heading_noise_rad²); seeded."""
    edge_i, edge_j, z, _ = graph.edge_arrays
    count = len(graph)
    steps = np.full((count, 3), np.nan)
    backward = edge_i == edge_j + 1
    steps[edge_j[backward] + 1] = np.column_stack(
        (  # inverse of z: pose i seen from pose i+1
            -np.cos(z[backward, 2]) * z[backward, 0] - np.sin(z[backward, 2]) * z[backward, 1],
            np.sin(z[backward, 2]) * z[backward, 0] - np.cos(z[backward, 2]) * z[backward, 1],
            -z[backward, 2],
        )
    )
    forward = np.flatnonzero(edge_j == edge_i + 1)[::-1]  # the first forward edge of a pair wins
    steps[edge_j[forward]] = z[forward]
    if np.isnan(steps[1:]).any():
        raise SystemExit(f"no odometry edge {int(np.argmax(np.isnan(steps[1:, 0])))} -> next: no odometry guess")
    rng = np.random.default_rng(seed)
    steps[1:, 2] += rng.normal(0.0, heading_noise_rad, count - 1)
    start = graph.vertices[0]
    headings = start[2] + np.concatenate(([0.0], np.cumsum(steps[1:, 2])))
    previous = headings[:-1]
    moves = np.column_stack(
        (
            np.cos(previous) * steps[1:, 0] - np.sin(previous) * steps[1:, 1],
            np.sin(previous) * steps[1:, 0] + np.cos(previous) * steps[1:, 1],
        )
    )
    positions = start[:2] + np.concatenate((np.zeros((1, 2)), np.cumsum(moves, axis=0)))
    return np.column_stack((positions, wrap_angle(headings)))


def scrambled_guess(graph: PoseGraph, seed: int) -> np.ndarray:
    """Every position at the origin, every heading uniform in [-π, π), the first pose kept; seeded."""
    rng = np.random.default_rng(seed)
    poses = np.zeros((len(graph), 3))
    poses[:, 2] = rng.uniform(-np.pi, np.pi, len(graph))
    poses[0] = graph.vertices[0]
    return poses


def init_table(data: Path, runs: int, method: str, heading_noise_rad: float, seed: int, max_iterations: int) -> None:
    """Plain LM against initialized LM from each poor start, as a markdown table."""
    print(
        f"\nplain vs initialized ({method}, at most {max_iterations} iterations) from poor initial guesses; "
        f"median of {runs} runs; odometry heading noise {heading_noise_rad} rad per step, seed {seed}\n"
    )
    print("| graph | start | init | chi2 start | chi2 init | chi2 final | iterations | converged | median s | min s |")
    print("|---|---|---|---:|---:|---:|---:|---|---:|---:|")
    for name in GRAPHS:
        graph = read_g2o(data / "posegraphs" / f"{name}.g2o")
        starts = {
            "file": graph.vertices.copy(),
            "odometry+noise": odometry_guess(graph, heading_noise_rad, seed),
            "scrambled": scrambled_guess(graph, seed),
        }
        for start_name, start in starts.items():
            for initialize in ("none", "orientations"):
                result, seconds, _ = timed_runs(graph, start, runs, method, initialize, max_iterations)
                chi2_init = "—" if result.chi2_initialized is None else f"{result.chi2_initialized:.2f}"
                print(
                    f"| {name} | {start_name} | {initialize} | {result.chi2_before:.6g} | {chi2_init} "
                    f"| {result.chi2_after:.2f} | {result.iterations} | {'yes' if result.converged else 'no'} "
                    f"| {statistics.median(seconds):.3f} | {min(seconds):.3f} |"
                )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5, help="optimizations per graph (default 5); the median is shown")
    parser.add_argument("--method", choices=("lm", "gn"), default="lm")
    parser.add_argument("--data", type=Path, default=DATA_DIR, help="the shared data directory")
    parser.add_argument(
        "--tables", choices=("gtsam", "init", "all"), default="all", help="which tables to print (default all)"
    )
    parser.add_argument(
        "--heading-noise", type=float, default=0.05, help="rad added per odometry step in the odometry+noise start"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the odometry+noise and scrambled starts")
    parser.add_argument(
        "--iterations", type=int, default=50, help="at most this many iterations in the init table (default 50)"
    )
    args = parser.parse_args(argv)
    if args.runs < 1 or args.iterations < 1:
        parser.error("--runs and --iterations must be at least 1")
    if args.tables in ("gtsam", "all"):
        gtsam_table(args.data, args.runs, args.method)
    if args.tables in ("init", "all"):
        init_table(args.data, args.runs, args.method, args.heading_noise, args.seed, args.iterations)
    return 0


def gtsam_table(data: Path, runs: int, method: str) -> None:
    """Our optimizer from each file's own guess against GTSAM's reference, as a markdown table."""
    references = gtsam_references(data / "README.md")

    print(f"method {method}, median of {runs} runs, first pose fixed\n")
    print(
        "| graph | poses | edges | chi2 before | chi2 after | GTSAM chi2 | chi2 diff | iterations (solves) "
        "| GTSAM iterations | median s | min s | median CPU s | GTSAM s | ratio |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name in GRAPHS:
        path = data / "posegraphs" / f"{name}.g2o"
        row = bench_graph(path, runs, method)
        ref = references.get(name)
        chi2_diff = f"{100 * (row['chi2_after'] - ref.chi2) / ref.chi2:+.2f} %" if ref else "—"
        ratio = f"{row['median_s'] / ref.seconds:.2f}" if ref else "—"
        converged = "" if row["converged"] else " (not converged)"
        print(
            f"| {name} | {row['poses']} | {row['edges']} | {row['chi2_before']:.6g} "
            f"| {row['chi2_after']:.2f}{converged} "
            f"| {ref.chi2 if ref else '—'} | {chi2_diff} | {row['iterations']} ({row['linear_solves']}) "
            f"| {ref.iterations if ref else '—'} | {row['median_s']:.3f} | {row['min_s']:.3f} | {row['cpu_s']:.3f} "
            f"| {ref.seconds if ref else '—'} | {ratio} |"
        )


if __name__ == "__main__":
    sys.exit(main())
