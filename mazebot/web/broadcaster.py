"""Sends the live map and robot state to every viewer, without any viewer slowing the others.

At ``rate_hz`` the broadcaster takes a snapshot of the shared state and of the map and,
only if something changed, builds one packet for everyone: a delta (the cells whose
value changed since the previous packet, plus the status fields that changed) or, every
``resync_every`` packets and whenever the grid was reallocated or rebuilt, a full map.
Packets are encoded once and the same bytes are queued for every viewer.

Cells are diffed here against the last map sent (vectorized, a few hundred microseconds
at 5 Hz), rather than taken from the grid's own dirty set, which belongs to SLAM.

Each viewer has a bounded queue drained by its own writer task. A viewer whose queue is
full (a phone on bad Wi-Fi) loses everything queued and is sent the current full map
instead, so memory stays bounded and nobody waits for it. A viewer that joins or asks
for a resync gets the full map of the last packet at once.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np
from aiohttp import WSCloseCode, web

from mazebot.cpu_budget import PartMeter
from mazebot.state import RunState, SharedState
from mazebot.web.protocol import (
    KIND_DELTA,
    KIND_FULL,
    CellsSection,
    GridSection,
    Packet,
    encode_packet,
    server_message,
    three_state_to_codes,
)

log = logging.getLogger(__name__)

#: Scale of the 2-D position covariance ellipse sent to the page: 95 % (chi-square, 2 dof).
ELLIPSE_CHI2_95 = 5.991
#: A trajectory point this close to the last one sent is taken for it (SLAM may rewrite the deque).
TRAIL_MATCH_M = 0.005
#: When more than 1/5 of the cells changed, a full map is smaller than a delta (5 bytes a cell).
DELTA_BYTES_PER_CELL = 5


def covariance_ellipse(cov: np.ndarray | None) -> list[float] | None:
    """``[a_m, b_m, angle_rad, theta_std_rad]``: the 95 % position ellipse (semi-axes, the
    major axis' angle from +x) and the heading standard deviation, from a 3x3 covariance."""
    if cov is None:
        return None
    c = np.asarray(cov, dtype=np.float64)
    if c.shape != (3, 3) or not np.all(np.isfinite(c)):
        return None
    vals, vecs = np.linalg.eigh(0.5 * (c[:2, :2] + c[:2, :2].T))
    vals = np.clip(vals, 0.0, None)
    k = math.sqrt(ELLIPSE_CHI2_95)
    angle = math.atan2(vecs[1, 1], vecs[0, 1])  # eigenvector of the larger eigenvalue
    return [
        round(k * math.sqrt(vals[1]), 4),
        round(k * math.sqrt(vals[0]), 4),
        round(angle, 3),
        round(math.sqrt(max(c[2, 2], 0.0)), 4),
    ]


class MapTracker:
    """The map as last sent, and what changed since.

    ``epoch`` increments whenever the grid changes shape, origin, generation or object
    (growth, loop-closure rebuild): indices of the old epoch mean nothing after that.
    """

    def __init__(self) -> None:
        self.epoch = 0
        self.codes: np.ndarray | None = None  # uint8 wire codes as last sent
        self.resolution_m = 0.0
        self.origin_m = (0.0, 0.0)
        self._key: tuple[Any, ...] | None = None

    def update(self, grid: Any) -> tuple[bool, np.ndarray | None]:
        """Take the current grid; return (reset, changed flat indices or None).

        ``reset`` means every client needs the full map (new epoch, or no map any more).
        """
        if grid is None:
            if self.codes is None:
                return False, None
            self.codes, self._key = None, None
            self.epoch += 1
            return True, None
        codes = three_state_to_codes(grid.three_state())
        key = (id(grid), grid.generation, codes.shape, tuple(grid.origin_m), grid.resolution_m)
        if key != self._key or self.codes is None or self.codes.shape != codes.shape:
            self._key = key
            self.codes = codes
            self.resolution_m = float(grid.resolution_m)
            self.origin_m = (float(grid.origin_m[0]), float(grid.origin_m[1]))
            self.epoch += 1
            return True, None
        changed = np.flatnonzero(codes.reshape(-1) != self.codes.reshape(-1))
        if changed.size == 0:
            return False, None
        self.codes = codes
        return False, changed

    def grid_section(self) -> GridSection | None:
        if self.codes is None:
            return None
        return GridSection(self.epoch, self.resolution_m, self.origin_m, self.codes)

    def cells_section(self, changed: np.ndarray) -> CellsSection:
        assert self.codes is not None
        return CellsSection(self.epoch, changed, self.codes.reshape(-1)[changed])


class Viewer:
    """One websocket client: a bounded outgoing queue and the writer that drains it."""

    def __init__(self, ws: web.WebSocketResponse, remote: str, capacity: int, meter: PartMeter | None = None) -> None:
        self.ws = ws
        self.meter = meter or PartMeter("web send per viewer")  # CPU of each send (mazebot.cpu_budget)
        self.remote = remote
        self.capacity = capacity
        self.needs_full = False
        self.dropped = 0  # items thrown away because the viewer fell behind
        self.sent_bytes = 0
        self.sent_packets = 0
        self._items: deque[bytes | str] = deque()
        self._wakeup = asyncio.Event()
        self._sending = False
        self._idle = asyncio.Event()  # set while nothing is queued or being sent
        self._idle.set()

    @property
    def queued(self) -> int:
        return len(self._items)

    def pending(self) -> list[bytes | str]:
        """What is queued and not yet sent, oldest first."""
        return list(self._items)

    def offer(self, item: bytes | str, full: Callable[[], bytes]) -> None:
        """Queue ``item``; when the queue is full, drop everything and queue ``full()`` first."""
        if len(self._items) >= self.capacity:
            self.dropped += len(self._items)
            self._items.clear()
            if isinstance(item, bytes):
                item = full()  # the full map replaces the lost deltas and this one
            else:
                self._items.append(full())
        self._items.append(item)
        self._wakeup.set()

    def drop_packets(self) -> None:
        """Forget the queued packets but keep the text messages: a client about to be closed
        still gets its last words, not a backlog of maps."""
        kept = [item for item in self._items if isinstance(item, str)]
        self.dropped += len(self._items) - len(kept)
        self._items = deque(kept)

    async def drained(self, timeout_s: float) -> bool:
        """Wait until everything queued went out (or ``timeout_s`` passed); whether it did."""
        if not (self._items or self._sending):
            return True
        self._idle.clear()
        try:
            await asyncio.wait_for(self._idle.wait(), timeout_s)
        except TimeoutError:
            return False
        return True

    async def pump(self) -> None:
        """Send queued items in order until the socket fails; run as the viewer's writer task."""
        try:
            while True:
                while not self._items:
                    self._idle.set()
                    self._wakeup.clear()
                    await self._wakeup.wait()
                item = self._items.popleft()
                self._sending = True
                start_s = time.thread_time()  # the frame is written to the socket inside the call
                if isinstance(item, bytes):
                    await self.ws.send_bytes(item)
                    self.sent_packets += 1
                else:
                    await self.ws.send_str(item)
                self.meter.add(time.thread_time() - start_s)
                self._sending = False
                self.sent_bytes += len(item)
        except (ConnectionError, RuntimeError) as exc:  # closing transport: the reader ends too
            log.debug("viewer %s: send failed (%s)", self.remote, exc)


class Broadcaster:
    """Builds packets from the shared state and queues them for every viewer.

    Example::

        b = Broadcaster(state, rate_hz=5, resync_every=50)
        viewer = b.add(ws, "10.0.0.7")     # queues the full map of the last packet
        b.tick()                           # one step; ``run()`` calls it at rate_hz
    """

    def __init__(
        self,
        state: SharedState,
        *,
        rate_hz: float = 5.0,
        resync_every: int = 50,
        queue_packets: int = 8,
        heartbeat_s: float = 10.0,
        trail_points: int = 1000,
        now_s: Callable[[], float] = time.monotonic,
    ) -> None:
        if resync_every < 1 or queue_packets < 1:
            raise ValueError(f"resync_every and queue_packets must be >= 1, got {resync_every}, {queue_packets}")
        self.state = state
        self.rate_hz = rate_hz
        self.resync_every = resync_every
        self.queue_packets = queue_packets
        self.heartbeat_s = heartbeat_s
        self.trail_points = trail_points
        self._now_s = now_s
        self.viewers: set[Viewer] = set()
        self.seq = 0
        self.map = MapTracker()
        self._status: dict[str, Any] = {}  # the compared status fields of the last packet
        self._extras: dict[str, Any] = {"elapsed_s": None, "t_ms": None}
        self._trail: list[float] = []  # flattened x, y of the tail as last sent
        self._trail_last: tuple[float, float] | None = None  # identity of the last point sent
        self._elapsed_frozen: float | None = None
        self._odo: deque[tuple[float, float]] = deque()  # (time_s, distance_m) over the last second
        self._full_cache: tuple[int, bytes] | None = None
        self.packets_built = 0
        self.bytes_built = 0
        self._errors_logged: set[str] = set()
        #: extra fields of the ``hello`` message (a replay says so there)
        self.hello_fields: Callable[[], dict[str, Any]] = dict
        #: called with every packet as it is built, in sequence order, on the loop (the Zenoh
        #: publisher's queue, :mod:`mazebot.fleet.robot_link`): must only enqueue
        self.taps: list[Callable[[bytes], None]] = []

    # -- viewers -------------------------------------------------------------------------

    def add(self, ws: web.WebSocketResponse, remote: str) -> Viewer:
        """Register a viewer; it is sent the hello and the full map of the last packet."""
        if self.seq == 0:
            self.tick()  # the first viewer: make a first packet so its full map has a status
        viewer = Viewer(ws, remote, self.queue_packets, self.state.cpu.part("web send per viewer"))
        self.viewers.add(viewer)
        viewer.offer(
            server_message("hello", protocol=1, seq=self.seq, rate_hz=self.rate_hz,
                           heartbeat_s=self.heartbeat_s, resync_every=self.resync_every, **self.hello_fields()),
            self.full_packet,
        )
        viewer.offer(self.full_packet(), self.full_packet)
        return viewer

    def remove(self, viewer: Viewer) -> None:
        self.viewers.discard(viewer)

    def resync(self, viewer: Viewer) -> None:
        """The viewer saw a gap: send it the full map of the last packet now."""
        viewer.offer(self.full_packet(), self.full_packet)

    def reply(self, viewer: Viewer, text: str) -> None:
        viewer.offer(text, self.full_packet)

    def full_packet(self) -> bytes:
        """The full map and status as of the last packet (same sequence number), encoded once."""
        if self._full_cache is None or self._full_cache[0] != self.seq:
            status = {**self._status, "trail": list(self._trail), **self._extras}
            data = encode_packet(Packet(KIND_FULL, self.seq, status, self.map.grid_section()))
            self._count(data)
            self._full_cache = (self.seq, data)
        return self._full_cache[1]

    def _count(self, data: bytes) -> None:
        self.packets_built += 1
        self.bytes_built += len(data)

    # -- the snapshot ----------------------------------------------------------------------

    def _snapshot(self, now_s: float) -> dict[str, Any]:
        """The status fields compared between packets (everything but time)."""
        s = self.state
        fault = s.active_fault
        return {
            "state": s.run_state.value,
            "pose": [round(s.pose.x_m, 3), round(s.pose.y_m, 3), round(s.pose.theta_rad, 3)],
            "ellipse": covariance_ellipse(s.pose_covariance),
            "path": [round(float(v), 3) for p in s.path for v in p[:2]],
            "goal": None if s.goal is None else [round(float(s.goal[0]), 3), round(float(s.goal[1]), 3)],
            "coverage": None if s.coverage is None else round(float(s.coverage), 3),
            "distance_m": None if (d := s.run_distance_m()) is None else round(d, 2),
            "planner": s.planner_status,
            "speed_mps": self._speed_mps(now_s),
            "fault": None if fault is None else {"source": fault.source, "message": fault.message},
        }

    def _speed_mps(self, now_s: float) -> float | None:
        odo = self.state.odometry
        if odo is None:
            return None
        self._odo.append((now_s, float(odo.distance_m)))
        while len(self._odo) > 2 and now_s - self._odo[1][0] >= 1.0:
            self._odo.popleft()
        (t0, d0), (t1, d1) = self._odo[0], self._odo[-1]
        return round((d1 - d0) / (t1 - t0), 2) if t1 > t0 else 0.0

    def _elapsed_s(self, now_s: float) -> float | None:
        """Time since start while running; frozen at its last value otherwise."""
        s = self.state
        if (s.run_state.moving or s.run_state is RunState.DONE) and s.started_at_s is not None:
            elapsed = s.elapsed_s(now_s)
            self._elapsed_frozen = None if elapsed is None else round(elapsed, 1)
        return self._elapsed_frozen

    def _trail_update(self) -> tuple[bool, list[float]]:
        """(reset, new flattened points) of the trajectory since the last packet."""
        traj = self.state.trajectory
        if self.trail_points == 0:
            return False, []
        n = len(traj)
        last = self._trail_last
        if n and traj[-1] is last:
            return False, []
        start: int | None = None
        if last is not None:  # the last point sent: the same object, or (rewritten by SLAM) the same place
            for i in range(n - 1, max(-1, n - 1 - self.trail_points), -1):
                p = traj[i]
                if p is last or (abs(p[0] - last[0]) < TRAIL_MATCH_M and abs(p[1] - last[1]) < TRAIL_MATCH_M):
                    start = i + 1
                    break
        reset = start is None
        if start is None:
            start = max(0, n - self.trail_points)
        new = [round(float(v), 2) for i in range(start, n) for v in traj[i][:2]]
        self._trail_last = traj[-1] if n else None
        self._trail = ([] if reset else self._trail) + new
        del self._trail[: max(0, len(self._trail) - 2 * self.trail_points)]
        return reset and (n > 0 or last is not None), new

    # -- one step --------------------------------------------------------------------------

    def tick(self) -> bool:
        """Send one packet if anything changed since the last one; return whether it did."""
        now_s = self._now_s()
        status = self._snapshot(now_s)
        trail_reset, trail_new = self._trail_update()
        map_reset, changed_cells = self.map.update(self.state.map)
        changed = {k: v for k, v in status.items() if k not in self._status or self._status[k] != v}
        if not (changed or trail_reset or trail_new or map_reset or changed_cells is not None):
            return False
        self.seq += 1
        self._status = status
        self._extras = {"elapsed_s": self._elapsed_s(now_s), "t_ms": round(time.time() * 1000.0, 1)}
        too_many = (
            changed_cells is not None and self.map.codes is not None
            and changed_cells.size * DELTA_BYTES_PER_CELL > self.map.codes.size
        )
        if map_reset or too_many or self.seq % self.resync_every == 0:
            packet = self.full_packet()
            for tap in self.taps:
                tap(packet)
            for viewer in self.viewers:
                viewer.needs_full = False
                viewer.offer(packet, self.full_packet)
            return True
        delta_status = {**changed, **self._extras}
        if trail_reset:
            delta_status["trail"] = list(self._trail)
        elif trail_new:
            delta_status["trail+"] = trail_new
        cells = None if changed_cells is None else self.map.cells_section(changed_cells)
        delta = encode_packet(Packet(KIND_DELTA, self.seq, delta_status, cells))
        self._count(delta)
        for tap in self.taps:
            tap(delta)
        for viewer in self.viewers:
            if viewer.needs_full:
                viewer.needs_full = False
                viewer.offer(self.full_packet(), self.full_packet)
            else:
                viewer.offer(delta, self.full_packet)
        return True

    def heartbeat(self) -> None:
        """Tell every viewer the last sequence number (lets it see a lost packet, and that we live)."""
        text = server_message("heartbeat", seq=self.seq)
        for viewer in self.viewers:
            if viewer.queued < viewer.capacity:  # a viewer that far behind gets a full map soon anyway
                viewer.offer(text, self.full_packet)

    async def run(self) -> None:
        """Tick at ``rate_hz`` and send heartbeats, until cancelled."""
        loop = asyncio.get_running_loop()
        period_s = 1.0 / self.rate_hz
        next_s = loop.time()
        next_heartbeat_s = next_s + self.heartbeat_s
        while True:
            try:
                with self.state.cpu.part("web packet").measure():
                    self.tick()
            except Exception as exc:  # a bad snapshot must not end the live page for good: log it once
                if repr(exc) not in self._errors_logged:
                    self._errors_logged.add(repr(exc))
                    log.exception("broadcast tick failed; the page shows the last good state")
            now = loop.time()
            if now >= next_heartbeat_s:
                self.heartbeat()
                next_heartbeat_s = now + self.heartbeat_s
            next_s += period_s
            if next_s < now:
                next_s = now + period_s
            await asyncio.sleep(next_s - now)

    async def close_all(self, code: int = WSCloseCode.GOING_AWAY, message: str = "server shutting down",
                        timeout_s: float = 2.0) -> None:
        """Close every viewer's socket with ``code`` (shutdown), waiting at most ``timeout_s``."""
        viewers = list(self.viewers)
        self.viewers.clear()
        closes = [asyncio.ensure_future(v.ws.close(code=code, message=message.encode())) for v in viewers]
        if closes:
            await asyncio.wait(closes, timeout=timeout_s)
