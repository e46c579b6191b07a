"""A :class:`~mazebot.slam.slam.Slam` that tells observers what it consumed, and when.

A recording must let replay take exactly the steps the live SLAM took: which revolutions
it processed (some are dropped when SLAM is behind), with odometry up to which reading,
and after how many scans each loop-closure result (computed in a thread) was merged.
The method itself is untouched; this subclass only reports after each step.

Example::

    slam = ObservedSlam(params, background=True, record_trajectory=False)
    slam.observers.append(my_observer)   # slam_updated(...), slam_final(...) and slam_applied(...)
"""

from __future__ import annotations

from collections.abc import Generator
from typing import Any, Protocol

from mazebot.io.scan import Scan
from mazebot.slam.slam import LoopClosureJob, LoopClosureResult, OdometrySource, PaintDecision, Slam, SlamUpdate


class SlamObserver(Protocol):
    def slam_updated(self, slam: Slam, scan: Scan, odometry: OdometrySource, update: SlamUpdate) -> None: ...

    def slam_final(self, slam: Slam) -> None: ...

    def slam_applied(self, slam: Slam, result: LoopClosureResult, rebuilt: bool) -> None: ...


class ObservedSlam(Slam):
    """Slam plus a list of observers called after ``update`` (``update_steps``) and ``apply``."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.observers: list[SlamObserver] = []

    def update_steps(
        self, scan: Scan, odometry: OdometrySource, *, paint: bool | PaintDecision = True
    ) -> Generator[None, None, SlamUpdate]:
        update = yield from super().update_steps(scan, odometry, paint=paint)
        for observer in self.observers:
            observer.slam_updated(self, scan, odometry, update)
        return update

    def final_job(self) -> LoopClosureJob | None:
        job = super().final_job()
        if job is not None:
            for observer in self.observers:
                observer.slam_final(self)
        return job

    def apply_steps(self, result: LoopClosureResult) -> Generator[None, None, bool]:
        rebuilt = yield from super().apply_steps(result)
        for observer in self.observers:
            observer.slam_applied(self, result, rebuilt)
        return rebuilt
