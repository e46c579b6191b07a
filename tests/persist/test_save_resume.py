"""Saving a run and resuming it: what is written loads back equal, a crash mid-save keeps the
previous save, a damaged file is one line, and a resumed SLAM continues in the saved map.

The SLAM is the real one, fed revolutions cast in a generated maze (the simulator's ray
caster) while the robot turns on the spot with a perfect odometry.
"""

from __future__ import annotations

import math
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mazebot.errors import MazebotError
from mazebot.geometry import compose, relative_pose, wrap_angle
from mazebot.io.scan import Scan
from mazebot.persist.resume import resume_slam
from mazebot.persist.snapshot import SavedRun, load_run, save_snapshot, take_snapshot
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.raycast import cast_rays
from mazebot.sim.world import World, world_from_layout
from mazebot.slam.ekf import OdometryHistory
from mazebot.slam.slam import Slam, SlamParams

PERIOD_S = 1 / 5.5
TURN_STEPS = 22
TURN_RAD = 0.05  # per revolution


@pytest.fixture(scope="module")
def world() -> World:
    return world_from_layout(generate_maze(6, 6, seed=3, kind="braided"), 0.012)


def _scan(world: World, pose: np.ndarray, t0_s: float, seed: int, turned_rad: float = 0.0) -> Scan:
    """One revolution (360 beams, 0.5 % range noise) ending at world ``pose``, the robot having
    turned ``turned_rad`` on the spot during it at a steady rate, as the odometry says."""
    n = 360
    angles = np.linspace(-np.pi, np.pi, n, endpoint=False)
    headings = pose[2] - turned_rad * (1.0 - (np.arange(n) + 1) / n)  # each beam from its own heading
    origins = np.tile(pose[:2], (n, 1))
    ranges = cast_rays(origins, angles + headings, world.segments, world.circles, 12.0)
    ranges = ranges * (1.0 + 0.005 * np.random.default_rng(seed).standard_normal(n))
    valid = np.isfinite(ranges)
    return Scan(angle_rad=angles, range_m=np.where(valid, ranges, 0.0), quality=np.where(valid, 47, 0).astype(np.uint8),
                time_s=t0_s + (np.arange(n) + 1) * (PERIOD_S / n), valid=valid)


def _params() -> SlamParams:
    return SlamParams(keyframe_angle_rad=0.15)  # a keyframe every few revolutions of the turn


def _mapped(world: World) -> tuple[Slam, np.ndarray]:
    """SLAM after a turn of 1 rad on the spot at the world's start; and the true final world pose."""
    start = np.asarray(world.start_pose, dtype=np.float64)
    slam = Slam(_params(), background=False, record_trajectory=False)
    history = OdometryHistory(horizon_s=30.0)
    history.append(0.0, 0.0, 0.0, 0.0)
    t = 0.0
    true = start
    for k in range(TURN_STEPS):
        heading = TURN_RAD * k
        true = compose(start, np.array([0.0, 0.0, heading]))
        scan = _scan(world, true, t, seed=k, turned_rad=TURN_RAD if k else 0.0)
        t += PERIOD_S
        history.append(t, 0.0, 0.0, heading)
        slam.update(scan, history)
    assert len(slam.keyframes) >= 5
    return slam, true


@pytest.fixture(scope="module")
def mapped(world: World) -> tuple[Slam, np.ndarray]:
    return _mapped(world)


def _save(slam: Slam, run_dir: Path) -> None:
    save_snapshot(take_snapshot(slam), run_dir)


def _saved_run(mapped: tuple[Slam, np.ndarray], run_dir: Path) -> tuple[SavedRun, np.ndarray]:
    """The mapped run saved in ``run_dir`` and loaded back; and the true final world pose."""
    slam, true_end = mapped
    _save(slam, run_dir)
    return load_run(run_dir), true_end


