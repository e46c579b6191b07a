"""Fuzzing at the issue's scale: 10^5 random lidar buffers and 10^4 random websocket frames.

Runs the suite's own hypothesis properties (``tests/io/test_rplidar_fuzz.py``,
``tests/web/test_websocket_fuzz.py``) with many more examples and a random (but
seeded, so repeatable) search instead of the suite's fixed one, and counts what each
property was really run on (the tests append their counts to ``$MAZEBOT_FUZZ_REPORT``).
A failing property is shrunk by hypothesis to a minimal input, printed by pytest.

    nice -n 5 .venv/bin/python bench/fuzz.py [--lidar-buffers 100000] [--ws-frames 10000] [--seed 1] [--out fuzz.json]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LIDAR_TESTS = "tests/io/test_rplidar_fuzz.py"
WS_TESTS = "tests/web/test_websocket_fuzz.py"
#: Buffers per example count in LIDAR_TESTS: seven properties at the full count, the driver's at a quarter.
LIDAR_PROPERTIES = 7.25
#: Frames per websocket example on average (lists of 1..8; measured on this suite's strategy).
WS_FRAMES_PER_EXAMPLE = 4.2


def _run(tests: str, env: dict[str, str], seed: int) -> tuple[int, float, str]:
    t0 = time.monotonic()
    cpu0 = os.times()
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", f"--hypothesis-seed={seed}", tests],
        cwd=ROOT, env=env, capture_output=True, text=True, check=False,
    )
    cpu1 = os.times()
    cpu_s = (cpu1.children_user - cpu0.children_user) + (cpu1.children_system - cpu0.children_system)
    tail = "\n".join((proc.stdout + proc.stderr).strip().splitlines()[-40:])
    return proc.returncode, time.monotonic() - t0, f"cpu {cpu_s:.1f} s\n{tail}" if proc.returncode else f"{cpu_s:.1f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lidar-buffers", type=int, default=100_000)
    ap.add_argument("--ws-frames", type=int, default=10_000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", default="fuzz.json")
    args = ap.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "counts.jsonl"
        env = {**os.environ, "MAZEBOT_FUZZ_RANDOM": "1", "MAZEBOT_FUZZ_REPORT": str(report),
               "MAZEBOT_FUZZ_LIDAR_EXAMPLES": str(math.ceil(args.lidar_buffers / LIDAR_PROPERTIES)),
               "MAZEBOT_FUZZ_WS_EXAMPLES": str(math.ceil(args.ws_frames / WS_FRAMES_PER_EXAMPLE))}
        result: dict[str, object] = {"seed": args.seed}
        for name, tests in (("lidar", LIDAR_TESTS), ("websocket", WS_TESTS)):
            code, wall_s, detail = _run(tests, env, args.seed)
            result[name] = {"passed": code == 0, "wall_s": round(wall_s, 1),
                            **({"cpu_s": float(detail)} if code == 0 else {"failure": detail})}
        for line in report.read_text().splitlines() if report.exists() else []:
            entry = json.loads(line)
            counts = entry.get("buffers") or entry.get("frames")
            key = "buffers" if "buffers" in entry else "frames"
            suite = result[entry["suite"]]
            assert isinstance(suite, dict)
            suite[key] = counts
            suite[f"{key}_total"] = sum(counts.values())
    Path(args.out).write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))
    ok = all(isinstance(result[s], dict) and result[s]["passed"] for s in ("lidar", "websocket"))  # type: ignore[index]
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
