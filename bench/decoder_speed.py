"""Wall time to decode about one second of lidar data, standard and express scans.

These were two unit tests (``< 5 ms``, best of 5) until the tests stopped timing anything on
a shared machine; the figure lives here now. The streams are the tests' own: 2000 standard
samples of a regular sweep (about 1 s of an A1) and 126 express capsules of a steadily
turning head (about 1 s at 4000 samples/s), each decoded by a fresh decoder in one feed.

Run: ``.venv/bin/python bench/decoder_speed.py [--repeat 20]``; prints JSON: the median and
the best of the runs, in milliseconds, against the 5 ms budget (a 200th of the data's time).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable

import numpy as np

from mazebot.io import rplidar_protocol as proto

BUDGET_MS = 5.0


def standard_stream(n: int = 2000, step_deg: float = 0.99) -> bytes:
    rng = np.random.default_rng(0)
    angle = (np.rint((np.arange(n) * step_deg % 360.0) * 64) % (360 * 64)) / 64.0
    dist = np.rint(rng.uniform(150, 8000, n) * 4) / 4
    quality = rng.integers(0, 64, n)
    start = np.zeros(n, dtype=bool)
    start[1:] = np.diff(angle) < 0
    return proto.encode_standard_samples(angle, dist, quality, start)


def express_stream(n_caps: int = 126, step_deg: float = 360 / (4000 / 5.5) * 32) -> bytes:
    return b"".join(
        proto.encode_express_capsule((k * step_deg) % 360, np.arange(32) + 100 * k, start=k == 0) for k in range(n_caps)
    )


def _times_ms(fn: Callable[[], object], repeat: int) -> list[float]:
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        out.append(1000 * (time.perf_counter() - t0))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=20)
    args = ap.parse_args()
    standard, express = standard_stream(), express_stream()
    result = {}
    for name, fn in (("standard", lambda: proto.StandardScanDecoder().feed(standard)),
                     ("express", lambda: proto.ExpressScanDecoder().feed(express))):
        ms = _times_ms(fn, args.repeat)
        result[name] = {"median_ms": round(statistics.median(ms), 3), "best_ms": round(min(ms), 3),
                        "budget_ms": BUDGET_MS, "runs": args.repeat}
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
