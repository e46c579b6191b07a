"""The laptop's side of the fleet: every robot on the network, each one's map and state mirrored.

A :class:`Fleet` finds robots by their liveliness tokens (``mazebot/*/alive``, with
history, so robots already running are found at once, and a robot that stops is seen to
leave) and subscribes to every robot's page packets, pose, scans and run state. Each
robot's packets are applied to a :class:`RobotMirror` exactly as the page applies them
(docs/protocol.md, "Applying packets"); a gap in the sequence numbers (a sample Zenoh
dropped) is mended by asking the robot's ``full`` queryable, not by waiting up to 50
packets for the next resync. The mirror's viewers (browser websockets,
:mod:`mazebot.fleet.watch_app`) get the robot's own packet bytes, and a full packet of the
mirror's last sequence number when they join or ask for one.

Zenoh calls back on its own threads; every callback only hands its sample to the event
loop (``call_soon_threadsafe``), where all the mirrors live.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mazebot.fleet import keys
from mazebot.web.broadcaster import Viewer
from mazebot.web.protocol import (
    KIND_FULL,
    CellsSection,
    GridSection,
    Packet,
    ProtocolError,
    decode_packet,
    encode_packet,
    server_message,
)

log = logging.getLogger(__name__)

#: How long a query to a robot may take before it is given up (seconds).
QUERY_TIMEOUT_S = 3.0
#: Three-state values of the wire codes 0 unknown, 1 free, 2 occupied (for recordings and map files).
THREE_STATE = np.array([-1, 0, 100], dtype=np.int8)


@dataclass
class RobotMirror:
    """One robot's page state as the last packets left it; ``viewers`` watch it through this watcher."""

    name: str
    info: dict[str, Any] = field(default_factory=dict)  # the robot's ``info`` answer (page hello fields)
    alive: bool = True
    seq: int = 0
    status: dict[str, Any] = field(default_factory=dict)
    trail: list[float] = field(default_factory=list)
    grid: GridSection | None = None
    waiting_full: bool = True  # nothing applied yet, or a gap: deltas are ignored until a full packet
    packets: int = 0
    gaps: int = 0
    pose: dict[str, Any] | None = None  # the last ``pose`` message (with covariance)
    last_seen_s: float = 0.0
    viewers: set[Viewer] = field(default_factory=set)
    #: (monotonic receive time, seq) of recent packets, for latency figures
    arrivals: list[tuple[float, int]] = field(default_factory=list)
    _full_cache: tuple[int, bytes] | None = None

    def apply(self, data: bytes) -> str:
        """Apply one packet; ``"applied"``, ``"ignored"`` (waiting for a full) or ``"gap"`` (ask for a full)."""
        packet = decode_packet(data)
        self.packets += 1
        if packet.kind == KIND_FULL:
            self.seq = packet.seq
            self.status = dict(packet.status)
            self.trail = list(packet.status.get("trail", []))
            self.grid = packet.map if isinstance(packet.map, GridSection) else None
            if self.grid is not None:
                self.grid = GridSection(self.grid.epoch, self.grid.resolution_m, self.grid.origin_m,
                                        self.grid.codes.copy())
            self.waiting_full = False
            return "applied"
        if self.waiting_full:
            return "ignored"
        cells = packet.map
        if packet.seq != (self.seq + 1) & 0xFFFFFFFF or (
            isinstance(cells, CellsSection) and (self.grid is None or cells.epoch != self.grid.epoch)
        ):
            self.waiting_full = True
            self.gaps += 1
            return "gap"
        if isinstance(cells, CellsSection) and self.grid is not None and len(cells):
            self.grid.codes.reshape(-1)[cells.indices] = cells.codes
        status = dict(packet.status)
        if "trail" in status:
            self.trail = list(status.pop("trail"))
        if "trail+" in status:
            self.trail.extend(status.pop("trail+"))
        self.status.update(status)
        self.seq = packet.seq
        return "applied"

    def full_packet(self) -> bytes:
        """The mirror as one full packet of its last sequence number (what a joining viewer gets)."""
        if self._full_cache is None or self._full_cache[0] != self.seq:
            status = {**self.status, "trail": list(self.trail)}
            data = encode_packet(Packet(KIND_FULL, self.seq, status, self.grid))
            self._full_cache = (self.seq, data)
        return self._full_cache[1]

    def three_state(self) -> np.ndarray | None:
        """The map as an occupancy grid's three-state array (-1/0/100), row 0 south; None before a map."""
        return None if self.grid is None else THREE_STATE[self.grid.codes]

    def hello(self) -> str:
        fields = {k: v for k, v in self.info.items() if k not in ("type", "seq")}
        fields.setdefault("protocol", 1)
        return server_message("hello", **{**fields, "seq": self.seq, "robot": self.name})

    def summary(self) -> dict[str, Any]:
        s = self.status
        return {"name": self.name, "alive": self.alive, "state": s.get("state"), "coverage": s.get("coverage"),
                "pose": s.get("pose"), "seq": self.seq, "packets": self.packets, "gaps": self.gaps,
                "viewers": len(self.viewers), "version": self.info.get("version")}


