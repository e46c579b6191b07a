"""The taps (mazebot.taps): listeners hear what happened; a broken one is logged, never in the way."""

from __future__ import annotations

import logging

import pytest

from mazebot import taps
from mazebot.state import Event, RunState, SharedState


def test_notify_calls_each_listener_in_order_and_survives_a_broken_one(caplog: pytest.LogCaptureFixture) -> None:
    heard: list[tuple[str, int]] = []

    def broken(value: int) -> None:
        raise ValueError("listener bug")

    listeners = (lambda v: heard.append(("first", v)), broken, lambda v: heard.append(("last", v)))
    before = taps.failures["test tap"]
    with caplog.at_level(logging.ERROR, logger="mazebot.taps"):
        taps.notify(listeners, 7, "test tap")
        taps.notify(listeners, 8, "test tap")
    assert heard == [("first", 7), ("last", 7), ("first", 8), ("last", 8)]
    assert taps.failures["test tap"] == before + 2
    assert caplog.text.count("a listener of test tap failed") == (1 if before == 0 else 0)  # not one line per call


def test_note_listeners_hear_each_event_the_status_page_keeps() -> None:
    state = SharedState()
    heard: list[Event] = []
    state.note_listeners += (heard.append,)
    state.note("lidar", "reconnected", 12.5)
    state.raise_fault("encoders", "left encoder silent", 13.0)
    assert heard == [Event("lidar", "reconnected", 12.5), Event("encoders", "left encoder silent", 13.0)]
    assert list(state.events) == heard


def test_a_failing_note_listener_cannot_stop_a_fault(caplog: pytest.LogCaptureFixture) -> None:
    # raise_fault notes before it moves to FAULT (the state in which the control task stops the
    # wheels): a listener that raises there must not leave the robot exploring
    state = SharedState(run_state=RunState.EXPLORING)

    def broken(event: Event) -> None:
        raise RuntimeError("a logger's bug")

    state.note_listeners = (broken,)
    with caplog.at_level(logging.ERROR, logger="mazebot.taps"):
        state.raise_fault("slam", "a scan could not be processed", 3.0)
    assert state.run_state is RunState.FAULT and state.interrupted is RunState.EXPLORING
    assert [e.source for e in state.events] == ["slam"]
