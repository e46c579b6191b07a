"""The benchmark harness end to end: the whole daemon on the simulated robot, virtual time.

The smoke suite is what CI runs (under two minutes: docs/design.md, "Budgets"); the exploration run is the
autonomous stack (planner, DWA, wheel PI, safety layer) on SLAM's map and pose, measured
against the simulator's ground truth.
"""

from __future__ import annotations

import itertools
import json
import math
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from mazebot.bench.cli import suite_specs
from mazebot.bench.runner import RunSpec, run_one
from mazebot.cli import main
from mazebot.config import Config
from mazebot.errors import UsageError

REQUIRED_KEYS = {
    "maze", "seed", "cells", "done", "time_s", "wall_s", "path_m", "avg_speed_mps", "coverage", "collisions",
    "revisits", "ate_rms_m", "ate_max_m", "heading_rms_deg", "map_f1", "scan_ms_p50", "scan_ms_p99",
    "control_jitter_ms_p99", "cpu_percent", "rss_mb",
}


def read_png(path: Path) -> tuple[int, int, bytes]:
    """Width, height and raw scanlines of a PNG, every chunk's CRC checked (an independent reader)."""
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", f"{path.name}: not a PNG signature"
    pos, idat, width, height, bit_depth, colour = 8, b"", 0, 0, 0, 0
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length : pos + 12 + length])
        assert zlib.crc32(kind + body) == crc, f"{path.name}: bad CRC in {kind!r}"
        if kind == b"IHDR":
            width, height, bit_depth, colour = struct.unpack(">IIBB", body[:10])
        elif kind == b"IDAT":
            idat += body
        pos += 12 + length
    assert bit_depth == 8 and colour == 2, f"{path.name}: expected 8-bit RGB"
    raw = zlib.decompress(idat)
    assert len(raw) == height * (1 + 3 * width)
    return width, height, raw


@pytest.mark.slow
def test_smoke_suite_with_the_scripted_drive_writes_every_key_and_figures_that_open(tmp_path: Path) -> None:
    assert main(["bench", "--suite", "smoke", "--drive", "scripted", "--out", str(tmp_path)]) == 0
    results = json.loads((tmp_path / "results.json").read_text())
    (run,) = results["runs"]
    assert run.keys() >= REQUIRED_KEYS, f"missing keys: {REQUIRED_KEYS - run.keys()}"
    assert run["done"] is True and run["collisions"] == 0
    assert run["cells"] == 36
    # SLAM against the ground truth: centimetre-level on the default 6x6 maze
    assert run["ate_rms_m"] < 0.02 and run["heading_rms_deg"] < 2.0
    assert run["map_f1"] > 0.9 and run["coverage"] > 0.9
    assert run["false_loop_closures"] == 0
    # virtual time has no control jitter to measure: null, never invented
    assert run["control_jitter_ms_p99"] is None
    assert "summary" in results
    report = (tmp_path / "report.md").read_text()
    figures = sorted(tmp_path.glob("*.png"))
    assert len(figures) == 2
    for png in figures:
        assert png.name in report
        width, height, raw = read_png(png)
        assert width > 100 and height > 100
        pixels = np.frombuffer(raw, np.uint8).reshape(height, 1 + 3 * width)[:, 1:]
        assert len(np.unique(pixels.reshape(-1, 3), axis=0)) >= 3  # a picture, not a blank


@pytest.mark.slow
def test_the_robot_explores_a_maze_by_itself_and_comes_back_to_the_start() -> None:
    """Start pressed once; the planner, DWA, wheel PI and safety layer drive on SLAM's estimate."""
    spec = RunSpec(None, (4, 4), seed=3, drive="explore", max_sim_s=300.0)
    metrics, record = run_one(Config(), spec)
    assert metrics["done"] is True, metrics["fault"]
    assert metrics["collisions"] == 0
    assert metrics["coverage"] >= 0.95
    assert metrics["map_f1"] >= 0.9
    state = record.state
    assert state is not None and state.run_state.value == "done"
    assert state.coverage == 1.0  # every reachable cell of the graph explored
    # back in the start cell, near its centre (the explorer's arrival tolerance is 6 cm)
    world = record.hardware.sim.world  # type: ignore[union-attr]
    x, y, _ = record.true_poses[-1]
    assert world.maze.cell_at(x, y) == world.maze.start_cell
    start_x, start_y, _ = world.start_pose
    assert math.dist((x, y), (start_x, start_y)) < 0.1
    # the planner's decisions are logged with their times: targets in order, the return last
    events = list(state.planner_events)
    assert events and all(a[0] <= b[0] for a, b in itertools.pairwise(events))
    assert any("look at" in text for _, text in events)
    assert any(text.startswith("return to start") for _, text in events)


