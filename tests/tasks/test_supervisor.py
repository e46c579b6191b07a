"""The supervisor: a crashing task stops the motors and becomes a visible fault."""

from __future__ import annotations

import asyncio

from mazebot.clock import RealClock
from mazebot.errors import EXIT_OK, EXIT_SOFTWARE
from mazebot.state import RunState, SharedState
from mazebot.tasks.supervisor import Supervisor


class RecordingMotors:
    def __init__(self) -> None:
        self.stops = 0

    def stop(self) -> None:
        self.stops += 1


async def _crash() -> None:
    await asyncio.sleep(0)
    raise RuntimeError("sensor exploded")


async def _forever(cancelled: list[str]) -> None:
    try:
        await asyncio.sleep(3600)
    except asyncio.CancelledError:
        cancelled.append("yes")
        raise


async def test_crash_stops_motors_records_fault_and_keeps_others_running() -> None:
    state, motors = SharedState(), RecordingMotors()
    sup = Supervisor(state, motors, RealClock(), exit_on_fault=False)
    cancelled: list[str] = []
    sup.start("slam", _crash)
    sup.start("web", lambda: _forever(cancelled))
    await asyncio.sleep(0.05)
    assert motors.stops == 1
    assert state.run_state is RunState.FAULT
    assert state.active_fault is not None
    assert state.active_fault.source == "slam"
    assert "RuntimeError: sensor exploded" in state.active_fault.message
    assert not sup.tasks["web"].done()
    sup.request_stop("test")
    assert await sup.wait() == EXIT_OK
    assert cancelled == ["yes"]


async def test_exit_on_fault_returns_software_error() -> None:
    state, motors = SharedState(), RecordingMotors()
    sup = Supervisor(state, motors, RealClock(), exit_on_fault=True)
    sup.start("slam", _crash)
    assert await asyncio.wait_for(sup.wait(), 1.0) == EXIT_SOFTWARE


async def test_request_stop_zeroes_motors_before_anything_is_cancelled() -> None:
    state, motors = SharedState(), RecordingMotors()
    sup = Supervisor(state, motors, RealClock(), exit_on_fault=False)
    sup.start("idle", lambda: _forever([]))
    sup.request_stop("signal SIGTERM")
    assert motors.stops == 1  # synchronously, inside the request
    await sup.wait()
    assert all(t.done() for t in sup.tasks.values())


async def test_a_failing_motor_stop_is_not_swallowed_silently(caplog) -> None:
    class BrokenMotors:
        def stop(self) -> None:
            raise OSError("I2C write failed")

    sup = Supervisor(SharedState(), BrokenMotors(), RealClock(), exit_on_fault=False)
    sup.request_stop("test")
    await sup.wait()
    assert "could not stop the motors" in caplog.text
