"""Reads lidar revolutions and hands them to the rest of the daemon."""

from __future__ import annotations

import asyncio

from mazebot.state import SharedState


async def run(lidar, state: SharedState) -> None:
    """Publish every revolution as ``state.latest_scan``, queue it for SLAM, keep the counters fresh.

    SLAM's queue (``state.scans``) is bounded: when SLAM is behind, the oldest waiting
    revolution is dropped (and counted), never the lidar reader blocked. The driver itself
    resyncs, restarts and reconnects; this loop only ends on cancellation.
    """
    async for scan in lidar.scans():
        state.latest_scan = scan
        queue = state.scans
        while queue.full():
            try:
                queue.get_nowait()
            except asyncio.QueueEmpty:  # pragma: no cover - single loop, cannot race
                break
            state.slam.scans_dropped += 1
        queue.put_nowait(scan)
        stats = state.sensors
        stats.lidar_revolutions += 1
        driver_stats = lidar.stats
        stats.lidar_bytes_dropped = driver_stats.bytes_dropped
        stats.lidar_reconnects = driver_stats.reconnects
