"""The plain form of a staged function: the same stages, the same result, the staged one's signature."""

from __future__ import annotations

import inspect
from collections.abc import Generator

import pytest

from mazebot.steps import all_at_once, all_at_once_method, run_steps


def halves_steps(a: int, b: int = 2, *, scale: int = 1) -> Generator[None, None, int]:
    """Two halves with a stage boundary between them."""
    first = a * scale
    yield
    return first + b * scale


halves = all_at_once(halves_steps, "Add two numbers, scaled.")


class Counter:
    def __init__(self) -> None:
        self.stages = 0

    def count_steps(self, n: int) -> Generator[None, None, int]:
        for _ in range(n):
            self.stages += 1
            yield
        return self.stages

    count = all_at_once_method(count_steps, "Count ``n`` stages.")


class Audited(Counter):
    """Overrides only the staged form: the plain one must run it too."""

    def count_steps(self, n: int) -> Generator[None, None, int]:
        total = yield from super().count_steps(n)
        return -total


def test_plain_function_returns_what_the_stages_return() -> None:
    assert halves(3, scale=2) == run_steps(halves_steps(3, scale=2)) == 10


def test_plain_function_has_the_staged_signature_and_its_own_name_and_help() -> None:
    staged = inspect.signature(halves_steps)
    assert inspect.signature(halves) == staged.replace(return_annotation="int")  # the result, not the generator
    assert halves.__name__ == "halves"
    doc = inspect.getdoc(halves) or ""
    assert doc.startswith("Add two numbers, scaled.")
    assert "every stage at once" in doc and "halves_steps" in doc


def test_plain_method_runs_every_stage() -> None:
    counter = Counter()
    assert counter.count(3) == 3
    assert counter.stages == 3
    assert Counter.count.__name__ == "count"
    assert Counter.count.__qualname__ == "Counter.count"


def test_plain_method_follows_a_subclass_that_overrides_the_staged_one() -> None:
    assert Audited().count(2) == -2


def test_a_staged_function_is_named_with_the_suffix() -> None:
    def halves(a: int) -> Generator[None, None, int]:
        yield
        return a

    with pytest.raises(ValueError, match="_steps"):
        all_at_once(halves)
