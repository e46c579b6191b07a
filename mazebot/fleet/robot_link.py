"""The robot on Zenoh: its state published under ``mazebot/<name>/``, start/stop taken with the PIN.

What goes out (:mod:`mazebot.fleet.keys`): the phone page's own packets, from a tap on the
web broadcaster (the same bytes, sequence numbers and full-map resyncs the page gets), the
pose with its covariance at ``[zenoh] pose_hz``, every ``scan_every``-th lidar revolution,
run-state changes and faults. A liveliness token ``mazebot/<name>/alive`` lets watchers
find the robot and see it leave.

Off the control loop's hot path: on the event loop the link only looks at the shared
state (at ``pose_hz``) and appends references to a queue; a thread of its own encodes
(JSON, base64) and calls Zenoh (``put`` with congestion control DROP, so a slow network
drops samples instead of blocking). A queue that is full drops the message and counts it.
Queries arrive on Zenoh's threads and are handed to the loop (``call_soon_threadsafe``),
where start/stop is decided exactly as for the page (the same :class:`ControlAuth`, so
wrong PINs over Zenoh and over the page share one lockout), then answered from the thread.

Zenoh queries carry no trustworthy sender address (any program may open a session with a
new id), so every Zenoh client counts as one client for the PIN lockout, and all start/stop
queries together are held to ``control_rate_per_s`` (a token bucket, as the page's messages).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

from mazebot import __version__
from mazebot.config import ZenohConfig
from mazebot.cpu_budget import PartMeter
from mazebot.fleet import keys
from mazebot.record.schemas import raw_scan_json
from mazebot.state import SharedState
from mazebot.web.auth import ControlAuth
from mazebot.web.broadcaster import Broadcaster
from mazebot.web.limits import TokenBucket
from mazebot.web.protocol import PROTOCOL_VERSION, ProtocolError, parse_client_message, server_message

log = logging.getLogger(__name__)

#: The address every Zenoh client's wrong PINs are counted against (see the module docstring).
ZENOH_CLIENT = "zenoh"
#: How long the publisher thread sleeps when nothing is queued (it is woken for each message).
IDLE_WAIT_S = 0.5


@dataclass
class LinkStats:
    """What the link did, for tests and benchmarks (counts since start)."""

    published: int = 0
    dropped: int = 0  # the queue was full
    failed: int = 0  # Zenoh refused a put or a reply
    queries: int = 0
    refused: int = 0  # start/stop refused: wrong or no PIN, locked out, too fast


class RobotLink:
    """One robot's Zenoh presence. Built and started by :func:`start_robot_link`; ``close()`` ends it.

    Example::

        link = RobotLink(session, "alpha", state, broadcaster, auth, ZenohConfig(), loop)
        link.start()           # token, publishers, queryables, the publisher thread
        await link.run()       # the loop side: pose, scans, run state (a task)
        link.close()
    """

    def __init__(self, session: Any, name: str, state: SharedState, broadcaster: Broadcaster, auth: ControlAuth,
                 params: ZenohConfig, loop: asyncio.AbstractEventLoop) -> None:
        self.session = session
        self.name = name
        self.state = state
        self.broadcaster = broadcaster
        self.auth = auth
        self.params = params
        self.loop = loop
        self.stats = LinkStats()
        self.meter = PartMeter("zenoh publish")  # CPU of the publisher thread
        self._poll_meter = state.cpu.part("zenoh poll")  # CPU the link takes on the loop
        state.cpu.adopt(self.meter)
        self._bucket = TokenBucket(params.control_rate_per_s, params.control_burst)
        # appended on the loop, popped by the thread: both atomic under the GIL
        self._queue: deque[tuple[str, Any]] = deque()
        self._wake = threading.Event()
        self._stopping = False
        self._thread: threading.Thread | None = None
        self._publishers: dict[str, Any] = {}
        self._declared: list[Any] = []
        self._last_scan: Any = None
        self._scans_seen = 0
        self._last_state: tuple[str, tuple[tuple[str, str], ...]] | None = None
        self._faults_seen: set[int] = set()

    # -- lifetime --------------------------------------------------------------------------

    def start(self) -> None:
        import zenoh

        drop = zenoh.CongestionControl.DROP
        for topic in keys.TOPICS:
            self._publishers[topic] = self.session.declare_publisher(
                keys.key(self.name, topic), congestion_control=drop, express=True)
        for what in keys.QUERYABLES:
            self._declared.append(self.session.declare_queryable(
                keys.key(self.name, what), lambda query, what=what: self._on_query(what, query)))
        self._declared.append(self.session.liveliness().declare_token(keys.key(self.name, "alive")))
        self._thread = threading.Thread(target=self._publish_forever, name="mazebot-zenoh", daemon=True)
        self._thread.start()
        self.broadcaster.taps.append(self._on_packet)

    def close(self) -> None:
        """Stop publishing, leave the network (watchers see the token go), close the session. Idempotent."""
        with contextlib.suppress(ValueError):
            self.broadcaster.taps.remove(self._on_packet)
        self._stopping = True
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        for entity in [*self._declared, *self._publishers.values()]:
            with contextlib.suppress(Exception):  # the session may be closed already
                entity.undeclare()
        self._declared.clear()
        self._publishers.clear()
        with contextlib.suppress(Exception):
            self.session.close()

    # -- the loop's side: look, and enqueue ---------------------------------------------------

    def _enqueue(self, topic: str, item: Any) -> None:
        if len(self._queue) >= self.params.queue_messages:
            self.stats.dropped += 1
            return
        self._queue.append((topic, item))
        self._wake.set()

    def _on_packet(self, packet: bytes) -> None:
        """The broadcaster's tap: every page packet, in order."""
        self._enqueue("packet", packet)

    async def run(self) -> None:
        """Look at the shared state ``pose_hz`` times a second; enqueue what is new. Until cancelled."""
        period_s = 1.0 / self.params.pose_hz
        next_s = self.loop.time()
        while True:
            with self._poll_meter.measure():
                self.poll()
            next_s += period_s
            now = self.loop.time()
            if next_s < now:
                next_s = now + period_s
            await asyncio.sleep(next_s - now)

    def poll(self) -> None:
        s = self.state
        now_ms = time.time() * 1000.0
        cov = s.pose_covariance
        self._enqueue("pose", (s.pose_time_s, (s.pose.x_m, s.pose.y_m, s.pose.theta_rad),
                               None if cov is None else cov.copy(), now_ms))
        scan = s.latest_scan
        if scan is not None and scan is not self._last_scan:
            self._last_scan = scan
            self._scans_seen += 1
            if self._scans_seen % self.params.scan_every == 0:
                self._enqueue("scan", scan)
        faults = tuple((f.source, f.message) for f in s.faults)
        current = (s.run_state.value, faults)
        if current != self._last_state:
            self._last_state = current
            self._enqueue("state", keys.state_message(current[0], list(faults), now_ms))
        for fault in s.faults:
            if id(fault) not in self._faults_seen:
                self._enqueue("fault", {"source": fault.source, "message": fault.message,
                                        "time_s": fault.time_s, "t_ms": round(now_ms, 1)})
        self._faults_seen = {id(f) for f in s.faults}

    # -- queries: from Zenoh's threads to the loop, answered from the publisher thread ----------

    def _on_query(self, what: str, query: Any) -> None:
        """On a Zenoh thread: hand the query to the loop (it owns the state and the PIN check)."""
        with contextlib.suppress(RuntimeError):  # the loop is closed: the daemon is ending
            self.loop.call_soon_threadsafe(self._answer, what, query)

    def _answer(self, what: str, query: Any) -> None:
        self.stats.queries += 1
        if what == "info":
            body = keys.dumps(self.info())
        elif what == "full":
            body = self.broadcaster.full_packet()
        else:
            body = keys.dumps(self.control(_payload_text(query)))
        self._queue.append(("reply", (query, body)))  # replies are never dropped: they are few
        self._wake.set()

    def info(self) -> dict[str, Any]:
        """The page's ``hello`` fields, and who this is."""
        b = self.broadcaster
        return {"type": "hello", "protocol": PROTOCOL_VERSION, "seq": b.seq, "rate_hz": b.rate_hz,
                "heartbeat_s": b.heartbeat_s, "resync_every": b.resync_every, "robot": self.name,
                "version": __version__}

    def control(self, text: str) -> dict[str, Any]:
        """Start or stop as the page's websocket does; the answer is the page's ``reply`` message."""
        try:
            msg = parse_client_message(text)
        except ProtocolError as exc:
            self.stats.refused += 1
            return {"type": "error", "status": 400, "message": str(exc)}
        if msg.type == "resync":
            return {"type": "error", "status": 400, "message": "resync: ask mazebot/<name>/full for the full packet"}
        if not self._bucket.take():
            self.stats.refused += 1
            return {"type": "reply", "command": msg.type, "ok": False, "status": 429,
                    "message": f"too many start/stop requests over Zenoh: at most {self.params.control_rate_per_s:g} "
                    "a second; try again"}
        status = self.auth.check(msg.token, ZENOH_CLIENT)
        if status != 200:
            self.stats.refused += 1
            log.warning("refused %s over Zenoh (%d)", msg.type, status)
            words = {401: "a PIN is needed", 403: "wrong PIN",
                     429: f"too many wrong PINs; try again in {self.auth.retry_after_s(ZENOH_CLIENT):.0f} s"}
            return {"type": "reply", "command": msg.type, "ok": False, "status": status, "message": words[status]}
        try:
            self.state.commands.put_nowait(msg.type)
        except asyncio.QueueFull:
            return {"type": "reply", "command": msg.type, "ok": False, "status": 503,
                    "message": "too many commands queued; try again"}
        log.info("%s accepted over Zenoh", msg.type)
        return {"type": "reply", "command": msg.type, "ok": True, "status": 200, "message": "accepted"}

    # -- the publisher thread ----------------------------------------------------------------

    def _publish_forever(self) -> None:
        while not self._stopping:
            if not self._queue:
                self._wake.wait(IDLE_WAIT_S)
                self._wake.clear()
                continue
            start_s = time.thread_time()
            while self._queue and not self._stopping:
                topic, item = self._queue.popleft()
                try:
                    self._send(topic, item)
                except Exception as exc:  # a closed session, a refused reply: count it, keep going
                    self.stats.failed += 1
                    log.debug("zenoh %s failed: %s", topic, exc)
            self.meter.add(time.thread_time() - start_s)

    def _send(self, topic: str, item: Any) -> None:
        if topic == "reply":
            query, body = item
            query.reply(query.key_expr, body)
            query.drop()  # the reply is final: the querier need not wait for its timeout
            return
        if topic == "packet":
            payload = item
        elif topic == "pose":
            time_s, pose, cov, t_ms = item
            payload = keys.dumps(keys.pose_message(time_s, pose, cov, t_ms))
        elif topic == "scan":
            payload = keys.dumps({**raw_scan_json(item, 0), "end_time_s": float(item.end_time_s),
                                  "t_ms": round(time.time() * 1000.0, 1)})
        else:
            payload = keys.dumps(item)
        self._publishers[topic].put(payload)
        self.stats.published += 1


def _payload_text(query: Any) -> str:
    payload = query.payload
    if payload is None:
        return ""
    try:
        return payload.to_bytes().decode("utf-8")
    except UnicodeDecodeError:
        return "\ufffd"  # not JSON either: parse_client_message says so


def start_robot_link(params: ZenohConfig, state: SharedState, broadcaster: Broadcaster, auth: ControlAuth,
                     loop: asyncio.AbstractEventLoop) -> RobotLink:
    """Open the session ``[zenoh]`` describes and start publishing; the caller closes the link."""
    from mazebot.fleet.session import open_session

    name = keys.robot_name(params.robot_name)
    session = open_session("[zenoh] enabled", params.mode, params.connect, params.listen, params.multicast_scouting)
    link = RobotLink(session, name, state, broadcaster, auth, params, loop)
    try:
        link.start()
    except Exception:
        link.close()
        raise
    log.info("on Zenoh as mazebot/%s (%s mode)", name, params.mode)
    return link


def hello_text(info: dict[str, Any]) -> str:
    """The page's ``hello`` message for a robot's ``info`` answer (a watcher sends it to its viewers)."""
    fields = {k: v for k, v in info.items() if k != "type"}
    return server_message("hello", **fields)
