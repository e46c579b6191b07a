"""Pose graph: SE(2) helpers, chi2 by hand, Jacobians by finite differences, optimization
against ground truth, the two real graphs against GTSAM's chi2, and the CLI."""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from mazebot.errors import EXIT_OK, EXIT_USAGE
from mazebot.slam import posegraph_cli
from mazebot.slam.g2o import G2oFormatError, read_g2o, write_g2o
from mazebot.slam.posegraph import (
    PoseGraph,
    PoseGraphError,
    compose,
    edge_jacobians,
    edge_residuals,
    inverse,
    relative_pose,
    wrap_angle,
)
from tests.data_paths import POSEGRAPHS

#: GTSAM 4.3 Levenberg-Marquardt results on this machine, from data/README.md
GTSAM_CHI2 = {"input_M3500_g2o": 137.91, "input_MITb_g2o": 770.24}


def v2t(pose: np.ndarray) -> np.ndarray:
    """Homogeneous 3x3 matrix of (x, y, theta): the reference the vector helpers must match."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.array([[c, -s, pose[0]], [s, c, pose[1]], [0.0, 0.0, 1.0]])


def t2v(matrix: np.ndarray) -> np.ndarray:
    return np.array([matrix[0, 2], matrix[1, 2], math.atan2(matrix[1, 0], matrix[0, 0])])


# --------------------------------------------------------------------------- SE(2) helpers


def test_wrap_angle_range_and_identity() -> None:
    angles = np.linspace(-20.0, 20.0, 4001)
    wrapped = wrap_angle(angles)
    assert np.all(wrapped >= -np.pi) and np.all(wrapped < np.pi)
    np.testing.assert_allclose(np.sin(wrapped), np.sin(angles), atol=1e-12)
    np.testing.assert_allclose(np.cos(wrapped), np.cos(angles), atol=1e-12)
    assert wrap_angle(np.pi) == pytest.approx(-np.pi)
    assert wrap_angle(0.25) == 0.25


def test_compose_relative_inverse_match_homogeneous_matrices() -> None:
    rng = np.random.default_rng(4)
    a = rng.uniform(-5, 5, size=(50, 3))
    b = rng.uniform(-5, 5, size=(50, 3))
    for k in range(50):
        np.testing.assert_allclose(compose(a[k], b[k]), t2v(v2t(a[k]) @ v2t(b[k])), atol=1e-12)
        np.testing.assert_allclose(relative_pose(a[k], b[k]), t2v(np.linalg.inv(v2t(a[k])) @ v2t(b[k])), atol=1e-12)
        np.testing.assert_allclose(inverse(a[k]), t2v(np.linalg.inv(v2t(a[k]))), atol=1e-12)
    # vectorized over rows, and broadcasting one pose against many
    np.testing.assert_allclose(relative_pose(a, compose(a, b)), wrap_angle(b) * [0, 0, 1] + b * [1, 1, 0], atol=1e-9)
    assert compose(a[0], b).shape == (50, 3)


# --------------------------------------------------------------------------- chi2 by hand


def three_pose_graph() -> PoseGraph:
    graph = PoseGraph()
    graph.add_vertex((0.0, 0.0, 0.0))
    graph.add_vertex((1.0, 0.0, np.pi / 2))
    graph.add_vertex((1.0, 1.0, np.pi))
    graph.add_edge(0, 1, (1.1, 0.0, 1.5), np.diag([1.0, 2.0, 3.0]))
    graph.add_edge(1, 2, (1.0, 0.1, np.pi / 2), np.array([[2.0, 0.5, 0.0], [0.5, 1.0, 0.0], [0.0, 0.0, 4.0]]))
    graph.add_edge(2, 0, (1.0, 1.0, np.pi - 0.1), np.diag([5.0, 5.0, 7.0]))
    return graph


def test_chi2_of_three_poses_matches_hand_computed_residuals() -> None:
    graph = three_pose_graph()
    # edge 0->1: X0⁻¹X1 = (1, 0, π/2); Z⁻¹ of that: R(-1.5)·(1 - 1.1, 0) and π/2 - 1.5
    e01 = np.array([-0.1 * math.cos(1.5), 0.1 * math.sin(1.5), math.pi / 2 - 1.5])
    # edge 1->2: X1⁻¹X2 = (1, 0, π/2) exactly the measurement's angle; R(-π/2)·(0, -0.1) = (-0.1, 0)
    e12 = np.array([-0.1, 0.0, 0.0])
    # edge 2->0: X2⁻¹X0 = (1, 1, -π); the angle error -π - (π - 0.1) wraps to +0.1
    e20 = np.array([0.0, 0.0, 0.1])
    np.testing.assert_allclose(graph.residuals(), [e01, e12, e20], atol=1e-12)
    by_hand = (
        1.0 * e01[0] ** 2
        + 2.0 * e01[1] ** 2
        + 3.0 * e01[2] ** 2  # Ω diagonal
        + 2.0 * 0.01  # 2·(-0.1)²; the 0.5 off-diagonal multiplies e_y = 0
        + 7.0 * 0.01
    )
    assert graph.chi2() == pytest.approx(by_hand, rel=1e-12)


def test_chi2_uses_the_off_diagonal_information() -> None:
    graph = PoseGraph()
    graph.add_vertex((0.0, 0.0, 0.0))
    graph.add_vertex((1.2, 0.3, 0.0))
    omega = np.array([[2.0, 0.5, 0.1], [0.5, 1.0, 0.0], [0.1, 0.0, 4.0]])
    graph.add_edge(0, 1, (1.0, 0.0, 0.0), omega)
    e = np.array([0.2, 0.3, 0.0])
    assert graph.chi2() == pytest.approx(2 * 0.04 + 2 * 0.5 * 0.06 + 1.0 * 0.09, rel=1e-12)
    assert graph.chi2() == pytest.approx(e @ omega @ e, rel=1e-12)


# --------------------------------------------------------------------------- Jacobians


def test_jacobians_match_central_finite_differences() -> None:
    rng = np.random.default_rng(11)
    count = 40
    vertices = np.column_stack((rng.uniform(-10, 10, (2 * count, 2)), rng.uniform(-np.pi, np.pi, 2 * count)))
    edge_i = np.arange(count)
    edge_j = np.arange(count, 2 * count)
    # measurements near the truth (small residuals) and far from it (large ones, angles near ±π)
    truth = relative_pose(vertices[edge_i], vertices[edge_j])
    measurements = compose(truth, rng.normal(0, 1.0, (count, 3)) * (0.5, 0.5, 0.3))
    measurements[::2] = compose(truth[::2], rng.uniform(-3, 3, (count // 2, 3)) * (1, 1, 0.9))
    _, a, b = edge_jacobians(vertices, edge_i, edge_j, measurements)
    step = 1e-6
    for which, jacobian in (("i", a), ("j", b)):
        for k in range(3):
            delta = np.zeros(3)
            delta[k] = step
            plus = vertices.copy()
            minus = vertices.copy()
            idx = edge_i if which == "i" else edge_j
            plus[idx] = compose(vertices[idx], delta)
            minus[idx] = compose(vertices[idx], -delta)
            e_plus = edge_residuals(plus, edge_i, edge_j, measurements)
            e_minus = edge_residuals(minus, edge_i, edge_j, measurements)
            numeric = (e_plus - e_minus) / (2 * step)
            numeric[:, 2] = wrap_angle(e_plus[:, 2] - e_minus[:, 2]) / (2 * step)
            np.testing.assert_allclose(numeric, jacobian[:, :, k], atol=2e-7, err_msg=f"de/dx_{which}[{k}]")


# --------------------------------------------------------------------------- optimization


def lap_trajectory(laps: int = 3, width_m: float = 4.0, height_m: float = 3.0, step_m: float = 0.5) -> np.ndarray:
    """Ground-truth poses driving ``laps`` times around a rectangle, turning 90° at corners."""
    poses = []
    x, y, theta = 0.0, 0.0, 0.0
    sides = [width_m, height_m, width_m, height_m]
    for _ in range(laps):
        for side in sides:
            for _ in range(round(side / step_m)):
                poses.append((x, y, theta))
                x += step_m * math.cos(theta)
                y += step_m * math.sin(theta)
            theta = float(wrap_angle(theta + math.pi / 2))
    poses.append((x, y, theta))
    return np.array(poses)


def noisy_lap_graph(seed: int = 0) -> tuple[PoseGraph, np.ndarray]:
    """Noisy odometry chain (dead-reckoned initial guess) + loop closures between laps."""
    rng = np.random.default_rng(seed)
    truth = lap_trajectory()
    odo_sigma = np.array([0.03, 0.03, 0.02])  # m, m, rad per 0.5 m step
    loop_sigma = np.array([0.01, 0.01, 0.005])
    graph = PoseGraph()
    graph.add_vertex(truth[0])
    count = len(truth)
    for k in range(1, count):
        z = compose(relative_pose(truth[k - 1], truth[k]), rng.normal(0.0, odo_sigma))
        graph.add_vertex(compose(graph.vertices[k - 1], z))
        graph.add_edge(k - 1, k, z, np.diag(1.0 / odo_sigma**2))
    per_lap = (count - 1) // 3
    for k in range(0, count - per_lap, 3):  # the same place on consecutive laps
        z = compose(relative_pose(truth[k], truth[k + per_lap]), rng.normal(0.0, loop_sigma))
        graph.add_edge(k, k + per_lap, z, np.diag(1.0 / loop_sigma**2))
    for k in range(6, per_lap, 6):  # places matched against the scan taken at the start pose
        z = compose(relative_pose(truth[0], truth[k]), rng.normal(0.0, 2 * loop_sigma))
        graph.add_edge(0, k, z, np.diag(1.0 / (2 * loop_sigma) ** 2))
    return graph, truth


def position_rms_m(poses: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((poses[:, :2] - truth[:, :2]) ** 2, axis=1))))


@pytest.mark.parametrize("method", ["lm", "gn"])
def test_optimization_recovers_ground_truth(method: str) -> None:
    graph, truth = noisy_lap_graph()
    before_m = position_rms_m(graph.vertices, truth)
    result = graph.optimize(method=method)
    after_m = position_rms_m(graph.vertices, truth)
    heading_rms = float(np.sqrt(np.mean(wrap_angle(graph.vertices[:, 2] - truth[:, 2]) ** 2)))
    assert result.converged
    assert result.chi2_after < result.chi2_before / 100
    assert before_m > 0.3, "the dead-reckoned start should be visibly wrong"
    assert after_m < 0.06  # about the loop-closure noise: the drift is gone
    assert after_m < before_m / 5
    assert heading_rms < 0.03
    np.testing.assert_array_equal(graph.vertices[0], truth[0])  # the first pose is held fixed
    # chi2 of a correct model at its optimum is about (#residuals - #unknowns)
    dof = 3 * graph.edge_count - 3 * (len(graph) - 1)
    assert 0.5 * dof < result.chi2_after < 1.5 * dof


def test_optimum_has_zero_gradient() -> None:
    graph, _ = noisy_lap_graph(seed=3)
    graph.optimize(relative_tolerance=1e-12)
    x = graph.vertices.copy()
    step = 1e-6
    chi2_0 = graph.chi2()
    for vertex in (5, 40, len(graph) - 1):
        for k in range(3):
            delta = np.zeros(3)
            delta[k] = step
            values = []
            for sign in (1, -1):
                moved = x.copy()
                moved[vertex] = compose(x[vertex], sign * delta)
                graph.vertices = moved
                values.append(graph.chi2())
            gradient = (values[0] - values[1]) / (2 * step)
            assert abs(gradient) < 1e-3 * max(1.0, chi2_0)
    graph.vertices = x


def test_fixed_vertices_do_not_move() -> None:
    graph, _ = noisy_lap_graph()
    start = graph.vertices.copy()
    graph.optimize(fixed=[0, 30])
    np.testing.assert_array_equal(graph.vertices[[0, 30]], start[[0, 30]])
    graph2, _ = noisy_lap_graph()
    graph2.fixed.add(12)
    graph2.optimize()
    np.testing.assert_array_equal(graph2.vertices[12], start[12])
    assert not np.array_equal(graph2.vertices[0], start[0])


def test_already_optimal_graph_stops_at_once() -> None:
    graph = PoseGraph()
    graph.add_vertex((0.0, 0.0, 0.0))
    graph.add_vertex((1.0, 0.0, 0.0))
    graph.add_edge(0, 1, (1.0, 0.0, 0.0))
    result = graph.optimize()
    assert (result.iterations, result.chi2_after, result.converged) == (0, 0.0, True)
    assert PoseGraph().optimize().converged


def test_two_poses_one_edge_is_solved_exactly() -> None:
    graph = PoseGraph()
    graph.add_vertex((1.0, 2.0, 0.5))
    graph.add_vertex((0.0, 0.0, 3.0))
    graph.add_edge(0, 1, (1.0, -0.5, 2.5), np.diag([10.0, 10.0, 100.0]))
    result = graph.optimize(method="gn")
    assert result.converged and result.chi2_after < 1e-20
    np.testing.assert_allclose(graph.vertices[1], compose((1.0, 2.0, 0.5), (1.0, -0.5, 2.5)), atol=1e-10)


def test_unanchored_part_is_refused() -> None:
    graph = PoseGraph()
    for x in range(4):
        graph.add_vertex((float(x), 0.0, 0.0), vertex_id=10 + x)
    graph.add_edge(0, 1, (1.0, 0.0, 0.0))
    graph.add_edge(2, 3, (1.0, 0.0, 0.0))
    with pytest.raises(PoseGraphError, match=r"2 vertices \(e\.g\. id 12\) are not connected to a fixed vertex"):
        graph.optimize()
    graph.optimize(fixed=[0, 2])  # anchoring each part makes it solvable


@pytest.mark.parametrize(
    ("call", "words"),
    [
        (lambda g: g.add_edge(0, 5, (1, 0, 0)), "outside 0..1"),
        (lambda g: g.add_edge(1, 1, (1, 0, 0)), "joins a vertex to itself"),
        (lambda g: g.add_edge(0, 1, (1, 0)), "add_edges needs"),
        (lambda g: g.add_edge(0, 1, (1, 0, np.nan)), "finite"),
        (lambda g: g.add_edge(0, 1, (1, 0, 0), -np.eye(3)), "positive semi-definite"),
        (lambda g: g.add_edge(0, 1, (1, 0, 0), [[1, 2, 0], [0, 1, 0], [0, 0, 1]]), "symmetric"),
        (lambda g: g.add_vertex((0, 0, 0), vertex_id=1), "vertex id 1 is already in the graph"),
        (lambda g: g.add_vertex((0, 0)), "3 finite numbers"),
        (lambda g: g.optimize(method="newton"), "method must be"),
        (lambda g: g.optimize(fixed=[9]), "fixed vertex index 9"),
        (lambda g: g.index_of(77), "no vertex with id 77"),
    ],
)
def test_bad_input_raises_one_line_usage_error(call: Callable[[PoseGraph], object], words: str) -> None:
    graph = PoseGraph()
    graph.add_vertex((0.0, 0.0, 0.0))
    graph.add_vertex((1.0, 0.0, 0.0))
    with pytest.raises(PoseGraphError) as caught:
        call(graph)
    assert words in str(caught.value)
    assert caught.value.exit_code == EXIT_USAGE


def test_edges_and_vertices_views() -> None:
    graph = three_pose_graph()
    edges = graph.edges
    assert [(e.i, e.j) for e in edges] == [(0, 1), (1, 2), (2, 0)]
    np.testing.assert_array_equal(edges[1].information[0], [2.0, 0.5, 0.0])
    for k in range(40):  # growing past the initial buffer keeps earlier poses
        graph.add_vertex((k, -k, 0.0))
    assert len(graph) == 43 and graph.vertices.shape == (43, 3)
    np.testing.assert_array_equal(graph.vertices[2], (1.0, 1.0, np.pi))


# --------------------------------------------------------------------------- real graphs


@pytest.mark.parametrize(
    ("name", "method"),
    [("input_M3500_g2o", "lm"), ("input_M3500_g2o", "gn"), ("input_MITb_g2o", "lm"), ("input_MITb_g2o", "gn")],
)
def test_real_graph_reaches_gtsam_chi2(name: str, method: str) -> None:
    path = POSEGRAPHS / f"{name}.g2o"
    if not path.exists():
        pytest.skip(f"{path} not present")
    graph = read_g2o(path)
    result = graph.optimize(method=method)
    assert result.converged
    assert result.chi2_after == pytest.approx(GTSAM_CHI2[name], rel=0.01)
    assert graph.chi2() == pytest.approx(result.chi2_after, rel=1e-12)


# --------------------------------------------------------------------------- CLI


def run_cli(argv: list[str]) -> int:
    """``mazebot posegraph ...`` without the command line's error handling: a failure raises."""
    parser = argparse.ArgumentParser(prog="mazebot")
    posegraph_cli.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_optimize_prints_json_and_writes_the_graph(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    graph, _ = noisy_lap_graph()
    source = tmp_path / "laps.g2o"
    write_g2o(graph, source)
    out = tmp_path / "laps_opt.g2o"
    assert run_cli(["posegraph", "optimize", str(source), "--out", str(out), "--json", "--method", "gn"]) == EXIT_OK
    report = json.loads(capsys.readouterr().out)
    assert report["poses"] == len(graph) and report["edges"] == graph.edge_count
    assert report["method"] == "gn" and report["converged"] is True
    assert report["chi2_final"] < report["chi2_initial"]
    assert {"iterations", "seconds", "linear_solves", "fixed", "output"} <= report.keys()
    assert read_g2o(out).chi2() == pytest.approx(report["chi2_final"], rel=1e-9)


def test_cli_prints_one_json_line_by_default(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    source = tmp_path / "three.g2o"
    write_g2o(three_pose_graph(), source)
    assert run_cli(["posegraph", "optimize", str(source)]) == EXIT_OK
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 1
    assert {"poses", "edges", "chi2_initial", "chi2_final", "iterations", "seconds"} <= json.loads(lines[0]).keys()


def test_cli_text_output(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    source = tmp_path / "three.g2o"
    write_g2o(three_pose_graph(), source)
    assert run_cli(["posegraph", "optimize", str(source), "--iterations", "5", "--text"]) == EXIT_OK
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"{source}: 3 poses, 3 edges, fixed [0]"
    assert lines[1].startswith("lm: chi2 ") and " iterations " in lines[1]


def test_cli_bad_file_raises_the_format_error(tmp_path: Path) -> None:
    source = tmp_path / "bad.g2o"
    source.write_text("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1\n")
    with pytest.raises(G2oFormatError, match=r"bad\.g2o:2: "):
        run_cli(["posegraph", "optimize", str(source)])
