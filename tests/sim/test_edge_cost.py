"""The emulated Pi GPIO path per edge (:mod:`mazebot.sim.edge_cost`), which the quota bench puts in
place of the simulator's GPIO edge thread."""

from __future__ import annotations

import pytest

from mazebot.sim.edge_cost import STAGES, measure_stages, pi_path_s_per_edge, simulator_excess_s_per_edge


def test_each_stage_is_timed_per_edge_and_the_pi_path_leaves_the_mocks_bookkeeping_out() -> None:
    costs = measure_stages(cycles=500, repeats=3)
    assert set(costs) == set(STAGES)
    assert all(0 < v < 1e-3 for v in costs.values())  # CPU seconds per edge: microseconds, not more
    pi = pi_path_s_per_edge(costs)
    assert pi == max(costs["mock_decode"] - costs["mock_alone"], costs["decode"]) + costs["lgpio_loop"]
    # the decoder itself is always in it, and so is lgpio's loop
    assert pi >= costs["decode"] + costs["lgpio_loop"]
    # the stand-in's loop holds our decoder too; what it does beyond the Pi's path is never negative
    assert costs["sim_path"] > costs["decode"]
    assert simulator_excess_s_per_edge(costs) == max(costs["sim_path"] - pi, 0.0)


def test_the_fastest_of_the_repeats_is_at_most_their_median() -> None:
    ticks = iter(range(1000))

    def clock() -> float:  # a fake clock: every run of every stage takes longer than the one before
        return float(next(ticks)) ** 2

    best = measure_stages(cycles=1, repeats=3, clock=clock, best=True)
    ticks = iter(range(1000))
    median = measure_stages(cycles=1, repeats=3, clock=clock)
    assert all(best[name] < median[name] for name in STAGES)


@pytest.mark.parametrize("cycles, repeats", [(0, 3), (10, 0)])
def test_nothing_to_time_is_an_error(cycles: int, repeats: int) -> None:
    with pytest.raises(ValueError, match="at least 1"):
        measure_stages(cycles, repeats)
