"""Fuzzing at the issue's scale: 10^5 random lidar buffers and 10^4 random websocket frames.

Runs the suite's own hypothesis properties (``tests/io/test_rplidar_fuzz.py``,
``tests/web/test_websocket_fuzz.py``) with many more examples and a random (but
seeded, so repeatable) search instead of the suite's fixed one, and counts what each
property was really run on (the tests append their counts to ``$MAZEBOT_FUZZ_REPORT``).
A failing property is shrunk by hypothesis to a minimal input, printed by pytest. Each
property runs in its own process (``--jobs`` at once); ``--max-minutes`` stops what is still
running then, and the counts say how far each got.

    nice -n 5 .venv/bin/python bench/fuzz.py [--lidar-buffers 100000] [--ws-frames 10000] [--seed 1]
        [--jobs 3] [--out fuzz.json]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LIDAR_TESTS = "tests/io/test_rplidar_fuzz.py"
WS_TESTS = "tests/web/test_websocket_fuzz.py"
#: Buffers per example count in LIDAR_TESTS: seven properties at the full count, the driver's at a quarter.
LIDAR_PROPERTIES = 7.25
#: Frames per websocket example on average (lists of 1..8; measured on this suite's strategy).
WS_FRAMES_PER_EXAMPLE = 4.2


#: The regression tests in those files take a fixed input: nothing to run at scale.
REGRESSIONS = ("test_a_sample_just_before_", "test_deep_nesting_")


def _collect(tests: str) -> list[str]:
    """The node ids of the fuzzing properties in ``tests``."""
    proc = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider", tests],
                          cwd=ROOT, capture_output=True, text=True, check=True)
    nodes = [line for line in proc.stdout.splitlines() if "::" in line]
    return [n for n in nodes if not n.split("::")[1].startswith(REGRESSIONS)]


async def _pytest(node: str, env: dict[str, str], seed: int, jobs: asyncio.Semaphore,
                  deadline: float) -> dict[str, object]:
    """One test (node id) in its own process; its outcome and wall time. Stopped at ``deadline``."""
    async with jobs:
        t0 = time.monotonic()
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", f"--hypothesis-seed={seed}", node,
            cwd=ROOT, env=env, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT)
        try:
            out, _ = await asyncio.wait_for(proc.communicate(), max(1.0, deadline - time.monotonic()))
        except TimeoutError:
            proc.kill()
            await proc.wait()
            return {"test": node.split("::")[1], "passed": None, "wall_s": round(time.monotonic() - t0, 1),
                    "failure": "stopped at the time limit (the counts say how far it got)"}
        wall_s = time.monotonic() - t0
    entry: dict[str, object] = {"test": node.split("::")[1], "passed": proc.returncode == 0, "wall_s": round(wall_s, 1)}
    if proc.returncode:
        lines = out.decode(errors="replace").strip().splitlines()
        # the assertion and hypothesis' falsifying example, not the captured log lines after them
        keep = [x for x in lines if not x.startswith(("DEBUG ", "INFO ", "WARNING ", "ERROR "))]
        entry["failure"] = "\n".join(keep[-80:])
    return entry


async def _run_all(nodes: list[str], env: dict[str, str], seed: int, jobs: int,
                   limit_s: float) -> list[dict[str, object]]:
    gate = asyncio.Semaphore(jobs)
    deadline = time.monotonic() + limit_s
    return list(await asyncio.gather(*(_pytest(n, env, seed, gate, deadline) for n in nodes)))


def _counts(report: Path) -> dict[str, Counter[str]]:
    """Per suite, the sum over processes of each process's last counts line."""
    last: dict[tuple[str, int], dict[str, int]] = {}
    for line in report.read_text().splitlines() if report.exists() else []:
        entry = json.loads(line)
        last[(entry["suite"], entry["pid"])] = entry.get("buffers") or entry.get("frames") or {}
    totals: dict[str, Counter[str]] = {"lidar": Counter(), "websocket": Counter()}
    for (suite, _), counts in last.items():
        totals[suite].update(counts)
    return totals


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lidar-buffers", type=int, default=100_000)
    ap.add_argument("--ws-frames", type=int, default=10_000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--jobs", type=int, default=3, help="tests run at once, each in its own process")
    ap.add_argument("--only", choices=["lidar", "websocket"], default=None, help="fuzz only this side")
    ap.add_argument("--max-minutes", type=float, default=120.0, help="stop what still runs after this long")
    ap.add_argument("--out", default="fuzz.json")
    args = ap.parse_args()

    report = Path(args.out).with_suffix(".counts.jsonl")
    report.unlink(missing_ok=True)
    env = {**os.environ, "MAZEBOT_FUZZ_RANDOM": "1", "MAZEBOT_FUZZ_REPORT": str(report),
           "MAZEBOT_FUZZ_LIDAR_EXAMPLES": str(math.ceil(args.lidar_buffers / LIDAR_PROPERTIES)),
           "MAZEBOT_FUZZ_WS_EXAMPLES": str(math.ceil(args.ws_frames / WS_FRAMES_PER_EXAMPLE))}
    # the websocket property first: it is one process, and one of many behind the lidar's
    # slow ones it could be stopped by --max-minutes before it reached its count
    nodes = (_collect(WS_TESTS) if args.only != "lidar" else []) + (
        _collect(LIDAR_TESTS) if args.only != "websocket" else [])
    cpu0 = os.times()
    t0 = time.monotonic()
    tests = asyncio.run(_run_all(nodes, env, args.seed, args.jobs, 60.0 * args.max_minutes))
    cpu1 = os.times()
    totals = _counts(report)
    result = {
        "seed": args.seed,
        "passed": all(t["passed"] is True for t in tests),
        "failed": [t["test"] for t in tests if t["passed"] is False],
        "stopped": [t["test"] for t in tests if t["passed"] is None],
        "lidar_buffers": dict(totals["lidar"]), "lidar_buffers_total": sum(totals["lidar"].values()),
        "websocket_frames": dict(totals["websocket"]), "websocket_frames_total": sum(totals["websocket"].values()),
        "wall_s": round(time.monotonic() - t0, 1),
        "cpu_s": round(cpu1.children_user - cpu0.children_user + cpu1.children_system - cpu0.children_system, 1),
        "tests": tests,
    }
    Path(args.out).write_text(json.dumps(result, indent=2))
    print(json.dumps({k: v for k, v in result.items() if k != "tests"}, indent=2))
    for t in tests:
        if t["passed"] is False:
            print(f"FAILED {t['test']}:\n{t['failure']}", file=sys.stderr)
    return 0 if result["passed"] else 1


if __name__ == "__main__":
    sys.exit(main())
