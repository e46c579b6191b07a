"""Orientation initialization of the pose graph (``initialize_orientations``, ``optimize(initialize=...)``):
angle unwrapping along the spanning tree, recovery of the optimum from a poor initial guess where
plain LM stalls, the real graphs, and the CLI's ``--init``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mazebot.slam.g2o import read_g2o, write_g2o
from mazebot.slam.posegraph import (
    PoseGraph,
    PoseGraphError,
    compose,
    estimate_headings,
    relative_pose,
    rotation_information,
    wrap_angle,
)
from tests.data_paths import POSEGRAPHS
from tests.slam.test_posegraph import lap_trajectory, run_cli

#: GTSAM 4.3 Levenberg-Marquardt from the files' own initial guess, from data/README.md
GTSAM_CHI2 = {"input_M3500_g2o": 137.91, "input_MITb_g2o": 770.24}


# --------------------------------------------------------------------------- unwrapping on one loop

#: four relative rotations near ±π: one full turn around the loop (they sum to 2π + 0.017 rad)
LOOP_ROTATIONS = np.array([3.10, 3.12, 3.13, -3.05])
LOOP_WEIGHTS = np.array([100.0, 400.0, 50.0, 200.0])


def expected_loop_headings(rotations: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Least squares on one cycle, by hand: the loop's closing error (wrapped to (-π, π]) is
    spread over the edges in proportion to their variance 1/w."""
    closing_error = float(wrap_angle(np.sum(rotations)))
    corrected = rotations - closing_error * (1.0 / weights) / np.sum(1.0 / weights)
    return np.concatenate(([0.0], np.cumsum(corrected)[:-1]))


def test_headings_on_a_loop_of_four_edges_near_pi() -> None:
    edge_i = np.array([0, 1, 2, 3])
    edge_j = np.array([1, 2, 3, 0])
    poses = np.zeros((4, 3))
    headings, turns = estimate_headings(4, edge_i, edge_j, LOOP_ROTATIONS, LOOP_WEIGHTS, [0], poses)
    expected = expected_loop_headings(LOOP_ROTATIONS, LOOP_WEIGHTS)
    np.testing.assert_allclose(wrap_angle(headings - expected), 0.0, atol=1e-12)
    # the one chord of the tree is moved by whole turns so that the loop sums to a multiple of 2π
    assert np.count_nonzero(turns) == 1
    assert abs(np.sum(LOOP_ROTATIONS + 2 * np.pi * turns)) < 0.1
    # each edge's wrapped residual is its share of the 0.017 rad closing error, not ~2π
    residuals = wrap_angle(headings[edge_j] - headings[edge_i] - LOOP_ROTATIONS)
    np.testing.assert_allclose(np.sum(residuals), -float(wrap_angle(np.sum(LOOP_ROTATIONS))), atol=1e-12)
    assert np.max(np.abs(residuals)) < 0.017


