"""Read and write 2D pose graphs in the g2o text format.

One record per line, fields separated by white space (Kümmerle et al., "g2o: A General
Framework for Graph Optimization", ICRA 2011; the format of the public SLAM datasets)::

    VERTEX_SE2 id x y theta
    EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33
    FIX id

Poses are in metres and radians; the six ``I..`` numbers are the upper triangle of the
edge's 3x3 information matrix, row by row. Empty lines and lines starting with ``#``
are skipped. Other record types (3D, landmarks, parameters) are refused with the line
that holds them, because silently dropping constraints would change the solution.

Writing goes to a temporary file in the target directory, is flushed to disk and then
renamed over the target (``os.replace`` is atomic on POSIX), so a crash leaves either
the old file or the complete new one, never half of it.

Example::

    graph = read_g2o("input_MITb_g2o.g2o")
    graph.optimize()
    write_g2o(graph, "MITb_optimized.g2o")
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from mazebot.errors import UsageError
from mazebot.files import write_atomic
from mazebot.slam.posegraph import PoseGraph, invalid_information

__all__ = ["G2oFormatError", "format_g2o", "parse_g2o", "read_g2o", "write_g2o"]

#: Upper-triangle positions of the six information numbers of ``EDGE_SE2``, row by row.
_UPPER_ROWS = (0, 0, 0, 1, 1, 2)
_UPPER_COLS = (0, 1, 2, 1, 2, 2)


_LAYOUT = {
    "VERTEX_SE2": "VERTEX_SE2 id x y theta",
    "EDGE_SE2": "EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33",
}


class G2oFormatError(UsageError):
    """A g2o file holds a line this reader cannot turn into a vertex, edge or fix."""

    def __init__(self, source: str, line_number: int, problem: str) -> None:
        super().__init__(f"{source}:{line_number}: {problem}")
        self.source = source
        self.line_number = line_number


def _numbers(fields: list[str], count: int, record: str) -> list[float]:
    """``count`` finite floats after a record's ids, or ValueError saying what the record looks like."""
    if len(fields) != count:
        raise ValueError(f"{record} needs {count} numbers after its ids ({_LAYOUT[record]}), found {len(fields)}")
    try:
        values = [float(f) for f in fields]
    except ValueError:
        bad = next(f for f in fields if not _is_float(f))
        raise ValueError(f"{record}: {bad!r} is not a number") from None
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"{record}: numbers must be finite, found {' '.join(fields)}")
    return values


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _integer(text: str, what: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise ValueError(f"{what}: vertex id {text!r} is not an integer") from None


def parse_g2o(lines: Iterable[str], source: str = "<g2o>") -> PoseGraph:
    """Build a ``PoseGraph`` from g2o text lines; ``source`` names the input in errors.

    Edges may name vertices defined later in the file (as g2o allows); vertex ids are
    kept in ``graph.vertex_ids`` and ``FIX`` ids become ``graph.fixed`` indices.
    """
    vertex_ids: list[int] = []
    poses: list[list[float]] = []
    line_of_id: dict[int, int] = {}
    edge_lines: list[int] = []
    edge_ends: list[tuple[int, int]] = []
    edge_values: list[list[float]] = []
    fixes: list[tuple[int, int]] = []  # (line, vertex id)
    for line_number, raw in enumerate(lines, start=1):
        text = raw.strip()
        if not text or text.startswith("#"):
            continue
        tag, *fields = text.split()
        try:
            if tag == "VERTEX_SE2":
                if not fields:
                    raise ValueError("VERTEX_SE2 needs an id and 3 numbers (x y theta)")
                vertex_id = _integer(fields[0], tag)
                pose = _numbers(fields[1:], 3, tag)
                if vertex_id in line_of_id:
                    raise ValueError(f"vertex id {vertex_id} is already defined on line {line_of_id[vertex_id]}")
                line_of_id[vertex_id] = line_number
                vertex_ids.append(vertex_id)
                poses.append(pose)
            elif tag == "EDGE_SE2":
                if len(fields) < 2:
                    raise ValueError("EDGE_SE2 needs 2 vertex ids, 3 measurement and 6 information numbers")
                ends = (_integer(fields[0], tag), _integer(fields[1], tag))
                if ends[0] == ends[1]:
                    raise ValueError(f"EDGE_SE2 joins vertex {ends[0]} to itself")
                edge_values.append(_numbers(fields[2:], 9, tag))
                edge_ends.append(ends)
                edge_lines.append(line_number)
            elif tag == "FIX":
                if not fields:
                    raise ValueError("FIX needs at least one vertex id")
                fixes.extend((line_number, _integer(f, tag)) for f in fields)
            else:
                raise ValueError(f"unsupported record {tag!r}; expected VERTEX_SE2, EDGE_SE2 or FIX")
        except ValueError as exc:
            raise G2oFormatError(source, line_number, str(exc)) from None

    for line_number, (id_i, id_j) in zip(edge_lines, edge_ends, strict=True):
        for vertex_id in (id_i, id_j):
            if vertex_id not in line_of_id:
                raise G2oFormatError(
                    source, line_number, f"EDGE_SE2 names vertex {vertex_id}, which no VERTEX_SE2 defines"
                )
    for line_number, vertex_id in fixes:
        if vertex_id not in line_of_id:
            raise G2oFormatError(source, line_number, f"FIX names vertex {vertex_id}, which no VERTEX_SE2 defines")

    values = np.array(edge_values, dtype=np.float64).reshape(-1, 9)
    information = np.zeros((len(values), 3, 3))
    information[:, _UPPER_ROWS, _UPPER_COLS] = values[:, 3:]
    information[:, _UPPER_COLS, _UPPER_ROWS] = values[:, 3:]
    bad = invalid_information(information)
    if bad.any():
        line_number = edge_lines[int(np.argmax(bad))]
        raise G2oFormatError(source, line_number, "EDGE_SE2 information matrix is not positive semi-definite")

    graph = PoseGraph()
    graph.add_vertices(np.array(poses, dtype=np.float64).reshape(-1, 3), vertex_ids)
    index_of_id = {vertex_id: index for index, vertex_id in enumerate(vertex_ids)}
    end_rows = np.array([(index_of_id[a], index_of_id[b]) for a, b in edge_ends], dtype=np.intp).reshape(-1, 2)
    graph.add_edges(end_rows[:, 0], end_rows[:, 1], values[:, :3], information)
    graph.fixed.update(index_of_id[vertex_id] for _, vertex_id in fixes)
    return graph


def read_g2o(path: str | os.PathLike[str]) -> PoseGraph:
    """Read a g2o 2D file into a ``PoseGraph``; bad lines raise ``G2oFormatError`` naming file and line."""
    path = Path(path)
    try:
        with path.open(encoding="utf-8") as stream:
            return parse_g2o(stream, source=str(path))
    except UnicodeDecodeError as exc:
        raise UsageError(f"{path}: not a g2o text file ({exc.reason} at byte {exc.start})") from None
    except OSError as exc:
        raise UsageError(f"cannot read g2o file {path}: {exc.strerror or exc}") from None


def format_g2o(graph: PoseGraph) -> Iterator[str]:
    """The lines (with newlines) of ``graph`` in g2o format.

    Numbers are written with ``repr`` precision (17 significant digits), so reading the
    file back gives bit-identical poses, measurements and information matrices.
    """
    ids = graph.vertex_ids
    for vertex_id, (x, y, theta) in zip(ids, graph.vertices.tolist(), strict=True):
        yield f"VERTEX_SE2 {vertex_id} {x!r} {y!r} {theta!r}\n"
    for index in sorted(graph.fixed):
        yield f"FIX {ids[index]}\n"
    edge_i, edge_j, measurements, information = graph.edge_arrays
    upper = information[:, _UPPER_ROWS, _UPPER_COLS]
    for i, j, z, info in zip(edge_i.tolist(), edge_j.tolist(), measurements.tolist(), upper.tolist(), strict=True):
        numbers = " ".join(repr(v) for v in (*z, *info))
        yield f"EDGE_SE2 {ids[i]} {ids[j]} {numbers}\n"


def write_g2o(graph: PoseGraph, path: str | os.PathLike[str]) -> None:
    """Write ``graph`` to ``path`` atomically (:func:`mazebot.files.write_atomic`)."""
    try:
        write_atomic(path, "".join(format_g2o(graph)).encode("utf-8"), create_folder=False)
    except OSError as exc:
        raise UsageError(f"cannot write g2o file {path}: {exc.strerror or exc}") from None
