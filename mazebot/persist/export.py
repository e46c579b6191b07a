"""Exports of a saved run: ROS map_server PGM + YAML, a PNG and an SVG for people, the cell graph.

- **PGM + YAML** (``--format pgm``): exactly what ROS ``map_server`` loads
  (wiki.ros.org/map_server, "Map format"): 254 free, 0 occupied, 205 unknown, north up
  so the YAML ``origin`` is the bottom-left pixel; ``resolution``, ``origin``,
  ``occupied_thresh``, ``free_thresh``, ``negate`` (:mod:`mazebot.slam.map_export`).
- **PNG** (``--format png``): the map scaled up, the keyframe trajectory in red (start
  marked green), a scale bar and a legend, drawn with a tiny built-in pixel font (no
  plotting library on the robot).
- **SVG** (``--format svg``): the same picture as vectors, in metres (1 user unit = 1 cm).
- **Cell graph** (``--format json``): the maze as the planner sees it
  (:class:`mazebot.planner.maze_graph.MazeGraph` built from the saved map): cells with
  their kind, open links, dead ends, the start cell. Fields the saved run cannot tell
  (the order cells were explored in, when no planner recorded it) are ``null``.
"""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from mazebot.config import MAZE_CELL_M
from mazebot.persist.runs import write_atomic
from mazebot.persist.snapshot import SavedRun
from mazebot.png import encode_png
from mazebot.slam.grid import FREE, OCCUPIED, UNKNOWN
from mazebot.slam.map_export import encode_pgm, encode_yaml

COLOURS = {"free": (255, 255, 255), "wall": (20, 20, 20), "unknown": (190, 190, 190), "path": (220, 30, 30)}
START_COLOUR = (30, 160, 30)

# 3x5 pixel glyphs, rows top to bottom, for the legend and the scale bar
_FONT = {
    "0": "111101101101111", "1": "010110010010111", "2": "111001111100111", "3": "111001111001111",
    "4": "101101111001001", "5": "111100111001111", "6": "111100111101111", "7": "111001001001001",
    "8": "111101111101111", "9": "111101111001111", ".": "000000000000010", " ": "000000000000000",
    "A": "010101111101101", "E": "111100110100111", "F": "111100110100100", "H": "101101111101101",
    "K": "101110100110101", "L": "100100100100111", "M": "101111111101101", "N": "101111111111101",
    "O": "111101101101111", "P": "111101111100100", "R": "110101110101101", "S": "111100111001111",
    "T": "111010010010010", "U": "101101101101111", "W": "101101111111101", "C": "111100100100111",
}


def three_state(saved: SavedRun) -> np.ndarray:
    """The saved map as -1 unknown / 0 free / 100 occupied (row 0 south), with the configured thresholds."""
    occupied = float(np.log(0.75 / 0.25))
    free = float(np.log(0.25 / 0.75))
    slam = saved.meta.get("config", {}).get("slam", {}) if isinstance(saved.meta.get("config"), dict) else {}
    # [slam.grid], or the flat grid_* keys of a run saved before the sections
    grid = slam.get("grid") or {k.removeprefix("grid_"): v for k, v in slam.items() if k.startswith("grid_")}
    if "occupied_prob" in grid and "free_prob" in grid:
        occupied = math.log(grid["occupied_prob"] / (1 - grid["occupied_prob"]))
        free = math.log(grid["free_prob"] / (1 - grid["free_prob"]))
    out = np.full(saved.log_odds.shape, UNKNOWN, dtype=np.int8)
    out[saved.log_odds > occupied] = OCCUPIED
    out[saved.log_odds < free] = FREE
    return out


def origin_m(saved: SavedRun) -> tuple[float, float]:
    return (saved.origin_cells[0] * saved.resolution_m + saved.cell_offset_m[0],
            saved.origin_cells[1] * saved.resolution_m + saved.cell_offset_m[1])


def export_pgm(saved: SavedRun, out: Path) -> list[Path]:
    """``OUT.pgm`` and ``OUT.yaml`` (``out`` without suffix, or with .pgm/.yaml)."""
    stem = out.with_suffix("") if out.suffix in (".pgm", ".yaml") else out
    pgm, yaml = stem.with_name(stem.name + ".pgm"), stem.with_name(stem.name + ".yaml")
    write_atomic(pgm, encode_pgm(three_state(saved)))
    write_atomic(yaml, encode_yaml(saved.resolution_m, origin_m(saved), pgm.name).encode())
    return [pgm, yaml]


