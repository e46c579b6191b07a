"""``mazebot runs`` and ``mazebot export-map``: the saved runs under the state directory.

Example::

    mazebot runs                                     # one line per saved run
    mazebot export-map latest --format pgm --out /tmp/maze   # /tmp/maze.pgm + /tmp/maze.yaml
"""

from __future__ import annotations

import argparse
from pathlib import Path

from mazebot.config import load_config
from mazebot.errors import EXIT_OK
from mazebot.persist.runs import find_run, list_runs, runs_root


def _cmd_runs(args: argparse.Namespace) -> int:
    root = runs_root(load_config(args.config).daemon.state_dir)
    runs = list_runs(root)
    if not runs:
        print(f"no saved runs in {root}")
        return EXIT_OK
    for run in runs:
        m = run.meta
        if not m:
            print(f"{run.name}  (not saved yet)")
            continue
        resumed = f"  resumed from {Path(m['resumed_from']).name}" if m.get("resumed_from") else ""
        recording = "  recorded" if m.get("recording") else ""
        print(
            f"{run.name}  saved {m.get('saved_at', '?')}  {m.get('scans', 0)} scans  {m.get('keyframes', 0)} keyframes"
            f"  {m.get('run_state', '?')}{recording}{resumed}"
        )
    return EXIT_OK


def _cmd_export(args: argparse.Namespace) -> int:
    from mazebot.persist.export import EXPORTERS
    from mazebot.persist.snapshot import load_run

    root = runs_root(load_config(args.config).daemon.state_dir)
    run_dir = find_run(root, args.run)
    saved = load_run(run_dir)
    out = Path(args.out) if args.out else run_dir / "export" / "map"
    for path in EXPORTERS[args.format](saved, out):
        print(path)
    return EXIT_OK


def register(sub: argparse._SubParsersAction) -> None:
    runs = sub.add_parser("runs", help="list the saved runs (STATE_DIR/runs)",
                          description="List the runs saved under [daemon] state_dir/runs, newest last.")
    runs.add_argument("--config", default=None, help="config file (for [daemon] state_dir)")
    runs.set_defaults(func=_cmd_runs)
    export = sub.add_parser("export-map", help="export a saved run's map: PNG, ROS PGM+YAML, SVG or the cell graph",
                            description="Export a saved run's map as PNG, ROS map_server PGM+YAML, SVG or the "
                                        "maze's cell graph as JSON.")
    export.add_argument("run", help="run name from `mazebot runs`, 'latest', or a run folder")
    export.add_argument("--format", default="png", choices=["png", "pgm", "svg", "json"],
                        help="png (legend, scale bar, path), pgm (+ yaml, ROS map_server), svg, json (cell graph)")
    export.add_argument("--out", default=None, help="output path without or with suffix (default RUN/export/map)")
    export.add_argument("--config", default=None, help="config file (for [daemon] state_dir)")
    export.set_defaults(func=_cmd_export)
