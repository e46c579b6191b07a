"""The CPU budget counts a part's own thread CPU time, not the wall time around it."""

from __future__ import annotations

import threading
import time

import pytest

from mazebot.cpu_budget import PARTS, CpuBudget, PartMeter
from mazebot.steps import run_steps


def _spin(cpu_s: float) -> None:
    end = time.thread_time() + cpu_s
    while time.thread_time() < end:
        pass


def test_measure_counts_cpu_not_sleep() -> None:
    meter = PartMeter("odometry")
    with meter.measure():
        time.sleep(0.05)  # waiting is not CPU
    with meter.measure():
        _spin(0.02)
    assert meter.calls == 2
    assert meter.recent_ms[0] < 5.0
    assert meter.recent_ms[1] >= 20.0
    assert meter.cpu_s == pytest.approx(sum(meter.recent_ms) / 1e3)


def test_other_threads_do_not_count() -> None:
    meter = PartMeter("control tick")
    busy = threading.Thread(target=_spin, args=(0.1,))
    with meter.measure():
        busy.start()
        busy.join()  # another thread's 0.1 s of CPU while this one waits
    assert meter.recent_ms[0] < 20.0


def test_steps_count_only_their_stages_as_one_call() -> None:
    meter = PartMeter("dwa")

    def work():
        _spin(0.01)
        yield
        _spin(0.01)
        return 7

    wrapped = meter.steps(work())
    next(wrapped)  # first stage
    _spin(0.03)  # what the loop does between the stages is not the part's
    with pytest.raises(StopIteration) as stop:
        next(wrapped)
    assert stop.value.value == 7
    assert meter.calls == 1
    assert 20.0 <= meter.recent_ms[0] < 30.0
    assert run_steps(meter.steps(work())) == 7
    assert meter.calls == 2


def test_table_lists_every_part_and_rates_per_robot_second() -> None:
    budget = CpuBudget()
    meter = budget.part("slam per revolution")
    for ms in (1.0, 2.0, 3.0, 100.0):
        meter.add(ms / 1e3)
    table = budget.table(robot_s=2.0)
    assert list(table) == list(PARTS)
    assert table["slam per revolution"]["calls"] == 4
    assert table["slam per revolution"]["cpu_ms_per_s"] == pytest.approx(53.0)
    assert table["slam per revolution"]["p99_ms"] > 90.0
    assert table["saving"] == {"calls": 0, "cpu_ms_per_s": None, "p50_ms": None, "p99_ms": None}


def test_unknown_part_is_refused_by_name() -> None:
    budget = CpuBudget()
    with pytest.raises(ValueError, match="unknown part 'slma'"):
        budget.part("slma")
    with pytest.raises(ValueError, match="unknown part 'gps'"):
        budget.adopt(PartMeter("gps"))


def test_each_garbage_collection_is_charged_to_its_meter_while_metered_and_none_after() -> None:
    import gc

    from mazebot.cpu_budget import garbage_collection_metered

    meter = PartMeter("garbage collection")
    cycles = []
    with garbage_collection_metered(meter):
        for _ in range(20_000):  # cycles to find: a collection that has work to do
            node: list = []
            node.append(node)
            cycles.append(node)
        cycles.clear()
        gc.collect()
        gc.collect(0)
    assert meter.calls >= 2 and meter.cpu_s > 0
    calls = meter.calls
    gc.collect()
    assert meter.calls == calls  # the callback is gone with the block