def _text(img: np.ndarray, x: int, y: int, text: str, colour: tuple[int, int, int], scale: int = 2) -> int:
    """Draw ``text`` with its top-left corner at (x, y); returns the x after it."""
    for ch in text.upper():
        glyph = _FONT.get(ch, _FONT[" "])
        for k, bit in enumerate(glyph):
            if bit == "1":
                r, c = y + (k // 3) * scale, x + (k % 3) * scale
                img[r : r + scale, c : c + scale] = colour
        x += 4 * scale
    return x


def _scale_bar_m(width_m: float) -> float:
    """A round length near a quarter of the map's width: 0.1, 0.2, 0.5, 1, 2, 5 ... m."""
    target = max(width_m / 4.0, 1e-3)
    power = 10 ** math.floor(math.log10(target))
    return max(m * power for m in (1, 2, 5) if m * power <= target) if target >= power else power


def render_png(saved: SavedRun, pixels_per_cell: int = 3) -> np.ndarray:
    """The RGB picture (row 0 at the top): map, trajectory, scale bar, legend."""
    t = three_state(saved)[::-1]
    rows, cols = t.shape
    k = pixels_per_cell
    margin, legend_h = 10, 40
    h, w = rows * k + 2 * margin + legend_h, max(cols * k + 2 * margin, 360)
    img = np.full((h, w, 3), 255, dtype=np.uint8)
    body = np.empty((rows, cols, 3), dtype=np.uint8)
    body[t == UNKNOWN] = COLOURS["unknown"]
    body[t == FREE] = COLOURS["free"]
    body[t == OCCUPIED] = COLOURS["wall"]
    img[margin : margin + rows * k, margin : margin + cols * k] = np.repeat(np.repeat(body, k, 0), k, 1)
    ox, oy = origin_m(saved)
    res = saved.resolution_m

    def to_px(x_m: float, y_m: float) -> tuple[int, int]:
        return margin + int((x_m - ox) / res * k), margin + int((rows - (y_m - oy) / res) * k)

    xy = saved.trajectory_xy
    for (x0, y0), (x1, y1) in itertools.pairwise(xy):
        (c0, r0), (c1, r1) = to_px(x0, y0), to_px(x1, y1)
        n = max(abs(c1 - c0), abs(r1 - r0), 1)
        cc = np.round(np.linspace(c0, c1, n + 1)).astype(int)
        rr = np.round(np.linspace(r0, r1, n + 1)).astype(int)
        ok = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
        img[rr[ok], cc[ok]] = COLOURS["path"]
    c, r = to_px(0.0, 0.0)
    img[max(r - 3, 0) : r + 4, max(c - 3, 0) : c + 4] = START_COLOUR
    # scale bar, under the map
    bar_m = _scale_bar_m(cols * res)
    bar_px = round(bar_m / res * k)
    y = margin + rows * k + 8
    img[y : y + 4, margin : margin + bar_px] = (0, 0, 0)
    _text(img, margin + bar_px + 6, y - 2, f"{bar_m:g} M", (0, 0, 0))
    # legend
    x, y = margin, y + 16
    for name, label in (("free", "FREE"), ("wall", "WALL"), ("unknown", "UNKNOWN"), ("path", "PATH")):
        img[y : y + 10, x : x + 10] = (0, 0, 0)
        img[y + 1 : y + 9, x + 1 : x + 9] = COLOURS[name]
        x = _text(img, x + 14, y, label, (0, 0, 0)) + 10
    return img


def export_png(saved: SavedRun, out: Path) -> list[Path]:
    path = out if out.suffix == ".png" else out.with_name(out.name + ".png")
    write_atomic(path, encode_png(render_png(saved)))
    return [path]


def render_svg(saved: SavedRun) -> str:
    """The map as SVG: one rectangle per horizontal run of free or wall cells; units of 1 cm, north up."""
    t = three_state(saved)
    rows, cols = t.shape
    res_cm = saved.resolution_m * 100.0
    ox, oy = origin_m(saved)
    width, height = cols * res_cm, rows * res_cm
    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {width:.1f} {height + 30:.1f}" '
        f'width="{width:.1f}mm" height="{height + 30:.1f}mm">',
        f'<rect width="{width:.1f}" height="{height:.1f}" fill="rgb{COLOURS["unknown"]}"/>',
    ]
    for value, name in ((FREE, "free"), (OCCUPIED, "wall")):
        parts.append(f'<g fill="rgb{COLOURS[name]}">')
        for r in range(rows):
            line = np.concatenate(([False], t[r] == value, [False]))
            edges = np.flatnonzero(np.diff(line.astype(np.int8)))
            y = (rows - 1 - r) * res_cm
            for c0, c1 in zip(edges[::2], edges[1::2], strict=True):
                parts.append(f'<rect x="{c0 * res_cm:.1f}" y="{y:.1f}" width="{(c1 - c0) * res_cm:.1f}" '
                             f'height="{res_cm:.1f}"/>')
        parts.append("</g>")
    pts = " ".join(f"{(x - ox) * 100:.1f},{height - (y - oy) * 100:.1f}" for x, y in saved.trajectory_xy)
    if pts:
        parts.append(f'<polyline points="{pts}" fill="none" stroke="rgb{COLOURS["path"]}" stroke-width="1"/>')
    parts.append(f'<circle cx="{-ox * 100:.1f}" cy="{height + oy * 100:.1f}" r="2" fill="rgb{START_COLOUR}"/>')
    bar_m = _scale_bar_m(cols * saved.resolution_m)
    parts.append(f'<rect x="2" y="{height + 8:.1f}" width="{bar_m * 100:.1f}" height="2" fill="black"/>')
    parts.append(f'<text x="{bar_m * 100 + 5:.1f}" y="{height + 11:.1f}" font-size="5">{bar_m:g} m</text>')
    x = 2.0
    for name, label in (("free", "free"), ("wall", "wall"), ("unknown", "unknown"), ("path", "trajectory")):
        parts.append(f'<rect x="{x:.1f}" y="{height + 18:.1f}" width="5" height="5" fill="rgb{COLOURS[name]}" '
                     'stroke="black" stroke-width="0.3"/>')
        parts.append(f'<text x="{x + 7:.1f}" y="{height + 22.5:.1f}" font-size="5">{label}</text>')
        x += 12 + 3.2 * len(label)
    parts.append("</svg>\n")
    return "\n".join(parts)


