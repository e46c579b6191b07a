"""g2o 2D files: exact round trips, one-line errors that name the line, atomic writes."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

import mazebot.slam.g2o as g2o
from mazebot.errors import EXIT_USAGE, MazebotError, UsageError
from mazebot.slam.g2o import G2oFormatError, parse_g2o, read_g2o, write_g2o
from mazebot.slam.posegraph import PoseGraph
from tests.data_paths import POSEGRAPHS

MITB = POSEGRAPHS / "input_MITb_g2o.g2o"


def random_graph(seed: int = 1) -> PoseGraph:
    """Non-contiguous ids, a FIX, full (correlated) information matrices, awkward floats."""
    rng = np.random.default_rng(seed)
    graph = PoseGraph()
    ids = [7, 3, 100, 42, 5]
    for vertex_id in ids:
        graph.add_vertex(rng.normal(size=3) * (10.0, 10.0, 1.0), vertex_id)
    for i, j in [(0, 1), (1, 2), (2, 3), (3, 4), (4, 0), (0, 2)]:
        root = rng.normal(size=(3, 3))
        graph.add_edge(i, j, rng.normal(size=3) / 3.0, root @ root.T + 0.1 * np.eye(3))
    graph.fixed.add(1)
    return graph


def assert_same_graph(a: PoseGraph, b: PoseGraph) -> None:
    assert a.vertex_ids == b.vertex_ids
    assert a.fixed == b.fixed
    np.testing.assert_array_equal(a.vertices, b.vertices)
    for left, right in zip(a.edge_arrays, b.edge_arrays, strict=True):
        np.testing.assert_array_equal(left, right)


def test_round_trip_is_bit_exact(tmp_path: Path) -> None:
    graph = random_graph()
    path = tmp_path / "graph.g2o"
    write_g2o(graph, path)
    back = read_g2o(path)
    assert_same_graph(graph, back)
    # and writing what was read gives the same bytes
    again = tmp_path / "again.g2o"
    write_g2o(back, again)
    assert again.read_bytes() == path.read_bytes()


def test_written_file_is_plain_g2o(tmp_path: Path) -> None:
    graph = PoseGraph()
    graph.add_vertex((0.0, 0.0, 0.0), 10)
    graph.add_vertex((1.0, 0.5, 0.25), 11)
    graph.add_edge(0, 1, (1.0, 0.5, 0.25), np.array([[1.0, 0.5, 0.0], [0.5, 2.0, 0.0], [0.0, 0.0, 3.0]]))
    graph.fixed.add(0)
    path = tmp_path / "small.g2o"
    write_g2o(graph, path)
    assert path.read_text().splitlines() == [
        "VERTEX_SE2 10 0.0 0.0 0.0",
        "VERTEX_SE2 11 1.0 0.5 0.25",
        "FIX 10",
        "EDGE_SE2 10 11 1.0 0.5 0.25 1.0 0.5 0.0 2.0 0.0 3.0",
    ]


@pytest.mark.skipif(not MITB.exists(), reason="shared data not present")
def test_real_file_round_trip(tmp_path: Path) -> None:
    graph = read_g2o(MITB)
    assert (len(graph), graph.edge_count) == (808, 827)
    out = tmp_path / "mit.g2o"
    write_g2o(graph, out)
    assert_same_graph(graph, read_g2o(out))


def test_upper_triangle_becomes_symmetric_information() -> None:
    graph = parse_g2o(
        [
            "# a comment, then a blank line",
            "",
            "VERTEX_SE2 0 0 0 0",
            "VERTEX_SE2 1 1 0 0",
            "EDGE_SE2 0 1 1 0 0 11 12 13 22 23 33.5",
        ]
    )
    info = graph.edge_arrays[3][0]
    np.testing.assert_array_equal(info, [[11, 12, 13], [12, 22, 23], [13, 23, 33.5]])


def test_edges_may_come_before_their_vertices_and_fix_is_kept() -> None:
    graph = parse_g2o(["EDGE_SE2 5 9 1 0 0 1 0 0 1 0 1", "FIX 9", "VERTEX_SE2 9 1 0 0", "VERTEX_SE2 5 0 0 0"])
    assert graph.vertex_ids == [9, 5]
    assert graph.fixed == {0}
    assert graph.edge_arrays[0].tolist() == [1] and graph.edge_arrays[1].tolist() == [0]


GOOD = ["VERTEX_SE2 0 0 0 0", "VERTEX_SE2 1 1 0 0"]


@pytest.mark.parametrize(
    ("bad_line", "words"),
    [
        ("VERTEX_SE3:QUAT 2 0 0 0 0 0 0 1", "unsupported record 'VERTEX_SE3:QUAT'"),
        ("VERTEX_SE2 2 0 0", "needs 3 numbers"),
        ("VERTEX_SE2 2 0 zero 0", "'zero' is not a number"),
        ("VERTEX_SE2 two 0 0 0", "vertex id 'two' is not an integer"),
        ("VERTEX_SE2 1 5 5 5", "vertex id 1 is already defined on line 2"),
        ("VERTEX_SE2 2 nan 0 0", "must be finite"),
        ("VERTEX_SE2", "needs an id"),
        ("EDGE_SE2 0 1 1 0 0 1 0 0 1 0", "needs 9 numbers after its ids"),
        ("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1 7", "found 10"),
        ("EDGE_SE2 0 7 1 0 0 1 0 0 1 0 1", "vertex 7, which no VERTEX_SE2 defines"),
        ("EDGE_SE2 1 1 1 0 0 1 0 0 1 0 1", "joins vertex 1 to itself"),
        ("EDGE_SE2 0 1 1 0 0 1 0 0 -1 0 1", "not positive semi-definite"),
        ("EDGE_SE2 0", "needs 2 vertex ids"),
        ("FIX 12", "FIX names vertex 12"),
        ("FIX", "FIX needs at least one vertex id"),
    ],
)
def test_malformed_line_names_file_and_line(tmp_path: Path, bad_line: str, words: str) -> None:
    path = tmp_path / "bad.g2o"
    path.write_text("\n".join([*GOOD, bad_line, "VERTEX_SE2 3 0 0 0"]) + "\n")
    with pytest.raises(G2oFormatError) as caught:
        read_g2o(path)
    message = str(caught.value)
    assert message.startswith(f"{path}:3: "), message
    assert words in message
    assert "\n" not in message
    assert caught.value.line_number == 3
    assert isinstance(caught.value, MazebotError) and caught.value.exit_code == EXIT_USAGE


def test_unreadable_inputs_are_usage_errors(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="cannot read g2o file"):
        read_g2o(tmp_path / "missing.g2o")
    binary = tmp_path / "binary.g2o"
    binary.write_bytes(b"\xff\xfe\x00VERTEX")
    with pytest.raises(UsageError, match="not a g2o text file"):
        read_g2o(binary)


def test_write_into_missing_directory_is_a_usage_error(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="cannot write g2o file"):
        write_g2o(random_graph(), tmp_path / "no" / "such" / "dir" / "out.g2o")


def test_a_failed_write_leaves_the_old_file_and_no_temp_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "graph.g2o"
    path.write_text("VERTEX_SE2 0 0 0 0\n")

    def crash_midway(graph: PoseGraph) -> Iterator[str]:
        yield "VERTEX_SE2 0 1 2 3\n"
        raise RuntimeError("simulated crash while writing")

    monkeypatch.setattr(g2o, "format_g2o", crash_midway)
    with pytest.raises(RuntimeError, match="simulated crash"):
        write_g2o(random_graph(), path)
    assert path.read_text() == "VERTEX_SE2 0 0 0 0\n"
    assert [p.name for p in tmp_path.iterdir()] == ["graph.g2o"]


def test_overwrite_in_place_replaces_the_whole_file(tmp_path: Path) -> None:
    path = tmp_path / "graph.g2o"
    path.write_text("# old content that is much longer than a tiny graph\n" * 100)
    graph = PoseGraph()
    graph.add_vertex((0.0, 0.0, 0.0))
    write_g2o(graph, path)
    assert path.read_text() == "VERTEX_SE2 0 0.0 0.0 0.0\n"
