"""The CPU budget counts a part's own thread CPU time, not the wall time around it."""

from __future__ import annotations

import threading
import time
import tracemalloc

import numpy as np
import pytest

from mazebot.cpu_budget import PARTS, RECENT_CALLS, CpuBudget, PartMeter, RecentValues
from mazebot.state import SharedState
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


def test_recent_values_keep_the_newest_oldest_first() -> None:
    ring = RecentValues(maxlen=3)
    assert len(ring) == 0 and list(ring) == [] and np.asarray(ring).shape == (0,)
    for v in (1.0, 2.0):
        ring.append(v)
    assert list(ring) == [1.0, 2.0]
    for v in (3.0, 4.0, 5.0):
        ring.append(v)
    assert list(ring) == [3.0, 4.0, 5.0]
    assert ring[0] == 3.0 and ring[-1] == 5.0
    assert np.asarray(ring, dtype=float).tolist() == [3.0, 4.0, 5.0]
    with pytest.raises(ValueError, match="at least one value"):
        RecentValues(maxlen=0)


def test_a_long_life_stays_within_the_bound() -> None:
    """A day of 50 Hz calls: the meter keeps its last RECENT_CALLS, in the memory it had after the first of them."""
    meter = PartMeter("odometry")
    for _ in range(RECENT_CALLS):
        meter.add(0.001)
    tracemalloc.start()
    try:
        before, _ = tracemalloc.get_traced_memory()
        for k in range(5 * RECENT_CALLS):
            meter.add(0.001 * (k % 7))
        after, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert meter.calls == 6 * RECENT_CALLS
    assert len(meter.recent_ms) == RECENT_CALLS
    assert after - before < 10_000  # bytes: nothing per call
    assert meter.summary(robot_s=100.0)["p99_ms"] == pytest.approx(6.0)


def test_the_shared_states_series_are_bounded() -> None:
    """Every per-call series of the shared state keeps a fixed number of values, however long the run."""
    state = SharedState()
    series = {name: getattr(state, name) for name in
              ("odometry_edge_age_ms", "control_lateness_ms", "scan_ms", "loop_job_ms", "planner_ms")}
    for name, values in series.items():
        assert isinstance(values, RecentValues), name
        for k in range(values.maxlen + 100):
            values.append(float(k))
        assert len(values) == values.maxlen, name
        assert values[-1] == float(values.maxlen + 99), name
        assert np.asarray(values).nbytes == 8 * values.maxlen, name
