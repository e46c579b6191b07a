"""The motor control loop on a thread of its own (``[daemon] control_thread``, the real clock).

What the thread is for: a tick falls due while the event loop is busy (a revolution's
SLAM, a planner tick, a loop blocked outright) and runs anyway. And what it must keep:
one writer of the motors, a crash reaching the supervisor, nothing written once stopped.
"""

from __future__ import annotations

import asyncio
import threading
import time

import numpy as np
import pytest

from mazebot.clock import RealClock
from mazebot.config import Config
from mazebot.sdnotify import ControlHeartbeat
from mazebot.slam.ekf import OdometryHistory
from mazebot.state import MotionRequest, RunState, SharedState
from mazebot.tasks import control_task


class Motors:
    """Remembers each write with the thread and the monotonic time it came from."""

    def __init__(self) -> None:
        self.writes: list[tuple[int, float, float, float]] = []  # (thread id, time s, left, right)
        self.fail_after: int | None = None

    def _note(self, left: float, right: float) -> None:
        if self.fail_after is not None and len(self.writes) >= self.fail_after:
            raise RuntimeError("the motor driver broke")
        self.writes.append((threading.get_ident(), time.monotonic(), left, right))

    def stop(self) -> None:
        self._note(0.0, 0.0)

    def set(self, left: float, right: float) -> None:
        self._note(left, right)


def _turning_state(loop: asyncio.AbstractEventLoop) -> SharedState:
    state = SharedState(run_state=RunState.EXPLORING, started_at_s=0.0)
    state.motion_command = MotionRequest(0.0, 0.5, "turn", loop.time() + 3600)  # in place: always allowed
    return state


async def _until(condition, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "condition not met in time"
        await asyncio.sleep(0.005)


async def test_ticks_run_on_their_own_thread_while_the_event_loop_is_blocked() -> None:
    loop = asyncio.get_running_loop()
    motors, state = Motors(), _turning_state(loop)
    heartbeat = ControlHeartbeat(RealClock())
    task = asyncio.create_task(control_task.run(motors, state, heartbeat,
                                                control_task.MotorControl.from_config(Config()), thread=True))
    await _until(lambda: len(motors.writes) >= 3)
    assert {w[0] for w in motors.writes} == {motors.writes[0][0]} != {threading.get_ident()}
    blocked_from = time.monotonic()
    time.sleep(0.6)  # noqa: ASYNC251 - the point: the event loop does nothing for 0.6 s (12 periods)
    blocked_until = time.monotonic()
    during = [w for w in motors.writes if blocked_from <= w[1] <= blocked_until]
    assert len(during) >= 2  # the wheels were still commanded (on the loop: none at all)
    assert any(abs(w[2]) > 0 for w in motors.writes)  # the turn was driven, not only stopped
    assert heartbeat.last_tick_s >= blocked_from  # the systemd watchdog sees the ticks
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    count = len(motors.writes)
    await asyncio.sleep(0.2)
    assert len(motors.writes) == count  # stopped means stopped: no write after the task ended
    assert not any(t.name == "mazebot-control" for t in threading.enumerate())


async def test_a_crash_on_the_control_thread_reaches_the_task_and_brakes() -> None:
    loop = asyncio.get_running_loop()
    motors, state = Motors(), _turning_state(loop)
    control = control_task.MotorControl.from_config(Config())
    original = control.tick
    calls = 0

    def tick(state: SharedState, now_s: float) -> tuple[float, float]:
        nonlocal calls
        calls += 1
        if calls == 4:
            raise ValueError("a broken tick")
        return original(state, now_s)

    control.tick = tick  # type: ignore[method-assign]
    task = asyncio.create_task(control_task.run(motors, state, RealClock(), control, thread=True))
    with pytest.raises(ValueError, match="a broken tick"):
        await asyncio.wait_for(task, 5.0)
    assert motors.writes[-1][2:] == (0.0, 0.0)  # the failing tick's last word was a stop


async def test_faults_from_the_control_thread_are_written_on_the_event_loop() -> None:
    loop = asyncio.get_running_loop()
    motors, state = Motors(), _turning_state(loop)
    from mazebot.io.motors import MotorWriteError

    class Failing(Motors):
        def _note(self, left: float, right: float) -> None:
            raise MotorWriteError("I2C write to channel 1 failed", channel=1, side="left", stopped=False)

    motors = Failing()
    seen_on: list[int] = []
    original = state.raise_fault

    def raise_fault(*args, **kwargs) -> None:
        seen_on.append(threading.get_ident())
        original(*args, **kwargs)

    state.raise_fault = raise_fault  # type: ignore[method-assign]
    task = asyncio.create_task(control_task.run(motors, state, RealClock(),
                                                control_task.MotorControl.from_config(Config()), thread=True))
    await _until(lambda: state.run_state is RunState.FAULT)
    assert seen_on and set(seen_on) == {threading.get_ident()}  # the loop's thread, never the control thread
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task


def test_rows_a_reader_may_hold_are_never_overwritten_by_later_appends() -> None:
    """The control thread interpolates in the odometry history while the odometry task
    appends. A reader takes (buffer, start, end) in one read; whatever is appended after
    it, through every copy into a new buffer, those rows must stay as they were (a buffer
    compacted in place would move other poses under the reader)."""
    history = OdometryHistory(horizon_s=0.004, capacity=8)
    for k in range(6):
        history.append(k * 0.001, k * 0.001, 0.0, 0.0)
    buf, start, end = history._live  # what OdometryHistory.at reads at once
    held = buf[start:end].copy()
    for k in range(6, 200):  # enough to fill the buffer and copy it on many times
        history.append(k * 0.001, k * 0.001, 0.0, 0.0)
        assert np.array_equal(buf[start:end], held), f"rows under a reader changed at append {k}"
    assert float(history.at(np.array([0.1985]))[0][0]) == pytest.approx(0.1985)


async def test_once_the_daemon_is_stopping_the_control_loop_commands_zero() -> None:
    """The supervisor zeroes the motors before it cancels the tasks; a tick on the control
    thread in between must not drive them again."""
    loop = asyncio.get_running_loop()
    motors, state = Motors(), _turning_state(loop)
    task = asyncio.create_task(control_task.run(motors, state, RealClock(),
                                                control_task.MotorControl.from_config(Config()), thread=True))
    await _until(lambda: any(abs(w[2]) > 0 for w in motors.writes))
    from mazebot.tasks.supervisor import Supervisor

    Supervisor(state, motors, RealClock(), exit_on_fault=False).request_stop("the test is over")
    stopped_at = time.monotonic()
    await asyncio.sleep(0.3)  # six periods with the task still running
    after = [w for w in motors.writes if w[1] > stopped_at]
    assert len(after) >= 2 and all(w[2:] == (0.0, 0.0) for w in after)
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
