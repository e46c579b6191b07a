"""The residuals of the recent sequential matches, and a match whose own residual stands far out of them.

ICP started in the wrong basin (the heading tens of degrees off, at a place whose walls fit
more than one way) can converge, with an inlier ratio that passes, to an alignment whose
residual is several times those of the right matches around it. Measured on the Intel log
with odometry noise ``0.1,0.1`` (seed 7): the right sequential matches' residuals had a
median of 17 mm, a 99th percentile of 95 mm and a maximum of 135 mm; a match 30° off
converged at 202 mm and was taken. One absolute limit cannot part them across logs: a
building scanned a metre apart leaves larger residuals at every match than one scanned every
few centimetres (a 0.15 m limit lost the ACES log). The run's own recent residuals can: a
match is in doubt when its residual exceeds a multiple of their median, the way KISS-ICP
takes its correspondence threshold from the deviations its registration has recently seen
instead of a fixed one (Vizzo et al., "KISS-ICP: In Defense of Point-to-Point ICP", IEEE
RA-L 2023, section III.C). A match in doubt is not refused: it asks for a second opinion
(:meth:`mazebot.slam.slam.Slam._search_steps` searches the whole correlative window).

Example::

    residuals = MatchResiduals(ratio=4.0, scans=50)
    for rmse_m in (0.015, 0.02, 0.017) * 10:
        residuals.add(rmse_m)
    residuals.in_doubt(0.2)  # True: twelve times the median
"""

from __future__ import annotations

from collections import deque

import numpy as np

#: no match is in doubt before this many matched scans have given their residuals: the median of fewer
#: than ten is the scatter of a few walls, not the run's
MIN_RESIDUALS = 10


class MatchResiduals:
    """The residuals (m) of the last ``scans`` matched scans; ``ratio`` times their median is the doubt's limit.

    ``ratio`` 0 turns the test off (no match is ever in doubt).
    """

    def __init__(self, ratio: float, scans: int) -> None:
        self.ratio = float(ratio)
        self._recent: deque[float] = deque(maxlen=max(int(scans), 1))

    def add(self, rmse_m: float) -> None:
        """One more matched scan's residual (m)."""
        self._recent.append(float(rmse_m))

    def limit_m(self, ratio: float | None = None) -> float:
        """The residual (m) beyond which a match is in doubt (infinite while the test is off or has too few).

        ``ratio`` (default: the doubt's own) lets other tests that judge a match by the same recent
        residuals, at their own multiple of the median, share this one history.
        """
        ratio = self.ratio if ratio is None else float(ratio)
        if ratio <= 0 or len(self._recent) < MIN_RESIDUALS:
            return float("inf")
        return ratio * float(np.median(np.fromiter(self._recent, dtype=np.float64)))

    def in_doubt(self, rmse_m: float, ratio: float | None = None) -> bool:
        """Does a match with this residual (m) stand out of the recent ones (by ``ratio``, see :meth:`limit_m`)?"""
        return float(rmse_m) > self.limit_m(ratio)
