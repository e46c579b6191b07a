"""``mazebot bench``: simulated runs on virtual time, measured against ground truth."""

from __future__ import annotations

import argparse
import os
import shlex
import signal
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from mazebot.bench.report import write_partial, write_report
from mazebot.bench.runner import RunSpec, run_one
from mazebot.config import Config, load_config
from mazebot.errors import EXIT_OK, UsageError
from mazebot.sim.faults import DEFAULT_AT_S, FAULTS, FaultSpec, parse_fault
from mazebot.sim.maze_file import packaged_maze_path, read_maze_layout

SUITES = ("smoke", "6x6", "standard", "full", "faults")


def suite_specs(suite: str, seeds: int, drive: str, clock: str, first_seed: int = 1) -> list[RunSpec]:
    """The runs of a suite. smoke: one 6x6 maze; 6x6: seeds x 6x6; standard: 6x6 + an 8x8 training maze;
    full: standard + generated 8x8 + the 5x5 training maze + a 16x16 contest maze;
    faults: every fault of :data:`mazebot.sim.faults.FAULTS` in its own run of the 6x6 maze (of each seed).
    Generated mazes take the seeds ``first_seed .. first_seed + seeds - 1``; above 1 the
    suite's fixed mazes are left out, so a suite can be split over several processes."""
    if suite == "faults":
        return [RunSpec(None, (6, 6), seed, drive, clock=clock, faults=(FaultSpec(name),))
                for seed in range(first_seed, first_seed + seeds) for name in FAULTS]
    n_seeds = 1 if suite == "smoke" else seeds
    specs = [RunSpec(None, (6, 6), seed, drive, clock=clock) for seed in range(first_seed, first_seed + n_seeds)]
    if suite in ("standard", "full") and first_seed == 1:
        specs.append(RunSpec(str(packaged_maze_path("training-8x8-test1.txt")), None, 1, drive, clock=clock))
    if suite == "full":
        specs += [RunSpec(None, (8, 8), seed, drive, clock=clock, max_sim_s=1800)
                  for seed in range(first_seed, first_seed + seeds)]
        specs.append(RunSpec(str(packaged_maze_path("minimaze.txt")), None, 1, drive, clock=clock))
        specs.append(RunSpec(str(packaged_maze_path("japan2013ef.txt")), None, 1, drive, clock=clock, max_sim_s=3600))
    return specs


SIM_S_PER_CELL = 14.0  # a 16x16 contest maze: 3584 s, the suite's own limit for japan2013ef


def time_limit_s(maze_path: str) -> float:
    """Simulated seconds a run of this maze file may take: 900 s, or 14 s a reachable cell.

    A 6x6 maze is mapped in ~80 s and a 16x16 one needs ~10 min, so one fixed limit would
    either cut the large mazes short (and call them not done) or let a stuck small run go on.
    Cells are counted from the start cell: training mazes sit small inside a 16x16 frame.
    """
    return max(900.0, SIM_S_PER_CELL * len(read_maze_layout(maze_path).reachable()))


def parse_size(text: str) -> tuple[int, int]:
    """``WxH`` (cells) of a generated maze, e.g. ``16x16``."""
    try:
        w_text, h_text = text.lower().split("x")
        w, h = int(w_text), int(h_text)
    except ValueError:
        raise UsageError(f"--size must be WxH in cells, e.g. 16x16, got {text!r}") from None
    if w < 2 or h < 2:
        raise UsageError(f"--size needs at least 2x2 cells, got {text!r}")
    return w, h


def generated_specs(size: tuple[int, int], seeds: range, drive: str, clock: str) -> list[RunSpec]:
    """Generated mazes of one size, one run per seed, with the time limit of a maze file of
    that many cells (a 16x16 tour needs far more than the 6x6's 900 s)."""
    max_sim_s = max(900.0, SIM_S_PER_CELL * size[0] * size[1])
    return [RunSpec(None, size, s, drive, clock=clock, max_sim_s=max_sim_s) for s in seeds]


def _progress(i: int, n: int, text: str) -> None:
    width = 30
    filled = int(width * i / n)
    bar = "#" * filled + "-" * (width - filled)
    end = "\r" if sys.stderr.isatty() and i < n else "\n"
    print(f"[{bar}] {i}/{n} {text}", end=end, file=sys.stderr, flush=True)


