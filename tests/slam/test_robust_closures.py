"""Dynamic covariance scaling: a wrong loop closure is down-weighted, the right ones keep their pull; with
``dcs_sequential_phi`` a wrong sequential edge that the loops contradict too, and no edge off the loops."""

from __future__ import annotations

import numpy as np

from mazebot.geometry import compose, relative_pose
from mazebot.slam.posegraph import PoseGraph
from mazebot.slam.robust_closures import dcs_weights, optimize_dcs, robust_edges, spanned_by_closures


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


#: the sequential edge made wrong along its axis in :func:`_two_laps_and_a_corridor` (on the first lap's second side)
WRONG_EDGE = 12


def _two_laps_and_a_corridor(
    rng: np.random.Generator, wrong_m: float
) -> tuple[np.ndarray, tuple[np.ndarray, ...], np.ndarray]:
    """A robot driving twice round a 4 m square (a pose every 0.5 m), then 4 m down a corridor with no loop.

    The chain's matches claim 2 mm and 0.06° as ICP's do on a building's scans (and are that good), but
    edge :data:`WRONG_EDGE` and one edge of the corridor are ``wrong_m`` too long along the direction of
    travel, as ICP stopping near a prediction a decimetre off. The second lap sees every pose of the first:
    closures true to the truth, at a tenth of a match's information (``[slam.loop] information_scale``).
    Returns the true poses, the edges ``(i, j, z, Ω)`` (the chain first) and the chain integrated.
    """
    lap = 32
    truth = []
    for _lap in range(2):
        for side in range(4):
            heading = side * np.pi / 2
            corner = np.array([[0, 0], [4, 0], [4, 4], [0, 4]][side], dtype=np.float64)
            for k in range(lap // 4):
                truth.append([*(corner + 0.5 * k * np.array([np.cos(heading), np.sin(heading)])), heading])
    x, y, heading = truth[-1]
    truth += [[x + 0.5 * k * np.cos(heading), y + 0.5 * k * np.sin(heading), heading] for k in range(1, 9)]
    poses = np.array(truth)
    n = len(poses)
    std = np.array([0.002, 0.002, 0.001])
    z = relative_pose(poses[:-1], poses[1:]) + rng.normal(0.0, 1.0, (n - 1, 3)) * std
    z[WRONG_EDGE, 0] += wrong_m
    z[n - 4, 0] += wrong_m
    match = np.diag(1.0 / std**2)
    first, second = np.arange(lap), np.arange(lap) + lap
    edges = (
        np.concatenate([np.arange(n - 1), first]),
        np.concatenate([np.arange(1, n), second]),
        np.concatenate([z, relative_pose(poses[first], poses[second])]),
        np.array([match] * (n - 1) + [0.1 * match] * lap),
    )
    guess = [poses[0]]
    for step in z:
        guess.append(compose(guess[-1], step))
    return poses, edges, np.array(guess)


def test_a_sequential_edge_the_loops_contradict_is_given_up_with_dcs_sequential_phi() -> None:
    truth, edges, guess = _two_laps_and_a_corridor(np.random.default_rng(0), wrong_m=0.2)
    n = len(truth)
    on_loops = slice(0, 64)
    errors = {}
    for sequential_phi in (0.0, 11.34):
        robust, phi, _ = robust_edges(edges[0], edges[1], n, 11.34, sequential_phi)
        result = optimize_dcs(guess, edges, robust, phi)
        errors[sequential_phi] = np.hypot(*(result.vertices[on_loops, :2] - truth[on_loops, :2]).T)
    assert np.max(errors[0.0]) > 0.1  # the closures alone: the wrong step bends both laps by decimetres
    assert np.max(errors[11.34]) < 0.02  # the wrong step given up: both laps within 2 cm of the truth


def test_an_edge_no_closure_spans_keeps_its_weight() -> None:
    truth, edges, guess = _two_laps_and_a_corridor(np.random.default_rng(0), wrong_m=0.2)
    n = len(truth)
    robust, phi, sequential = robust_edges(edges[0], edges[1], n, 11.34, 11.34)
    assert robust[WRONG_EDGE]
    assert not np.any(robust[63 : n - 1])  # the corridor after the last closure: its only ties
    result = optimize_dcs(guess, edges, robust, phi)
    assert result.weights[sequential][WRONG_EDGE] < 0.1
    assert np.all(result.weights[~sequential] > 0.5)  # the true closures keep their pull
    # the corridor is the chain's, wrong step and all: relative to the loop's last pose, as the edges say
    corridor = relative_pose(result.vertices[63], result.vertices[64:])
    chained = relative_pose(guess[63], guess[64:])
    np.testing.assert_allclose(corridor, chained, atol=0.01)


def test_spanned_by_closures_counts_the_cycles_through_each_sequential_edge() -> None:
    ei = np.array([0, 1, 2, 3, 4, 0, 1, 2])
    ej = np.array([1, 2, 3, 4, 5, 3, 4, 7])  # the last one to a vertex beyond the chain (the wall grid's)
    closure = ej - ei > 1
    np.testing.assert_array_equal(spanned_by_closures(ei, ej, closure, 6), [1, 2, 2, 1, 0])


def test_without_dcs_sequential_phi_only_the_closures_are_robust() -> None:
    _, edges, _ = _two_laps_and_a_corridor(np.random.default_rng(0), wrong_m=0.0)
    robust, phi, sequential = robust_edges(edges[0], edges[1], 72, 11.34, 0.0)
    np.testing.assert_array_equal(robust, edges[1] - edges[0] > 1)
    assert np.all(phi == 11.34) and not np.any(sequential)
