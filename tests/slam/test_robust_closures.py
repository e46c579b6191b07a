"""Dynamic covariance scaling: a wrong loop closure is down-weighted, the right ones keep their pull."""

from __future__ import annotations

import numpy as np

from mazebot.geometry import relative_pose
from mazebot.slam.posegraph import PoseGraph
from mazebot.slam.robust_closures import dcs_weights, optimize_dcs


def test_dcs_weights_keep_agreeing_edges_and_shrink_the_others() -> None:
    w = dcs_weights(np.array([0.0, 5.0, 11.34, 100.0, 1e4]), 11.34)
    assert w[0] == 1.0 and w[1] == 1.0 and w[2] == 1.0
    assert 0.04 < w[3] < 0.06  # (2 Φ / (Φ + χ²))²
    assert w[4] < 1e-5


def _loop_graph(rng: np.random.Generator, wrong_shift_m: float) -> tuple[np.ndarray, tuple, np.ndarray, np.ndarray]:
    """A robot driving twice round a 4 m square (one pose every 0.5 m); noisy chain, true closures, one wrong."""
    side = 8
    truth = []
    for _lap in range(2):
        for edge in range(4):
            for k in range(side):
                heading = edge * np.pi / 2
                corner = [np.array([0, 0]), np.array([4, 0]), np.array([4, 4]), np.array([0, 4])][edge]
                step = 0.5 * k * np.array([np.cos(heading), np.sin(heading)])
                truth.append([*(corner + step), heading])
    truth = np.array(truth, dtype=np.float64)
    truth[:, :2] += rng.normal(0.0, 0.001, (len(truth), 2))
    n = len(truth)
    inc = relative_pose(truth[:-1], truth[1:])
    noisy = inc + rng.normal(0.0, 1.0, inc.shape) * np.array([0.02, 0.02, 0.01])
    seq_info = np.diag([1 / 0.02**2, 1 / 0.02**2, 1 / 0.01**2])
    ei = list(range(n - 1))
    ej = list(range(1, n))
    z = list(noisy)
    omega = [seq_info] * (n - 1)
    # the second lap sees the first lap's poses: true closures every 4 poses
    closure_info = np.diag([1 / 0.02**2, 1 / 0.02**2, 1 / 0.005**2])
    for i in range(0, 32, 4):
        ei.append(i)
        ej.append(i + 32)
        z.append(relative_pose(truth[i], truth[i + 32]))
        omega.append(closure_info)
    # and one wrong one: pose 50 "seen" from pose 10 a metre away from where it is
    wrong = relative_pose(truth[10], truth[50]) + np.array([wrong_shift_m, 0.0, 0.0])
    ei.append(10)
    ej.append(50)
    z.append(wrong)
    omega.append(closure_info)
    # the initial guess: the noisy chain integrated
    guess = [truth[0]]
    for u in noisy:
        c, s = np.cos(guess[-1][2]), np.sin(guess[-1][2])
        last = guess[-1]
        guess.append(np.array([last[0] + c * u[0] - s * u[1], last[1] + s * u[0] + c * u[1], last[2] + u[2]]))
    edges = (np.array(ei), np.array(ej), np.array(z), np.array(omega))
    closure = np.array([j - i > 1 for i, j in zip(ei, ej, strict=True)])
    return truth, edges, closure, np.array(guess)


def test_a_wrong_closure_bends_plain_least_squares_but_not_dcs() -> None:
    _, edges, closure, guess = _loop_graph(np.random.default_rng(3), wrong_shift_m=1.0)
    plain = PoseGraph()
    plain.add_vertices(guess)
    plain.add_edges(*edges)
    plain.optimize(max_iterations=30, method="lm")
    robust = optimize_dcs(guess, edges, closure, phi=11.34, max_rounds=6)
    clean = PoseGraph()  # what the right edges alone say
    clean.add_vertices(guess)
    clean.add_edges(*(a[:-1] for a in edges))
    clean.optimize(max_iterations=30, method="lm")
    assert np.max(np.hypot(*(plain.vertices[:, :2] - clean.vertices[:, :2]).T)) > 0.15  # the wrong metre pulls
    assert np.max(np.hypot(*(robust.vertices[:, :2] - clean.vertices[:, :2]).T)) < 0.01
    assert robust.weights[-1] < 0.01  # the wrong closure switched (almost) off
    assert np.all(robust.weights[:-1] > 0.9)  # the right ones keep their weight


def test_without_a_wrong_closure_dcs_is_one_plain_optimization() -> None:
    _, edges, closure, guess = _loop_graph(np.random.default_rng(4), wrong_shift_m=0.0)
    plain = PoseGraph()
    plain.add_vertices(guess)
    plain.add_edges(*edges)
    plain.optimize(max_iterations=30, method="lm")
    robust = optimize_dcs(guess, edges, closure, phi=11.34)
    assert robust.rounds == 1
    np.testing.assert_allclose(robust.vertices, plain.vertices, atol=1e-9)
    assert np.all(robust.weights == 1.0)
