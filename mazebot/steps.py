"""Work in stages: a generator that yields between its stages and returns a result.

A long computation on the event loop (a SLAM keyframe scan, a planner tick) holds up
every other task until it ends; the 20 Hz control tick then runs late by as much. Written
as a generator that yields where it may be interrupted, the same code serves both kinds
of caller: offline tools run it to the end at once (:func:`run_steps`), the daemon's
tasks let the loop run between two stages (:func:`run_steps_async`). The stages and
their order do not depend on the caller, so neither does the result.

Example::

    def work() -> Generator[None, None, int]:
        a = first_half()
        yield                       # the loop may run other tasks here
        return a + second_half()

    run_steps(work())               # offline: all at once
    await run_steps_async(work())   # in a task: the loop runs between the halves

The staged generator is the one definition; its plain form (the same arguments, the
result at once) is made from it, so the signature is written once::

    def match_scan_steps(target: Target, ...) -> Generator[None, None, IcpResult]: ...
    match_scan = all_at_once(match_scan_steps, "Align a scan to a target.")

    class Slam:
        def update_steps(self, scan: Scan, ...) -> Generator[None, None, SlamUpdate]: ...
        update = all_at_once_method(update_steps, "Process one revolution.")
"""

from __future__ import annotations

import asyncio
import functools
import inspect
import time
import typing
from collections.abc import Callable, Generator
from typing import Concatenate, ParamSpec, TypeVar

T = TypeVar("T")
P = ParamSpec("P")
S = TypeVar("S")

_SUFFIX = "_steps"


def run_steps(steps: Generator[None, None, T]) -> T:
    """Run every stage at once and return the result."""
    while True:
        try:
            next(steps)
        except StopIteration as stop:
            return stop.value


def _plain_name(staged: Callable[..., object]) -> str:
    """``x`` for a staged ``x_steps``: the plain form's name."""
    name = staged.__name__
    if not name.endswith(_SUFFIX):
        raise ValueError(f"a staged function's name ends in {_SUFFIX!r}; got {name!r}: rename it x{_SUFFIX}")
    return name.removesuffix(_SUFFIX)


def _plain_doc(summary: str | None, staged_ref: str) -> str:
    """The plain form's docstring: what it does, then how it differs from the staged form."""
    how = f"Runs every stage at once (:func:`mazebot.steps.run_steps`); {staged_ref} is the staged form."
    return how if not summary else f"{inspect.cleandoc(summary)}\n\n{how}"


def _result_annotation(annotation: object) -> object:
    """``T`` of a ``Generator[None, None, T]`` return annotation (a string under postponed evaluation)."""
    if isinstance(annotation, str):
        prefix, suffix = "Generator[None, None, ", "]"
        if annotation.startswith(prefix) and annotation.endswith(suffix):
            return annotation[len(prefix) : -len(suffix)]
        return inspect.Signature.empty
    args = typing.get_args(annotation)
    return args[2] if len(args) == 3 else inspect.Signature.empty


def _named(plain: Callable[..., object], staged: Callable[..., object], doc: str) -> None:
    """Name ``plain`` after ``staged`` without its suffix; ``help()`` shows its parameters and its result."""
    functools.update_wrapper(plain, staged)
    plain.__name__ = _plain_name(staged)
    plain.__qualname__ = staged.__qualname__.removesuffix(_SUFFIX)
    plain.__doc__ = doc
    signature = inspect.signature(staged)
    plain.__signature__ = signature.replace(  # type: ignore[attr-defined]
        return_annotation=_result_annotation(signature.return_annotation)
    )


def all_at_once(
    staged: Callable[P, Generator[None, None, T]], doc: str | None = None
) -> Callable[P, T]:
    """The plain form of a staged function ``x_steps``: same arguments, every stage at once.

    For callers with no event loop to keep running (offline tools, tests). Typed with the
    staged function's own parameters, so mypy checks a call of either form the same way.
    ``doc`` says what the function does (the plain form's help adds that it runs the
    stages at once and names the staged one)::

        build_target = all_at_once(build_target_steps, "The keyframes' points as an ICP target.")
    """

    def plain(*args: P.args, **kwargs: P.kwargs) -> T:
        return run_steps(staged(*args, **kwargs))

    _named(plain, staged, _plain_doc(doc, f":func:`{staged.__name__}`"))
    return plain


def all_at_once_method(
    staged: Callable[Concatenate[S, P], Generator[None, None, T]], doc: str | None = None
) -> Callable[Concatenate[S, P], T]:
    """:func:`all_at_once` for a method ``x_steps``, in the class body after it: ``x = all_at_once_method(x_steps)``.

    The staged method is looked up on the instance at each call, so a subclass that
    overrides only ``x_steps`` (to add a stage, or to observe the result) changes
    ``x`` too: both forms always run the same stages.
    """
    name = staged.__name__

    def plain(self: S, /, *args: P.args, **kwargs: P.kwargs) -> T:
        steps: Generator[None, None, T] = getattr(self, name)(*args, **kwargs)
        return run_steps(steps)

    _named(plain, staged, _plain_doc(doc, f":meth:`{name}`"))
    return plain


async def run_steps_async(steps: Generator[None, None, T], cpu_s: list[float] | None = None) -> T:
    """Run the stages with the event loop free in between; adds their thread CPU time to ``cpu_s[0]``.

    The CPU time counts only the stages themselves, not what other tasks did in between
    (the benchmark's per-scan figure). If the awaiting task is cancelled, the generator
    is closed where it stands.
    """
    staged = steps if cpu_s is None else timed_stages(steps, cpu_s)
    try:
        while True:
            try:
                next(staged)
            except StopIteration as stop:
                return stop.value
            await asyncio.sleep(0)
    finally:
        staged.close()


def timed_stages(steps: Generator[None, None, T], cpu_s: list[float]) -> Generator[None, None, T]:
    """The same stages, each one's thread CPU time added to ``cpu_s[0]`` as it runs.

    Only the stages' own CPU counts, not what the thread did between them; closing the
    wrapper closes ``steps`` where it stands.
    """
    try:
        while True:
            start_s = time.thread_time()
            try:
                next(steps)
            except StopIteration as stop:
                return stop.value
            finally:
                cpu_s[0] += time.thread_time() - start_s
            yield
    finally:
        steps.close()
