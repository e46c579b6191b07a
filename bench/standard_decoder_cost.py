"""Thread CPU of the standard-scan decoder on a realistic A1 stream, fast path on and off.

The stream: revolutions of 360 samples whose ranges come in smooth stretches with jumps
(walls at different distances), each angle reported minus the range-dependent offset a
triangulation head takes off (the emulator's ``standard_offset_deg``), 5 % without a
return, fed in 480-byte reads as a port delivers them at 115 200 baud.

Run: ``.venv/bin/python bench/standard_decoder_cost.py [--repeat N] [--profile]``.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import statistics
import time

import numpy as np

from mazebot.io import rplidar_protocol as proto
from mazebot.sim.lidar_emulator import standard_offset_deg

READ_BYTES = 480
SAMPLES_PER_REVOLUTION = 360


def realistic_stream(revolutions: int = 60, seed: int = 1) -> bytes:
    rng = np.random.default_rng(seed)
    parts = []
    n = SAMPLES_PER_REVOLUTION
    for _ in range(revolutions):
        raw_deg = np.arange(n) * (360.0 / n) + rng.uniform(0, 360.0 / n)
        dist_mm = np.empty(n)
        i = 0
        while i < n:  # a wall: 5..40 samples at one distance, slowly changing
            length = min(int(rng.integers(5, 40)), n - i)
            dist_mm[i : i + length] = rng.uniform(150, 1500) + rng.normal(0, 5) * np.arange(length)
            i += length
        dist_mm = np.clip(dist_mm, 150, 6000)
        dist_mm[rng.random(n) < 0.05] = 0.0
        angle_deg = (raw_deg - np.where(dist_mm > 0, standard_offset_deg(dist_mm), 0.0)) % 360.0
        start = np.zeros(n, dtype=bool)
        start[0] = True
        parts.append(proto.encode_standard_samples(angle_deg, dist_mm, np.where(dist_mm > 0, 47, 0), start))
    return b"".join(parts)


class FullRhythmFit(proto.StandardScanDecoder):
    FAST_PATH = False


def decode_cpu_s(decoder_class: type[proto.StandardScanDecoder], data: bytes) -> tuple[float, int]:
    """(thread CPU seconds, samples decoded) of decoding ``data`` in reads of READ_BYTES."""
    decoder = decoder_class()
    decoder.reset(synced=True)
    samples = 0
    start_s = time.thread_time()
    for at in range(0, len(data), READ_BYTES):
        samples += len(decoder.feed(data[at : at + READ_BYTES]))
    samples += len(decoder.flush())
    return time.thread_time() - start_s, samples


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5, help="runs per decoder (the median is printed)")
    parser.add_argument("--profile", action="store_true", help="print the decoder's 15 costliest calls")
    args = parser.parse_args()
    data = realistic_stream()
    for name, cls in (("as shipped", proto.StandardScanDecoder), ("full rhythm fit", FullRhythmFit)):
        runs = [decode_cpu_s(cls, data) for _ in range(args.repeat)]
        cpu_s = statistics.median(r[0] for r in runs)
        reads = len(data) // READ_BYTES + 1
        print(f"{name}: {runs[0][1]} samples, {cpu_s * 1e3:.1f} ms CPU, {cpu_s / reads * 1e3:.3f} ms per read "
              f"(median of {args.repeat})")
    if args.profile:
        profile = cProfile.Profile()
        profile.runcall(decode_cpu_s, proto.StandardScanDecoder, data)
        pstats.Stats(profile).sort_stats("cumulative").print_stats(15)


if __name__ == "__main__":
    main()