class Fleet:
    """Every robot one Zenoh session can see. ``start()`` on the loop; ``close()`` at the end.

    Example::

        fleet = Fleet(open_session("mazebot watch"))
        fleet.start()
        ...                                  # fleet.robots fills as robots are found
        reply = await fleet.control("alpha", "start", "123456")
    """

    def __init__(self, session: Any) -> None:
        self.session = session
        self.robots: dict[str, RobotMirror] = {}
        self.loop: asyncio.AbstractEventLoop | None = None
        self._declared: list[Any] = []
        self._full_pending: set[str] = set()
        #: called on the loop with (robot name, topic, decoded message) for every sample: recorders
        self.listeners: list[Callable[[str, str, Any], None]] = []
        self.full_requests = 0
        self._tasks: set[asyncio.Future[Any]] = set()

    def start(self) -> None:
        self.loop = asyncio.get_running_loop()
        sub = self.session.declare_subscriber
        self._declared.append(self.session.liveliness().declare_subscriber(
            keys.every_robot("alive"), self._threadsafe(self._on_alive), history=True))
        for topic in keys.TOPICS:
            self._declared.append(sub(keys.every_robot(topic),
                                      self._threadsafe(functools.partial(self._on_sample, topic))))

    def close(self) -> None:
        for entity in self._declared:
            with contextlib.suppress(Exception):
                entity.undeclare()
        self._declared.clear()
        with contextlib.suppress(Exception):
            self.session.close()

    def _threadsafe(self, handler: Callable[[Any], None]) -> Callable[[Any], None]:
        loop = self.loop
        assert loop is not None

        def on_zenoh_thread(sample: Any) -> None:
            # read the sample here: its payload belongs to this callback
            item = (str(sample.key_expr), sample.kind == type(sample.kind).PUT, sample.payload.to_bytes())
            with contextlib.suppress(RuntimeError):  # the loop is closed: the watcher is ending
                loop.call_soon_threadsafe(handler, item)

        return on_zenoh_thread

    # -- on the loop -------------------------------------------------------------------------

    def _spawn(self, coro: Any) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)  # held until done: the loop keeps only weak references
        task.add_done_callback(self._tasks.discard)

    def _robot(self, name: str) -> RobotMirror:
        robot = self.robots.get(name)
        if robot is None:
            robot = self.robots[name] = RobotMirror(name)
            log.info("found robot %s", name)
            self._spawn(self._fetch_info(name))
        return robot

    def _on_alive(self, item: tuple[str, bool, bytes]) -> None:
        key_expr, kind, _ = item
        name = keys.robot_of(key_expr)
        if name is None:
            return
        robot = self._robot(name)
        robot.alive = bool(kind)  # a put: the token appeared; a delete: it went
        if robot.alive:
            self._spawn(self.request_full(name))
        else:
            log.info("robot %s left", name)

    def _on_sample(self, topic: str, item: tuple[str, bool, bytes]) -> None:
        key_expr, _kind, payload = item
        name = keys.robot_of(key_expr)
        if name is None:
            return
        robot = self._robot(name)
        robot.last_seen_s = time.monotonic()
        if topic == "packet":
            self.on_packet(robot, payload)
            return
        try:
            message = json.loads(payload)
        except ValueError:
            log.debug("robot %s sent a %s that is not JSON", name, topic)
            return
        if topic == "pose":
            robot.pose = message
        for listener in self.listeners:
            listener(name, topic, message)

    def on_packet(self, robot: RobotMirror, data: bytes) -> None:
        try:
            verdict = robot.apply(data)
        except ProtocolError as exc:
            log.warning("robot %s sent a bad packet: %s", robot.name, exc)
            return
        robot.arrivals.append((time.monotonic(), robot.seq))
        del robot.arrivals[:-2000]
        if verdict == "gap":
            self._spawn(self.request_full(robot.name))
            return
        if verdict != "applied":
            return
        for viewer in robot.viewers:
            viewer.offer(data, robot.full_packet)
        for listener in self.listeners:
            listener(robot.name, "packet", robot)

    async def query(self, name: str, what: str, payload: bytes | None = None) -> bytes | None:
        """The robot's answer to ``mazebot/<name>/<what>``, or None (no answer within the timeout)."""

        def ask() -> bytes | None:
            replies = self.session.get(keys.key(name, what), payload=payload, timeout=QUERY_TIMEOUT_S)
            for reply in replies:
                if reply.ok is not None:
                    return reply.ok.payload.to_bytes()
            return None

        return await asyncio.to_thread(ask)

    async def _fetch_info(self, name: str) -> None:
        data = await self.query(name, "info")
        if data is not None:
            self.robots[name].info = json.loads(data)

    async def request_full(self, name: str) -> None:
        """Ask the robot for its full packet now (after a gap, or on finding it)."""
        if name in self._full_pending:
            return
        self._full_pending.add(name)
        self.full_requests += 1
        try:
            data = await self.query(name, "full")
        finally:
            self._full_pending.discard(name)
        robot = self.robots.get(name)
        if data is None or robot is None:
            return
        packet_seq = decode_packet(data).seq
        if not robot.waiting_full and packet_seq <= robot.seq:
            return  # a resync came first and the chain goes on: this one is older
        self.on_packet(robot, data)

    async def control(self, name: str, command: str, token: str | None) -> dict[str, Any]:
        """Start or stop a robot with its PIN; the robot's ``reply`` (status 504: no answer)."""
        body = json.dumps({"type": command, "token": token}).encode()
        data = await self.query(name, "control", body)
        if data is None:
            return {"type": "reply", "command": command, "ok": False, "status": 504,
                    "message": f"robot {name} did not answer over Zenoh"}
        return json.loads(data)