def parse_quota(text: str) -> float | None:
    """``--cpu-quota``: a percentage of one core (above 0; above 100 is several cores), or
    ``max`` for no limit (the same processes and accounting, nothing throttled)."""
    if text.lower() in ("max", "unlimited", "none"):
        return None
    try:
        percent = float(text.rstrip("%"))
    except ValueError:
        raise UsageError(f"--cpu-quota must be a percentage of one core (e.g. 25) or max, got {text!r}") from None
    cores = os.cpu_count() or 1
    if not 0.0 < percent <= 100.0 * cores:
        raise UsageError(f"--cpu-quota must be above 0 and at most {100 * cores} % (this machine's {cores} cores), "
                         f"got {text!r}")
    return percent


def _cmd_bench_quota(args: argparse.Namespace, config: Config, specs: list[RunSpec], command: str) -> int:
    """The daemon under a CPU quota, the world in its own process (:mod:`mazebot.bench.quota_run`)."""
    from mazebot.bench.report import write_quota_report

    percent = parse_quota(args.cpu_quota)
    if args.clock == "virtual":
        raise UsageError("--cpu-quota runs on the real clock; leave out --clock virtual")
    for spec in specs:
        if spec.drive != "explore":
            raise UsageError("--cpu-quota runs --drive explore only (the scripted tour reads the true pose, "
                             "which lives in the world's process)")
        if spec.faults:
            raise UsageError("--cpu-quota does not inject --faults (the injector reaches into both processes)")
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    runs: list[dict[str, Any]] = []
    _progress(0, len(specs), "starting")
    # SIGTERM (e.g. to the whole process group) ends the runs as Ctrl-C does: daemon, world, cgroup
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        _quota_runs(args, config, specs, percent, runs)
    finally:
        signal.signal(signal.SIGTERM, previous)
    write_quota_report(out_dir, runs, command)
    print(f"wrote {out_dir / 'results.json'} and {out_dir / 'report.md'} ({len(specs)} runs)", file=sys.stderr)
    return EXIT_OK if all(r["done"] for r in runs) else 1


def _quota_runs(args: argparse.Namespace, config: Config, specs: list[RunSpec], percent: float | None,
                runs: list[dict[str, Any]]) -> None:
    from mazebot.bench.cgroup import CpuQuota
    from mazebot.bench.quota_run import quota_metrics, run_two_process

    for i, spec in enumerate(specs, 1):
        cfg = config.model_copy(deep=True)
        cfg.sim.seed = spec.seed
        cfg.sim.world = spec.world  # type: ignore[assignment]
        cfg.daemon.exit_on_fault = True
        with CpuQuota.create(f"mazebot-bench-{os.getpid()}-{i}", percent) as group:
            record = run_two_process(
                cfg, spec.maze_path, spec.seed if not spec.maze_path else None,
                spec.size if not spec.maze_path else None, spec.max_sim_s, group,
            )
        metrics = quota_metrics(cfg, spec, record)
        runs.append(metrics)
        _progress(i, len(specs), f"{spec.name} seed {spec.seed} at {args.cpu_quota} % of one core: "
                  f"done={metrics['done']} in {metrics['time_s']} s, daemon CPU {metrics['daemon_cpu_percent']} % "
                  f"({metrics['daemon_cpu_percent_sim_out']} % with the simulator's GPIO share out)")