def export_svg(saved: SavedRun, out: Path) -> list[Path]:
    path = out if out.suffix == ".svg" else out.with_name(out.name + ".svg")
    write_atomic(path, render_svg(saved).encode())
    return [path]


def cell_graph(saved: SavedRun, cell_size_m: float | None = None) -> dict[str, Any]:
    """The maze cell graph of the saved map; what cannot be known is ``None``."""
    from mazebot.planner.maze_graph import Direction, MazeGraph

    meta = saved.meta
    cfg = meta.get("config") if isinstance(meta.get("config"), dict) else {}
    if cell_size_m is None:
        cell_size_m = float(cfg.get("sim", {}).get("cell_size_m", MAZE_CELL_M)) if cfg else MAZE_CELL_M
    graph = MazeGraph(cell_size_m=cell_size_m)
    graph.update(three_state(saved), origin_m(saved), saved.resolution_m)
    out: dict[str, Any] = {
        "cell_size_m": cell_size_m,
        "source": "maze graph built from the saved map (mazebot.planner.maze_graph)",
        "frame": None,
        "cells": None,
        "open_links": None,
        "dead_ends": None,
        "start": None,
        # the planner's visiting order is not part of a saved run unless it recorded one
        "explored_order": meta.get("explored_order"),
    }
    if not graph.ready or graph.frame is None:
        return out
    frame = graph.frame
    out["frame"] = {"angle_rad": frame.angle_rad, "origin_m": list(frame.origin_m)}
    cells = sorted(graph.cells())
    out["cells"] = [
        {"cell": list(c), "kind": str(graph.kind(c)), "center_m": [round(v, 4) for v in frame.cell_center_m(c)]}
        for c in cells
    ]
    links = []
    for c in cells:
        for d in (Direction.E, Direction.N):  # each link once
            n = (c[0] + d.step[0], c[1] + d.step[1])
            if graph.link_between(c, n).name == "OPEN":
                links.append([list(c), list(n)])
    out["open_links"] = links
    out["dead_ends"] = [list(c) for c in cells if len(graph.open_neighbours(c)) == 1]
    out["start"] = list(frame.cell_of(0.0, 0.0))
    return out


def export_json(saved: SavedRun, out: Path) -> list[Path]:
    path = out if out.suffix == ".json" else out.with_name(out.name + ".json")
    write_atomic(path, (json.dumps(cell_graph(saved), indent=2) + "\n").encode())
    return [path]


EXPORTERS = {"pgm": export_pgm, "png": export_png, "svg": export_svg, "json": export_json}