def test_loop_unwrapping_does_not_depend_on_edge_direction_or_anchor_heading() -> None:
    # reverse edges 1 and 3 (their measurements flip sign) and start the anchor at 2.5 rad
    edge_i = np.array([0, 2, 2, 0])
    edge_j = np.array([1, 1, 3, 3])
    rotations = LOOP_ROTATIONS * np.array([1, -1, 1, -1])
    poses = np.array([[0.0, 0.0, 2.5], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    headings, _ = estimate_headings(4, edge_i, edge_j, rotations, LOOP_WEIGHTS, [0], poses)
    expected = 2.5 + expected_loop_headings(LOOP_ROTATIONS, LOOP_WEIGHTS)
    assert headings[0] == 2.5
    np.testing.assert_allclose(wrap_angle(headings - expected), 0.0, atol=1e-12)


def test_initialize_orientations_on_a_square_with_headings_near_pi() -> None:
    # ground truth: a 1 m square driven once around, so the headings turn by 2π along the loop and
    # start near -π; the guess has every position at the origin and every heading wrong
    truth = np.array([[0.0, 0.0, -3.1], [1.0, 0.0, -1.5], [1.0, 1.0, 0.05], [0.0, 1.0, 1.6]])
    graph = PoseGraph()
    graph.add_vertices(np.column_stack((np.zeros((4, 2)), [-3.1, 2.0, -2.5, -0.4])))
    edge_i = np.array([0, 1, 2, 3])
    edge_j = np.array([1, 2, 3, 0])
    graph.add_edges(edge_i, edge_j, relative_pose(truth[edge_i], truth[edge_j]), np.tile(np.eye(3), (4, 1, 1)))
    graph.vertices[0] = truth[0]
    assert np.sum(graph.edge_arrays[2][:, 2]) == pytest.approx(2 * np.pi)
    result = graph.initialize_orientations()
    assert result.chi2_after < 1e-20 < result.chi2_before
    assert result.wrapped_edges == 1
    np.testing.assert_allclose(graph.vertices[:, :2], truth[:, :2], atol=1e-12)
    np.testing.assert_allclose(wrap_angle(graph.vertices[:, 2] - truth[:, 2]), 0.0, atol=1e-12)
    assert np.all((graph.vertices[:, 2] >= -np.pi) & (graph.vertices[:, 2] < np.pi))


def test_rotation_information_is_the_marginal_of_the_rotation() -> None:
    rng = np.random.default_rng(2)
    roots = rng.normal(size=(20, 3, 3))
    information = roots @ roots.transpose(0, 2, 1) + 0.1 * np.eye(3)
    information[:5, :2, 2] = information[:5, 2, :2] = 0.0  # block diagonal: just Ω_θθ
    weights = rotation_information(information)
    np.testing.assert_allclose(weights, 1.0 / np.linalg.inv(information)[:, 2, 2], rtol=1e-9)
    np.testing.assert_array_equal(weights[:5], information[:5, 2, 2])
    # translation only, or a rank-one Ω mixing translation and rotation: nothing about the heading alone
    v = np.array([1.0, 2.0, 3.0])
    assert rotation_information(np.array([np.diag([1.0, 1.0, 0.0]), np.outer(v, v)])).tolist() == [0.0, 0.0]


# --------------------------------------------------------------------------- poor initial guesses


def lap_graph(seed: int) -> tuple[PoseGraph, np.ndarray]:
    """Noisy odometry along three laps plus loop closures between laps; vertices start at the truth."""
    rng = np.random.default_rng(seed)
    truth = lap_trajectory()
    count = len(truth)
    per_lap = (count - 1) // 3
    odometry_i = np.arange(count - 1)
    loop_i = np.arange(0, count - per_lap, 3)
    edge_i = np.concatenate((odometry_i, loop_i))
    edge_j = np.concatenate((odometry_i + 1, loop_i + per_lap))
    sigma = np.concatenate(
        (np.tile([0.03, 0.03, 0.02], (len(odometry_i), 1)), np.tile([0.01, 0.01, 0.005], (len(loop_i), 1)))
    )
    measurements = compose(relative_pose(truth[edge_i], truth[edge_j]), rng.normal(0.0, 1.0, sigma.shape) * sigma)
    graph = PoseGraph()
    graph.add_vertices(truth)
    graph.add_edges(edge_i, edge_j, measurements, np.eye(3) / sigma[:, None, :] ** 2)
    return graph, truth


def scrambled(truth: np.ndarray, seed: int) -> np.ndarray:
    """The poorest guess: every position at the origin, every heading uniform; the first pose kept."""
    rng = np.random.default_rng(seed)
    poses = np.zeros_like(truth)
    poses[:, 2] = rng.uniform(-np.pi, np.pi, len(truth))
    poses[0] = truth[0]
    return poses


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_initialized_lm_reaches_the_optimum_where_plain_lm_stalls(seed: int) -> None:
    graph, truth = lap_graph(seed)
    reference = graph.optimize()  # from the ground truth: the optimum this graph should reach
    optimum = graph.vertices.copy()
    assert reference.converged and reference.chi2_after < 150.0
    poor = scrambled(truth, 100 + seed)

    graph.vertices = poor
    plain = graph.optimize()
    graph.vertices = poor
    initialized = graph.optimize(initialize="orientations")

    assert initialized.converged and initialized.initialize == "orientations"
    assert initialized.chi2_after == pytest.approx(reference.chi2_after, rel=1e-6)
    np.testing.assert_allclose(graph.vertices[:, :2], optimum[:, :2], atol=1e-5)
    np.testing.assert_allclose(wrap_angle(graph.vertices[:, 2] - optimum[:, 2]), 0.0, atol=1e-5)
    # the linear initialization alone lands in the optimum's basin, close to it
    assert initialized.chi2_initialized is not None
    assert initialized.chi2_initialized < 2 * reference.chi2_after < initialized.chi2_before
    assert 0.0 < initialized.initialize_seconds <= initialized.seconds
    # from the same guess plain LM stops in a local minimum three orders of magnitude higher
    assert plain.chi2_after > 1000 * reference.chi2_after


def test_initialize_orientations_alone_then_optimize() -> None:
    graph, truth = lap_graph(0)
    graph.vertices = scrambled(truth, 7)
    first = graph.initialize_orientations()
    assert first.chi2_after < first.chi2_before / 1000
    assert first.wrapped_edges > 0  # the three laps make chords three turns apart along the tree
    np.testing.assert_array_equal(graph.vertices[0], truth[0])
    # the guess is built from the measurements only: the scrambled poses do not matter
    again, _ = lap_graph(0)
    again.vertices = scrambled(truth, 8)
    again.initialize_orientations()
    np.testing.assert_allclose(again.vertices, graph.vertices, atol=1e-12)
    assert graph.optimize().chi2_after < 150.0


def test_initialization_keeps_every_fixed_vertex_and_reaches_the_same_optimum() -> None:
    graph, truth = lap_graph(1)
    graph.optimize(fixed=[0, 20])
    optimum = graph.vertices.copy()
    graph.vertices = scrambled(truth, 3)
    graph.vertices[20] = truth[20]
    start = graph.vertices.copy()
    graph.initialize_orientations(fixed=[0, 20])
    np.testing.assert_array_equal(graph.vertices[[0, 20]], start[[0, 20]])
    graph.optimize(fixed=[0, 20], initialize="orientations")
    np.testing.assert_array_equal(graph.vertices[[0, 20]], start[[0, 20]])
    np.testing.assert_allclose(graph.vertices[:, :2], optimum[:, :2], atol=1e-5)


def test_initialization_with_an_edge_that_measures_no_rotation() -> None:
    # vertex 2 hangs off the chain by a translation-only edge: its heading keeps the guess and
    # its position follows the edge; the rest is solved as usual
    graph = PoseGraph()
    graph.add_vertices([(0.0, 0.0, 0.0), (5.0, 5.0, 2.0), (3.0, -1.0, 0.7)])
    graph.add_edge(0, 1, (1.0, 0.0, np.pi / 2), np.eye(3))
    graph.add_edge(1, 2, (0.0, 2.0, 0.0), np.diag([1.0, 1.0, 0.0]))
    graph.initialize_orientations()
    np.testing.assert_allclose(graph.vertices[1], (1.0, 0.0, np.pi / 2), atol=1e-12)
    np.testing.assert_allclose(graph.vertices[2], (-1.0, 0.0, 0.7), atol=1e-12)
    assert graph.chi2() < 1e-20


def test_initialization_refuses_what_it_cannot_solve() -> None:
    graph = PoseGraph()
    graph.add_vertices([(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (2.0, 0.0, 0.0)])
    graph.add_edge(0, 1, (1.0, 0.0, 0.0))
    with pytest.raises(PoseGraphError, match="not connected to a fixed vertex"):
        graph.initialize_orientations()
    with pytest.raises(PoseGraphError, match="initialize must be"):
        graph.optimize(initialize="lago")  # type: ignore[arg-type]
    graph.add_edge(1, 2, (1.0, 0.0, 0.0), np.diag([1.0, 0.0, 1.0]))  # says nothing about y
    with pytest.raises(PoseGraphError, match="translation information does not determine"):
        graph.initialize_orientations()
    assert PoseGraph().initialize_orientations().chi2_after == 0.0


# --------------------------------------------------------------------------- real graphs


def test_mitb_initialized_beats_the_local_minimum_of_plain_lm() -> None:
    path = POSEGRAPHS / "input_MITb_g2o.g2o"
    if not path.exists():
        pytest.skip(f"{path} not present")
    graph = read_g2o(path)
    result = graph.optimize(initialize="orientations")
    assert result.converged
    # measured on this graph: 41.16, against 770.24 for GTSAM's LM from the file's guess
    assert result.chi2_after < GTSAM_CHI2["input_MITb_g2o"] / 10
    assert graph.chi2() == pytest.approx(result.chi2_after, rel=1e-12)


def test_m3500_initialized_reaches_the_gtsam_optimum() -> None:
    path = POSEGRAPHS / "input_M3500_g2o.g2o"
    if not path.exists():
        pytest.skip(f"{path} not present")
    graph = read_g2o(path)
    graph.vertices = scrambled(graph.vertices, 0)
    result = graph.optimize(initialize="orientations")
    assert result.converged
    assert result.chi2_after == pytest.approx(GTSAM_CHI2["input_M3500_g2o"], rel=1e-3)


# --------------------------------------------------------------------------- CLI


def test_cli_init_orientations(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    graph, truth = lap_graph(0)
    graph.vertices = scrambled(truth, 100)
    source = tmp_path / "scrambled.g2o"
    write_g2o(graph, source)
    reports = {}
    for init in ("none", "orientations"):
        out = tmp_path / f"{init}.g2o"
        assert run_cli(["posegraph", "optimize", str(source), "--init", init, "--out", str(out)]) == 0
        reports[init] = json.loads(capsys.readouterr().out)
        assert read_g2o(out).chi2() == pytest.approx(reports[init]["chi2_final"], rel=1e-9)
    assert reports["none"]["initialize"] == "none" and reports["none"]["chi2_initialized"] is None
    assert reports["orientations"]["initialize"] == "orientations"
    assert reports["orientations"]["chi2_initial"] == pytest.approx(reports["none"]["chi2_initial"], rel=1e-12)
    assert reports["orientations"]["chi2_initialized"] < reports["orientations"]["chi2_initial"] / 1000
    assert reports["orientations"]["chi2_final"] < reports["none"]["chi2_final"] / 1000

    assert run_cli(["posegraph", "optimize", str(source), "--init", "orientations", "--text"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[1].startswith("init orientations: chi2 ") and lines[2].startswith("lm: chi2 ")
    with pytest.raises(SystemExit):
        run_cli(["posegraph", "optimize", str(source), "--init", "lago"])
    capsys.readouterr()


def test_cli_default_is_no_initialization(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    graph, _ = lap_graph(0)
    source = tmp_path / "laps.g2o"
    write_g2o(graph, source)
    assert run_cli(["posegraph", "optimize", str(source)]) == 0
    assert json.loads(capsys.readouterr().out)["initialize"] == "none"
