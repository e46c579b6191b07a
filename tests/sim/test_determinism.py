"""Virtual-time runs are reproducible: the same seed gives the same trajectory.

The benchmark's figures are only comparable from one change to the next if a run is a
function of its seed. On virtual time every wait is a timer, so the order of events is
fixed; the simulator's speed-ups (batched lidar sampling, bounded pin history, skipped
polls) must not change that. Loop-closure jobs run in a worker process, but their
results are handed to SLAM at a fixed simulated time after submission
(:mod:`mazebot.bench.virtual_executor`), so SLAM's estimate repeats too.
"""

from __future__ import annotations

import numpy as np
import pytest

from mazebot.bench.runner import RunSpec, run_one
from mazebot.config import Config

pytestmark = pytest.mark.slow  # whole simulated runs, twice


def _short_run(seed: int) -> tuple[np.ndarray, int, int]:
    _, record = run_one(Config(), RunSpec(None, (4, 4), seed, "scripted", max_sim_s=6.0))
    robot = record.hardware.sim
    assert record.state.sensors.lidar_revolutions > 10  # the lidar really ran through the driver
    return np.asarray(robot.trajectory), robot.left_signal.edges, record.state.sensors.lidar_revolutions


def test_same_seed_same_trajectory() -> None:
    first, second = _short_run(7), _short_run(7)
    np.testing.assert_array_equal(first[0], second[0])
    assert first[1:] == second[1:]
    assert len(first[0]) > 50 and first[1] > 500  # it drove, and the encoders saw it


def test_another_seed_another_run() -> None:
    a, b = _short_run(7)[0], _short_run(8)[0]
    assert a.shape != b.shape or not np.array_equal(a, b)


def test_same_seed_same_slam_estimate_with_loop_closures_merged() -> None:
    def estimate() -> tuple[np.ndarray, int]:
        _, record = run_one(Config(), RunSpec(None, (4, 4), 3, "scripted", max_sim_s=40.0))
        return np.asarray(record.est_poses), len(record.state.loop_job_ms)

    (first, jobs), (second, _) = estimate(), estimate()
    assert jobs >= 2  # corrections from the worker were merged along the way
    np.testing.assert_array_equal(first, second)
    assert np.ptp(first[:, 0]) > 0.3  # and the estimate went somewhere
