"""``mazebot posegraph optimize``: optimize a g2o 2D pose graph from the command line.

Reads ``IN.g2o``, runs ``PoseGraph.optimize`` and prints one JSON line
``{"poses", "edges", "chi2_initial", "chi2_final", "iterations", "seconds", ...}``
(chi2 = sum of squared Mahalanobis residuals); ``--text`` prints two human lines
instead. ``--init orientations`` replaces the file's initial guess first (headings by
linear least squares, then positions; see ``mazebot.slam.posegraph``): use it when the
initial guess is poor; ``chi2_initialized`` then reports the cost after that step and
``seconds`` includes it. ``--out`` writes the optimized graph (atomically) in the same format, keeping
vertex ids, edges and ``FIX`` lines.

Example::

    mazebot posegraph optimize ../shared/data/posegraphs/input_MITb_g2o.g2o --out /tmp/mit.g2o
    mazebot posegraph optimize ../shared/data/posegraphs/input_MITb_g2o.g2o --init orientations
"""

from __future__ import annotations

import argparse
import json
import math

from mazebot.argtypes import positive_int
from mazebot.errors import EXIT_OK, UsageError
from mazebot.slam.g2o import read_g2o, write_g2o


def _cmd_optimize(args: argparse.Namespace) -> int:
    graph = read_g2o(args.input)
    if len(graph) == 0:
        raise UsageError(f"{args.input}: no VERTEX_SE2 lines; nothing to optimize")
    result = graph.optimize(max_iterations=args.iterations, method=args.method, initialize=args.init)
    if args.out is not None:
        write_g2o(graph, args.out)
    fixed_ids = [graph.vertex_ids[i] for i in sorted(graph.fixed)] or [graph.vertex_ids[0]]
    report = {
        "input": str(args.input),
        "output": None if args.out is None else str(args.out),
        "poses": len(graph),
        "edges": graph.edge_count,
        "fixed": fixed_ids,
        "method": result.method,
        "initialize": result.initialize,
        "chi2_initial": result.chi2_before,
        "chi2_initialized": result.chi2_initialized,
        "chi2_final": result.chi2_after,
        "iterations": result.iterations,
        "linear_solves": result.linear_solves,
        "converged": result.converged,
        "seconds": result.seconds,
        "initialize_seconds": result.initialize_seconds,
    }
    if not args.text:
        print(json.dumps(report))
        return EXIT_OK
    status = "converged" if result.converged else f"not converged after {args.iterations} iterations"
    print(f"{args.input}: {len(graph)} poses, {graph.edge_count} edges, fixed {fixed_ids}")
    if result.chi2_initialized is not None:
        print(
            f"init {result.initialize}: chi2 {_number(result.chi2_before)} -> {_number(result.chi2_initialized)} "
            f"in {result.initialize_seconds:.3f} s"
        )
    print(
        f"{result.method}: chi2 {_number(result.chi2_before)} -> {_number(result.chi2_after)} "
        f"in {result.iterations} iterations ({result.linear_solves} linear solves), {result.seconds:.3f} s, {status}"
    )
    if args.out is not None:
        print(f"wrote {args.out}")
    return EXIT_OK


def _number(value: float) -> str:
    return f"{value:.6g}" if math.isfinite(value) and abs(value) >= 1e6 else f"{value:.4f}"


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    posegraph = sub.add_parser("posegraph", help="2D pose graphs in g2o format")
    psub = posegraph.add_subparsers(dest="posegraph_command", required=True)
    optimize = psub.add_parser(
        "optimize",
        help="optimize a g2o 2D pose graph (VERTEX_SE2, EDGE_SE2, FIX) and report chi2",
        description="Least-squares optimization of a 2D pose graph; the first vertex (or the FIX ones) stays put.",
    )
    optimize.add_argument("input", metavar="IN.g2o", help="pose graph in g2o 2D format")
    optimize.add_argument("--out", metavar="OUT.g2o", default=None, help="write the optimized graph here (atomic)")
    optimize.add_argument(
        "--method",
        choices=("lm", "gn"),
        default="lm",
        help="lm: Levenberg-Marquardt (default, safe from poor initial guesses); gn: plain Gauss-Newton",
    )
    optimize.add_argument(
        "--init",
        choices=("none", "orientations"),
        default="none",
        help="orientations: replace the initial guess by headings, then positions, solved by linear least squares "
        "from the measurements before iterating (for poor initial guesses); none: start from the file's poses "
        "(default)",
    )
    optimize.add_argument(
        "--iterations", type=positive_int, default=50, metavar="N", help="at most N linearizations (default 50)"
    )
    output = optimize.add_mutually_exclusive_group()
    output.add_argument("--json", action="store_true", help="print one JSON line (the default)")
    output.add_argument("--text", action="store_true", help="print human-readable lines instead of JSON")
    optimize.set_defaults(func=_cmd_optimize)
