"""CPU cost of one lattice fit (``mazebot.slam.lattice_fit.fit_pitch``) on synthetic wall faces, median of 7.

Usage: ``python bench/lattice_fit_cost.py``. Four classes of faces (seen from +u, -u, +v,
-v) on lines of a 0.29 m pitch, 4 mm of scatter, fitted near the configured 0.3048 m.
"""

from __future__ import annotations

import time

import numpy as np

from mazebot.slam.lattice_fit import fit_pitch


def main() -> None:
    rng = np.random.default_rng(0)
    for n_lines, n in ((7, 5000), (17, 20000)):
        classes = []
        for axis in (0, 0, 1, 1):
            positions = rng.integers(0, n_lines, n) * 0.29 + rng.normal(0.0, 0.004, n) + 0.5
            classes.append((positions, np.ones(n), axis))
        times = []
        for _ in range(7):
            start = time.process_time()
            fit = fit_pitch(classes, 0.3048, search=0.08, tolerance_m=0.02)
            times.append(time.process_time() - start)
        print(f"{n_lines} lines, {4 * n} points: pitch {fit.pitch_m:.5f} m, median {1e3 * sorted(times)[3]:.1f} ms")


if __name__ == "__main__":
    main()