def test_revisits_count_real_back_tracking_not_swaying_across_a_cell_border() -> None:
    from mazebot.bench.metrics import count_revisits
    from mazebot.sim.maze_file import parse_maze

    layout = parse_maze("o---o---o---o\n|           |\no---o---o---o\n", 0.3048)
    cx0, cy = layout.cell_center_m((0, 0))
    border_x = cx0 + 0.5 * 0.3048
    # down the corridor, swaying +-1 cm across the (0,0)|(1,0) border ten times, on to (2,0)
    sway = [(border_x + (0.01 if k % 2 else -0.01), cy) for k in range(10)]
    ahead = [(cx0 + k * 0.05, cy) for k in range(13)]
    assert count_revisits(layout, np.array([*sway, *ahead])) == 0
    # back-tracking from (2,0) to (0,0) is two revisits: (1,0) and (0,0)
    back = [(x, cy) for x, _ in reversed(ahead)]
    assert count_revisits(layout, np.array([*ahead, *back])) == 2


def test_a_suite_can_be_split_over_processes_by_its_first_seed() -> None:
    first = suite_specs("standard", 15, "explore", "virtual")
    second = suite_specs("standard", 15, "explore", "virtual", first_seed=16)
    generated = [s.seed for s in first + second if s.size == (6, 6)]
    assert generated == list(range(1, 31))
    assert [s.seed for s in suite_specs("6x6", 5, "explore", "virtual", first_seed=6)] == [6, 7, 8, 9, 10]


def test_the_fault_suite_runs_every_fault_on_each_seed_asked_for() -> None:
    from mazebot.sim.faults import FAULTS

    specs = suite_specs("faults", 2, "explore", "virtual", first_seed=3)
    assert len(specs) == 2 * len(FAULTS)
    assert {(s.seed, s.faults[0].name) for s in specs} == {(seed, name) for seed in (3, 4) for name in FAULTS}
    assert {s.seed for s in suite_specs("faults", 1, "explore", "virtual")} == {1}


def test_a_long_suite_writes_what_it_has_measured_as_it_goes(tmp_path: Path) -> None:
    from mazebot.bench.report import write_partial

    runs = [{"maze": "m", "seed": 1, "done": True, "time_s": 10.0, "collisions": 0}]
    write_partial(tmp_path, runs, "mazebot bench ...", planned=3)
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["partial"] is True and results["planned_runs"] == 3
    assert results["runs"] == runs and results["summary"]["done"] == 1


def test_large_maze_files_get_a_time_limit_that_fits_their_size() -> None:
    """A 16x16 contest maze needs ~10 simulated minutes: 900 s would call it not done."""
    from mazebot.bench.cli import time_limit_s
    from mazebot.sim.maze_file import packaged_maze_path

    assert time_limit_s(str(packaged_maze_path("default_6x6.txt"))) == 900.0
    assert time_limit_s(str(packaged_maze_path("japan2013ef.txt"))) == 14.0 * 256


def test_generated_mazes_of_another_size_get_a_time_limit_for_their_cells() -> None:
    from mazebot.bench.cli import generated_specs, parse_size

    assert parse_size("16x16") == (16, 16) and parse_size("8X5") == (8, 5)
    for bad in ("16", "16x", "axb", "1x16"):
        with pytest.raises(UsageError):
            parse_size(bad)
    specs = generated_specs((16, 16), range(3, 6), "scripted", "virtual")
    assert [(s.size, s.seed, s.drive) for s in specs] == [((16, 16), k, "scripted") for k in (3, 4, 5)]
    assert specs[0].max_sim_s == pytest.approx(14.0 * 256)  # the 6x6's 900 s would cut a 16x16 tour
    assert generated_specs((6, 6), range(1, 2), "scripted", "virtual")[0].max_sim_s == 900.0
