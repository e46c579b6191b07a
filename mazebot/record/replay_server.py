"""A replay behind the phone page: ``mazebot replay FILE.mcap --serve``.

The recording goes through the same SLAM as offline (:class:`~mazebot.record.replay.Replayer`,
step for step), paced as recorded (``--speed``), and what SLAM produces is written into a
:class:`~mazebot.state.SharedState` the way the daemon's tasks write it: the map, the
correction ``map_from_odom``, the covariance and keyframe trail (as the SLAM task), the
pose composed with each encoder reading (as the odometry task), and the recorded run
state. The real web application (:func:`mazebot.web.app.create_app`, the same broadcaster
and websocket protocol) serves that state, so the phone sees the run again: the map
grows, the robot and its trail move.

The page is told it is a replay (``replay`` in the websocket's ``hello`` and in
``/api/status``); start and stop are answered with 409: there is no robot behind it.

SLAM runs on the event loop as in the daemon; loop-closure jobs run in an executor and
are awaited where the live run merged them, so the served map is the offline replay's
map, cell for cell. When the recording ends the page keeps showing the final map until
the server is stopped (Ctrl-C, SIGTERM).
"""

from __future__ import annotations

import asyncio
import logging
import secrets
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

from aiohttp import web

from mazebot.errors import HardwareUnavailable
from mazebot.geometry import compose
from mazebot.record.reader import Recording
from mazebot.record.replay import TOPICS, Pace, Replayer, ReplayResult
from mazebot.state import RunState, SharedState
from mazebot.web.app import WebSettings, create_app

log = logging.getLogger(__name__)

#: What the served replay reads: SLAM's inputs and steps, and the run state for the page.
FED_TOPICS = (*TOPICS, "/mazebot/run_state")
#: With no pacing (``--fast``), the loop is given back to the web server this often.
FAST_YIELD_MESSAGES = 20


@dataclass
class ReplayProgress:
    """What the page and ``/api/status`` are told about the replay (``replay`` field)."""

    file: str
    speed: float | None  # 1.0 = as recorded; None = as fast as possible
    messages: int  # messages to feed
    fed: int = 0
    finished: bool = False

    @classmethod
    def of(cls, recording: Recording, speed: float | None) -> ReplayProgress:
        counts = recording.message_counts
        return cls(recording.path.name, speed, sum(counts.get(t, 0) for t in FED_TOPICS))

    def as_json(self) -> dict[str, Any]:
        return {
            "file": self.file,
            "speed": self.speed,
            "progress": round(self.fed / self.messages, 3) if self.messages else 1.0,
            "finished": self.finished,
        }


class StatePublisher:
    """Writes SLAM's and the odometry's results into the shared state, as the daemon's tasks do."""

    def __init__(self, state: SharedState, replayer: Replayer, now_s: Callable[[], float] = time.monotonic) -> None:
        self.state = state
        self.replayer = replayer
        self._now_s = now_s

    def encoders(self, time_s: float) -> None:
        state, odo = self.state, self.replayer.odometry.pose
        state.odometry = odo
        x, y, th = compose(state.map_from_odom, (odo.x_m, odo.y_m, odo.theta_rad))
        state.pose.x_m, state.pose.y_m, state.pose.theta_rad = float(x), float(y), float(th)
        state.pose_time_s = time_s

    def slam_step(self, kind: str, what: Any) -> None:
        state, slam = self.state, self.replayer.slam
        state.map = slam.grid
        stats = state.slam
        stats.scans = slam.scans
        stats.keyframes = len(slam.keyframes)
        if kind == "update":
            state.map_from_odom = tuple(float(v) for v in what.map_from_odom)  # type: ignore[assignment]
            state.pose_covariance = what.covariance
            if what.keyframe is not None:
                state.trajectory.append((float(what.pose[0]), float(what.pose[1])))
            return
        # a loop-closure result merged: the keyframes moved, the map may have been rebuilt
        stats.loop_closures = len(slam.closures)
        stats.map_rebuilds += bool(what)
        state.map_from_odom = tuple(float(v) for v in slam.map_from_odom)  # type: ignore[assignment]
        trail = slam.keyframe_poses()[-(state.trajectory.maxlen or len(slam.keyframes)) :]
        state.trajectory = deque(((float(x), float(y)) for x, y, _ in trail), maxlen=state.trajectory.maxlen)

    def run_state(self, value: str) -> None:
        try:
            run_state = RunState(value)
        except ValueError:
            log.warning("recorded run state %r is unknown; the page keeps %s", value, self.state.run_state.value)
            return
        state = self.state
        if run_state.moving and state.started_at_s is None:
            state.begin_run(self._now_s())
        if run_state is RunState.DONE:
            state.finished_at_s = self._now_s()
        state.run_state = run_state


async def feed(
    recording: Recording,
    state: SharedState,
    progress: ReplayProgress,
    executor: ThreadPoolExecutor,
) -> ReplayResult:
    """Feed the recording through SLAM into ``state`` at ``progress.speed``; the result at the end."""
    loop = asyncio.get_running_loop()
    replayer = Replayer(recording, submit=lambda job: executor.submit(job.run))
    publisher = StatePublisher(state, replayer)
    pace = None if progress.speed is None else Pace(progress.speed, loop.time())
    for msg in recording.messages(FED_TOPICS):
        if pace is not None:
            if (due_s := pace.wait_s(msg.log_time_ns, loop.time())) > 0:
                await asyncio.sleep(due_s)
        elif progress.fed % FAST_YIELD_MESSAGES == 0:
            await asyncio.sleep(0)
        if msg.topic == "/mazebot/run_state":
            publisher.run_state(str(msg.data.get("state")))
        else:
            job = replayer.waits_for(msg)
            if job is not None:  # the live run merged this job's result here: wait for it, off the loop
                await asyncio.wrap_future(job)
            for kind, what in replayer.feed(msg):
                publisher.slam_step(kind, what)
            if msg.topic == "/mazebot/encoders":
                publisher.encoders(float(msg.data["time_s"]))
        progress.fed += 1
    progress.finished = True
    if state.run_state.moving:
        state.finished_at_s = time.monotonic()
    return replayer.finish()


async def start_server(
    state: SharedState, progress: ReplayProgress, settings: WebSettings, host: str, port: int
) -> web.AppRunner:
    """The daemon's web application on ``host:port``, marked as a replay; the caller owns cleanup."""
    app = create_app(state, settings=settings, replay=progress.as_json)
    runner = web.AppRunner(app, handle_signals=False, access_log=None, shutdown_timeout=2.0)
    await runner.setup()
    try:
        await web.TCPSite(runner, host, port).start()
    except OSError as exc:
        await runner.cleanup()
        raise HardwareUnavailable(
            f"the replay's web page cannot listen on {host}:{port} ({exc.strerror or exc}); "
            "choose another --port or stop the other program"
        ) from None
    return runner


def replay_settings(web_config: Any) -> WebSettings:
    """``[web]`` as the daemon uses it, with a control token nobody knows: nothing is controlled."""
    return WebSettings.from_config(web_config, secrets.token_hex(16))



def speed_text(speed: float | None) -> str:
    return "as fast as possible" if speed is None else f"at {speed:g}x"
