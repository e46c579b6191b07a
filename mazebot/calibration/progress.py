"""The steps of a calibration and how far each has come: printed on the terminal, JSON for a page.

A :class:`Progress` holds one :class:`Step` per routine in the order they run. Each
change is handed to ``on_change`` (the terminal prints a line) and the whole list is
``as_json()`` (what a setup page or ``/api/calibration`` would show).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

StepState = Literal["pending", "running", "done", "failed"]


@dataclass
class Step:
    """One routine of the calibration: ``measured`` holds its figures once known (units in the keys)."""

    name: str
    title: str
    state: StepState = "pending"
    detail: str = ""
    measured: dict[str, Any] = field(default_factory=dict)


class Progress:
    """The calibration's steps, in order; ``on_change(step)`` is called on every change."""

    def __init__(self, steps: list[tuple[str, str]], on_change: Callable[[Step], None] | None = None) -> None:
        self.steps = [Step(name, title) for name, title in steps]
        self._on_change = on_change

    def step(self, name: str) -> Step:
        return next(s for s in self.steps if s.name == name)

    def update(self, name: str, state: StepState | None = None, detail: str | None = None, **measured: Any) -> None:
        step = self.step(name)
        if state is not None:
            step.state = state
        if detail is not None:
            step.detail = detail
        step.measured.update(measured)
        if self._on_change is not None:
            self._on_change(step)

    def index(self, name: str) -> int:
        return next(i for i, s in enumerate(self.steps) if s.name == name) + 1

    def as_json(self) -> list[dict[str, Any]]:
        return [asdict(s) for s in self.steps]