def test_a_saved_map_and_pose_graph_load_back_equal(mapped: tuple[Slam, np.ndarray], tmp_path: Path) -> None:
    slam, _ = mapped
    snap = take_snapshot(slam)
    save_snapshot(snap, tmp_path)
    saved = load_run(tmp_path)
    assert np.array_equal(saved.log_odds, snap.log_odds.astype(np.float32))
    assert saved.origin_cells == snap.origin_cells and saved.resolution_m == snap.resolution_m
    assert len(saved.keyframes) == len(snap.keyframes) == len(saved.graph)
    for got, want, pose in zip(saved.keyframes, snap.keyframes, snap.poses, strict=True):
        assert got.time_s == want.time_s
        assert np.array_equal(got.pose, pose)
        assert np.array_equal(got.hits, want.hits) and np.array_equal(got.match_points, want.match_points)
        assert np.array_equal(got.ray_ends, want.ray_ends) and np.array_equal(got.ray_hit, want.ray_hit)
    # the pose graph: the same vertices and the same edges (g2o text keeps every digit of a float)
    np.testing.assert_allclose(saved.graph.vertices, snap.graph.vertices, rtol=0, atol=1e-12)
    for got_edges, want_edges in zip(saved.graph.edge_arrays, snap.graph.edge_arrays, strict=True):
        np.testing.assert_allclose(got_edges, want_edges, rtol=1e-12, atol=1e-12)
    assert saved.meta["pose"] == list(snap.pose) and saved.meta["keyframes"] == len(snap.keyframes)


