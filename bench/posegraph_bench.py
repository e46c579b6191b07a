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

from mazebot.slam.g2o import read_g2o

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


def bench_graph(path: Path, runs: int, method: str) -> dict[str, float | int | bool]:
    graph = read_g2o(path)
    initial = graph.vertices.copy()
    seconds = []
    cpu_seconds = []
    result = None
    for _ in range(runs):
        graph.vertices = initial
        start_s = time.perf_counter()
        start_cpu_s = time.process_time()
        result = graph.optimize(method=method)
        cpu_seconds.append(time.process_time() - start_cpu_s)
        seconds.append(time.perf_counter() - start_s)
    assert result is not None
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5, help="optimizations per graph (default 5); the median is shown")
    parser.add_argument("--method", choices=("lm", "gn"), default="lm")
    parser.add_argument("--data", type=Path, default=DATA_DIR, help="the shared data directory")
    args = parser.parse_args(argv)
    if args.runs < 1:
        parser.error("--runs must be at least 1")
    references = gtsam_references(args.data / "README.md")

    print(f"method {args.method}, median of {args.runs} runs, first pose fixed\n")
    print(
        "| graph | poses | edges | chi2 before | chi2 after | GTSAM chi2 | chi2 diff | iterations (solves) "
        "| GTSAM iterations | median s | min s | median CPU s | GTSAM s | ratio |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name in GRAPHS:
        path = args.data / "posegraphs" / f"{name}.g2o"
        row = bench_graph(path, args.runs, args.method)
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
    return 0


if __name__ == "__main__":
    sys.exit(main())
