"""Reads lidar revolutions and hands them to the rest of the daemon."""

from __future__ import annotations

from mazebot.state import SharedState


async def run(lidar, state: SharedState) -> None:
    """Publish every revolution as ``state.latest_scan`` and keep the sensor counters fresh.

    The driver itself resyncs, restarts and reconnects; this loop only ends on
    cancellation.
    """
    async for scan in lidar.scans():
        state.latest_scan = scan
        stats = state.sensors
        stats.lidar_revolutions += 1
        driver_stats = lidar.stats
        stats.lidar_bytes_dropped = driver_stats.bytes_dropped
        stats.lidar_reconnects = driver_stats.reconnects
