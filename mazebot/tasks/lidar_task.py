"""Reads lidar revolutions and hands them to the rest of the daemon."""

from __future__ import annotations

import asyncio

from mazebot.state import SharedState

#: At most one "garbled bytes" event this often.
GARBLED_NOTE_EVERY_S = 5.0


async def run(lidar, state: SharedState) -> None:
    """Publish every revolution as ``state.latest_scan``, queue it for SLAM, keep the counters fresh.

    SLAM's queue (``state.scans``) is bounded: when SLAM is behind, the oldest waiting
    revolution is dropped (and counted), never the lidar reader blocked. The driver itself
    resyncs, restarts and reconnects; this loop only ends on cancellation.
    """
    last_garbled_s: float | None = None
    meter = getattr(lidar, "decode_meter", None)  # fakes in tests may have none
    if meter is not None:
        state.cpu.adopt(meter)
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
        dropped = driver_stats.bytes_dropped - stats.lidar_bytes_dropped
        reconnected = driver_stats.reconnects - stats.lidar_reconnects
        stats.lidar_bytes_dropped = driver_stats.bytes_dropped
        stats.lidar_reconnects = driver_stats.reconnects
        end_s = scan.end_time_s
        if reconnected > 0:
            state.note("lidar", f"the lidar is scanning again after a reconnect ({driver_stats.last_error})", end_s)
        if dropped > 0 and (last_garbled_s is None or end_s - last_garbled_s >= GARBLED_NOTE_EVERY_S):
            last_garbled_s = end_s
            state.note("lidar", f"{dropped} bytes from the lidar made no sense and were skipped (noise on its "
                       "serial line?); the decoder resynchronised and scanning goes on", end_s)
