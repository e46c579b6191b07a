"""Applies the user's start/stop commands (from the web page) to the run state."""

from __future__ import annotations

import logging

from mazebot.clock import Clock
from mazebot.state import RunState, SharedState

log = logging.getLogger(__name__)


def apply_command(command: str, state: SharedState, motors, clock: Clock) -> str:
    """Apply one command; return a short human answer. Stop always wins and always stops."""
    if command == "stop":
        motors.stop()
        if state.run_state in (RunState.RUNNING, RunState.IDLE, RunState.DONE):
            state.run_state = RunState.STOPPED
        return "stopped"
    if command == "start":
        if state.run_state is RunState.FAULT:
            fault = state.active_fault
            return f"cannot start: {fault.message if fault else 'a fault is active'}"
        if state.run_state is not RunState.RUNNING:
            state.run_state = RunState.RUNNING
            state.started_at_s = clock.now_s()
        return "running"
    return f"unknown command {command!r}; expected start or stop"


async def run(state: SharedState, motors, clock: Clock) -> None:
    while True:
        command = await state.commands.get()
        answer = apply_command(command, state, motors, clock)
        log.info("command %s: %s", command, answer)