def test_a_crash_in_the_middle_of_a_save_leaves_the_previous_save_whole(
    world: World, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    slam, _ = _mapped(world)
    _save(slam, tmp_path)
    before = load_run(tmp_path)
    # more map, then a save that dies while writing its third file (grid.npz): the process
    # is gone before that file's rename, as with a power cut
    history = OdometryHistory(horizon_s=30.0)
    history.append(0.0, 0.0, 0.0, 0.0)
    writes: list[str] = []
    real_replace = os.replace

    def replace_then_die(src: str, dst: str) -> None:
        writes.append(Path(dst).name)
        if len(writes) == 3:
            raise OSError(28, "No space left on device")
        real_replace(src, dst)

    slam.keyframes.append(slam.keyframes[-1])  # the live SLAM moved on (one keyframe more)
    monkeypatch.setattr("mazebot.files.os.replace", replace_then_die)
    with pytest.raises(OSError):
        _save(slam, tmp_path)
    monkeypatch.undo()
    assert writes == ["map.pgm", "map.yaml", "grid.npz"]
    after = load_run(tmp_path)  # meta.json, grid, graph and keyframes of the first save, all whole
    assert len(after.keyframes) == len(before.keyframes)
    assert np.array_equal(after.log_odds, before.log_odds)
    assert after.meta == before.meta
    assert not [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")]  # no temporary file left


@pytest.mark.parametrize(("name", "damage"), [
    ("grid.npz", b"PK\x03\x04 cut short"),
    ("keyframes.npz", b""),
    ("meta.json", b'{"format_version": 1, '),
])
def test_a_damaged_file_is_one_line_naming_the_run(
    mapped: tuple[Slam, np.ndarray], tmp_path: Path, name: str, damage: bytes
) -> None:
    _save(mapped[0], tmp_path)
    (tmp_path / name).write_bytes(damage)
    with pytest.raises(MazebotError) as err:
        load_run(tmp_path)
    message = str(err.value)
    assert "\n" not in message and str(tmp_path) in message


def test_a_graph_that_disagrees_with_the_keyframes_is_one_line(mapped: tuple[Slam, np.ndarray], tmp_path: Path) -> None:
    _save(mapped[0], tmp_path)
    lines = (tmp_path / "graph.g2o").read_text().splitlines()
    vertices = [line for line in lines if line.startswith("VERTEX_SE2")]
    (tmp_path / "graph.g2o").write_text("\n".join(vertices[:-1]) + "\n")  # one pose and every edge lost
    with pytest.raises(MazebotError) as err:
        load_run(tmp_path)
    assert "\n" not in str(err.value) and "graph.g2o" in str(err.value)


def test_resume_continues_from_the_saved_pose_in_the_saved_map(
    world: World, mapped: tuple[Slam, np.ndarray], tmp_path: Path
) -> None:
    saved, true_end = _saved_run(mapped, tmp_path)
    saved_pose = np.asarray(saved.meta["pose"])
    start = np.asarray(world.start_pose, dtype=np.float64)
    # the truth in the map frame (the first run's start pose), where the first run stopped
    truth = relative_pose(start, true_end)
    assert math.hypot(*(saved_pose[:2] - truth[:2])) < 0.02  # the save holds the right pose
    assert abs(math.degrees(wrap_angle(saved_pose[2] - truth[2]))) < 0.5
    resumed = resume_slam(_params(), saved, guess=tuple(saved_pose), background=False, record_trajectory=False)
    # a new process: the odometry starts again from zero, the robot has not moved
    history = OdometryHistory(horizon_s=30.0)
    history.append(0.0, 0.0, 0.0, 0.0)
    history.append(PERIOD_S, 0.0, 0.0, 0.0)
    update = resumed.update(_scan(world, true_end, 0.0, seed=500), history)
    found = resumed.relocalization
    assert found is not None and found.accepted
    # the robot stood still: found where the save left it, and where it truly is
    assert math.hypot(*(found.pose[:2] - saved_pose[:2])) < 0.01
    assert abs(math.degrees(wrap_angle(found.pose[2] - saved_pose[2]))) < 0.5
    assert math.hypot(*(found.pose[:2] - truth[:2])) < 0.02
    assert abs(math.degrees(wrap_angle(found.pose[2] - truth[2]))) < 0.5
    assert math.hypot(*(update.pose[:2] - truth[:2])) < 0.02
    assert abs(math.degrees(wrap_angle(update.pose[2] - truth[2]))) < 0.5
    # the saved keyframes and map go on: nothing restarted from an empty map
    assert len(resumed.keyframes) >= len(saved.keyframes)
    known = resumed.grid.three_state() != resumed.grid.three_state()[0, 0]
    assert known.sum() >= (saved.log_odds != 0).sum() * 0.9
    # the robot turns on: the resumed run tracks in the same frame
    t = PERIOD_S
    for k in range(1, 6):
        true = compose(true_end, np.array([0.0, 0.0, TURN_RAD * k]))
        scan = _scan(world, true, t, seed=600 + k, turned_rad=TURN_RAD)
        t += PERIOD_S
        history.append(t, 0.0, 0.0, TURN_RAD * k)
        update = resumed.update(scan, history)
    want = relative_pose(start, true)
    assert math.hypot(*(update.pose[:2] - want[:2])) < 0.02
    assert abs(math.degrees(wrap_angle(update.pose[2] - want[2]))) < 0.5
    turned = wrap_angle(update.pose[2] - found.pose[2])  # what the resumed run measured of the turn
    assert abs(math.degrees(turned - 5 * TURN_RAD)) < 0.5


def test_a_robot_that_starts_to_turn_in_its_first_revolution_is_found_with_the_lidars_stamps_shifted(
    world: World, mapped: tuple[Slam, np.ndarray], tmp_path: Path
) -> None:
    # The lidar's stamps are late by 0.1 s against the odometry's, and the robot starts to turn
    # half-way through the revolution. Re-localization must de-skew the revolution at the shifted
    # stamps, as SLAM's own update does: at the unshifted ones the odometry says the turn began
    # before the first sample, and the samples are spread over twice the true turn.
    saved, true_end = _saved_run(mapped, tmp_path)
    start = np.asarray(world.start_pose, dtype=np.float64)
    offset_s, rate_radps, turn_from_s = 0.1, 1.0, 0.5 * PERIOD_S
    params = replace(_params(), lidar_time_offset_s=offset_s, estimate_time_offset=False)
    resumed = resume_slam(params, saved, guess=tuple(saved.meta["pose"]), background=False,
                          record_trajectory=False)
    history = OdometryHistory(horizon_s=30.0)
    for t in np.arange(0.0, PERIOD_S + 0.3, 0.005):
        history.append(float(t), 0.0, 0.0, rate_radps * max(0.0, float(t) - turn_from_s))
    n = 360
    beam_s = (np.arange(n) + 1) * (PERIOD_S / n)  # each beam's true time
    turned = rate_radps * np.maximum(0.0, beam_s - turn_from_s)
    angles = np.linspace(-np.pi, np.pi, n, endpoint=False)
    origins = np.tile(true_end[:2], (n, 1))
    ranges = cast_rays(origins, angles + true_end[2] + turned, world.segments, world.circles, 12.0)
    valid = np.isfinite(ranges)
    scan = Scan(angle_rad=angles, range_m=np.where(valid, ranges, 0.0), quality=np.where(valid, 47, 0).astype(np.uint8),
                time_s=beam_s + offset_s, valid=valid)  # stamped late
    resumed.update(scan, history)
    found = resumed.relocalization
    assert found is not None and found.accepted
    truth = relative_pose(start, compose(true_end, np.array([0.0, 0.0, turned[-1]])))
    assert math.hypot(*(found.pose[:2] - truth[:2])) < 0.02
    assert abs(math.degrees(wrap_angle(found.pose[2] - truth[2]))) < 0.5