def _cmd_bench(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    clock = args.clock or ("real" if args.cpu_quota is not None else "virtual")
    if args.seeds is None:  # one maze of 16 runs is the fault suite; three seeds for the others
        args.seeds = 1 if args.suite == "faults" and not (args.maze or args.size or args.room) else 3
    if args.seeds < 1:
        raise UsageError("--seeds must be at least 1")
    if args.first_seed < 1:
        raise UsageError(f"--first-seed must be at least 1, got {args.first_seed}")
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    if args.room:
        if args.maze or args.size:
            raise UsageError("give either --room or --maze/--size, not both")
        specs = [RunSpec(None, None, s, args.drive, clock=clock, world="room") for s in seeds]
    elif args.size:
        if args.maze:
            raise UsageError("give either --size or --maze, not both")
        specs = generated_specs(parse_size(args.size), seeds, args.drive, clock)
    elif args.maze:
        for path in args.maze:
            if not Path(path).is_file():
                raise UsageError(f"maze file {path} not found")
        specs = [RunSpec(p, None, s, args.drive, clock=clock, max_sim_s=time_limit_s(p))
                 for p in args.maze for s in seeds]
    else:
        specs = suite_specs(args.suite, args.seeds, args.drive, clock, args.first_seed)
    if args.faults:
        extra = tuple(parse_fault(text) for text in args.faults)
        specs = [replace(spec, faults=spec.faults + extra) for spec in specs]
    if args.slow_cpu:
        if clock != "virtual":
            raise UsageError("--slow-cpu emulates a slower computer on the virtual clock; drop --clock real "
                             "and --cpu-quota (which slows the real one)")
        from mazebot.sim.virtual_time import PI_CLASS_CPU

        specs = [replace(spec, slow=PI_CLASS_CPU) for spec in specs]
    command = "mazebot " + " ".join(shlex.quote(a) for a in args.argv)
    if args.cpu_quota is not None:
        return _cmd_bench_quota(args, config, specs, command)
    out_dir = Path(args.out)
    runs = []
    t0 = time.perf_counter()
    _progress(0, len(specs), "starting")
    out_dir.mkdir(parents=True, exist_ok=True)
    for i, spec in enumerate(specs, 1):
        metrics, record = run_one(config, spec)
        runs.append((metrics, record))
        faults = metrics.get("faults") or []
        outcome = (f"faults passed {sum(r['passed'] for r in faults)}/{len(faults)}" if faults
                   else f"done={metrics['done']}")
        injected = " " + ",".join(str(f) for f in spec.faults) if spec.faults else ""
        _progress(i, len(specs), f"{spec.name} seed {spec.seed}{injected}: "
                  f"{metrics['time_s']} s simulated in {metrics['wall_s']} s, {outcome}")
        if i < len(specs):  # a long suite keeps what it has measured if it is stopped early
            write_partial(out_dir, [m for m, _ in runs], command, len(specs))
    results = write_report(out_dir, runs, command)
    print(f"wrote {out_dir / 'results.json'} and {out_dir / 'report.md'} "
          f"({len(specs)} runs, {time.perf_counter() - t0:.1f} s)", file=sys.stderr)
    if any(spec.faults for spec in specs):  # a fault run passes on its fault's numbers, not on finishing
        return EXIT_OK if all(row["passed"] for r in results["runs"] for row in (r["faults"] or [])) else 1
    return EXIT_OK if all(r["done"] for r in results["runs"]) else 1


def register(sub: argparse._SubParsersAction) -> None:
    bench = sub.add_parser("bench", help="measure whole simulated runs against ground truth",
                           description="Run whole simulated runs and measure them against the ground truth: "
                                       "DIR/results.json, DIR/report.md and figures.")
    bench.add_argument("--suite", choices=SUITES, default="smoke", help="which set of mazes (default smoke)")
    bench.add_argument("--maze", action="append", default=None, help="run these maze files instead of a suite")
    bench.add_argument("--room", action="store_true",
                       help="run the room with cylinders ([sim] room_*) instead of mazes, one run per seed")
    bench.add_argument("--size", default=None, metavar="WxH",
                       help="run generated mazes of this size (cells, e.g. 16x16) instead of a suite, "
                            "one per seed")
    bench.add_argument("--seeds", type=int, default=None,
                       help="seeds per generated maze (default 3; 1 for --suite faults)")
    bench.add_argument("--first-seed", type=int, default=1,
                       help="first seed of the generated mazes (default 1; above 1 the suite's fixed mazes are "
                            "left out, so a suite can be split over several processes)")
    bench.add_argument("--drive", choices=("explore", "scripted"), default="explore",
                       help="explore: the autonomous stack; scripted: a ground-truth tour of every cell")
    bench.add_argument("--clock", choices=("virtual", "real"), default=None,
                       help="virtual: as fast as the CPU allows (default); real: wall-clock time")
    bench.add_argument("--cpu-quota", default=None, metavar="PERCENT",
                       help="run the daemon in a cgroup with PERCENT %% of one core (10 ms period; max: no "
                            "limit) and the simulated world in a process of its own, on the real clock; "
                            "needs root and a cgroup CPU controller (Pi 4 ~ 25, Pi 5 ~ 50, Pi 3B+ ~ 15)")
    bench.add_argument("--faults", nargs="+", default=None, metavar="NAME[@T]",
                       help="inject these faults into every run, T simulated seconds after the start "
                       f"(default {DEFAULT_AT_S:g}); names: {', '.join(FAULTS)}")
    bench.add_argument("--slow-cpu", action="store_true",
                       help="virtual clock: behave like a Pi-class computer, deterministically (each task step "
                       "costs 4.5 ms, the loop stalls 0.1-0.25 s every 3 s; mazebot.sim.virtual_time)")
    bench.add_argument("--out", default="bench-out", help="output directory (default bench-out)")
    bench.add_argument("--config", default=None, help="config file")
    bench.set_defaults(func=_cmd_bench)
