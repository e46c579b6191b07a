"""The broadcaster without sockets: what it sends, when, and to a viewer that falls behind."""

from __future__ import annotations

import json
import math
from collections import deque

import numpy as np
import pytest

from mazebot.slam.grid import OccupancyGrid
from mazebot.slam.odometry import OdometryPose
from mazebot.state import RunState, SharedState
from mazebot.web.broadcaster import Broadcaster, Viewer, covariance_ellipse
from mazebot.web.protocol import KIND_DELTA, KIND_FULL, decode_packet


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _packets(viewer: Viewer) -> list[bytes]:
    return [p for p in viewer.pending() if isinstance(p, bytes)]


def _drain(viewer: Viewer) -> list[bytes | str]:
    items = viewer.pending()
    viewer._items.clear()  # what the writer task would have sent
    return items


@pytest.fixture
def state() -> SharedState:
    return SharedState()


def test_a_new_viewer_gets_hello_and_a_full_map_then_nothing_until_something_changes(state, fake_grid) -> None:
    state.map = fake_grid()
    b = Broadcaster(state, now_s=Clock())
    viewer = b.add(None, "phone")  # type: ignore[arg-type]
    hello, full = _drain(viewer)
    assert json.loads(hello)["type"] == "hello"
    packet = decode_packet(full)
    assert packet.kind == KIND_FULL and packet.seq == 1 and packet.map is not None
    assert packet.status["state"] == "idle" and packet.status["pose"] == [0.0, 0.0, 0.0]
    for _ in range(10):
        assert b.tick() is False
    assert viewer.pending() == []


def test_deltas_carry_only_changed_cells_and_fields_and_rebuild_the_map_exactly(state, fake_grid, mirror) -> None:
    grid = fake_grid()
    state.map = grid
    b = Broadcaster(state, now_s=Clock())
    viewer, page = b.add(None, "phone"), mirror()  # type: ignore[arg-type]
    rng = np.random.default_rng(1)
    for step in range(30):
        rows, cols = rng.integers(0, grid.shape[0], 12), rng.integers(0, grid.shape[1], 12)
        grid.cells[rows, cols] = rng.choice([-1, 0, 100], 12)
        state.pose.x_m = 0.01 * step
        assert b.tick()
        for item in _drain(viewer):
            if isinstance(item, bytes):
                assert page.apply(item)
        assert page.matches(grid)
    deltas = [decode_packet(p) for p in _two_more_steps(b, state, grid)]
    assert all(d.kind == KIND_DELTA for d in deltas)
    assert page.gaps == 0 and page.status["pose"][0] == pytest.approx(0.29)


def _two_more_steps(b: Broadcaster, state: SharedState, grid) -> list[bytes]:
    """Two more steps: one map-only change, one pose-only change; their raw packets."""
    viewer = b.add(None, "late")  # type: ignore[arg-type]
    _drain(viewer)
    grid.cells[3, 4] = 100 if grid.cells[3, 4] != 100 else 0
    b.tick()
    only_map = decode_packet(_packets(viewer)[-1])
    assert set(only_map.status) == {"elapsed_s", "t_ms"}  # no unchanged field repeated
    assert len(only_map.map) == 1 and only_map.map.indices[0] == 3 * grid.shape[1] + 4
    state.pose.theta_rad = 1.0
    b.tick()
    only_pose = decode_packet(_packets(viewer)[-1])
    assert only_pose.map is None and only_pose.status["pose"][2] == 1.0
    return _packets(viewer)


def test_every_50th_packet_is_a_full_map(state, fake_grid) -> None:
    state.map = fake_grid()
    b = Broadcaster(state, now_s=Clock(), queue_packets=1000)
    viewer = b.add(None, "phone")  # type: ignore[arg-type]
    _drain(viewer)
    for step in range(120):
        state.pose.y_m = 0.001 * (step + 1)
        b.tick()
    kinds = {decode_packet(p).seq: decode_packet(p).kind for p in _packets(viewer)}
    assert sorted(s for s, k in kinds.items() if k == KIND_FULL) == [50, 100]
    assert len(kinds) == 120


def test_map_growth_and_rebuild_send_a_full_map_with_a_new_epoch(state, fake_grid, mirror) -> None:
    grid = fake_grid()
    grid.cells[10, 10] = 100
    state.map = grid
    b = Broadcaster(state, now_s=Clock())
    viewer, page = b.add(None, "phone"), mirror()  # type: ignore[arg-type]
    for item in _packets(viewer):
        page.apply(item)
    epoch = page.epoch
    _drain(viewer)
    grid.grow(60, 80)
    assert b.tick()
    (packet,) = _packets(viewer)
    assert decode_packet(packet).kind == KIND_FULL
    page.apply(packet)
    assert page.epoch != epoch and page.codes.shape == (60, 80) and page.matches(grid)
    # a loop closure replaces the grid object (same shape): full map again
    _drain(viewer)
    rebuilt = fake_grid()
    rebuilt.cells = grid.cells.copy()
    rebuilt.origin_m, rebuilt.generation = grid.origin_m, grid.generation + 1
    state.map = rebuilt
    b.tick()
    assert decode_packet(_packets(viewer)[0]).kind == KIND_FULL
    # the map going away (a new run) is a full packet without a map
    _drain(viewer)
    state.map = None
    b.tick()
    gone = decode_packet(_packets(viewer)[0])
    assert gone.kind == KIND_FULL and gone.map is None


def test_a_real_occupancy_grid_is_mirrored_through_growth(state, mirror) -> None:
    grid = OccupancyGrid(resolution_m=0.05, margin_m=0.2)
    state.map = grid
    b = Broadcaster(state, now_s=Clock())
    viewer, page = b.add(None, "phone"), mirror()  # type: ignore[arg-type]
    angles = np.linspace(-math.pi, math.pi, 90, endpoint=False)
    for k in range(8):  # the robot drives east; the grid grows as it sees farther
        x = 0.3 * k
        ends = np.column_stack((x + 1.0 * np.cos(angles), 1.0 * np.sin(angles)))
        grid.integrate(np.array([x, 0.0, 0.0]), ends, np.ones(90, bool))
        state.pose.x_m = x
        b.tick()
        for item in _drain(viewer):
            if isinstance(item, bytes):
                assert page.apply(item)
        np.testing.assert_array_equal(page.codes, (grid.three_state() == 0) * 1 + (grid.three_state() == 100) * 2)


def test_a_slow_viewer_loses_its_queue_and_gets_a_full_map_while_others_get_every_delta(state, fake_grid, mirror):
    grid = fake_grid()
    state.map = grid
    b = Broadcaster(state, now_s=Clock(), queue_packets=4)
    slow = b.add(None, "slow")  # type: ignore[arg-type]
    fast, page = b.add(None, "fast"), mirror()  # type: ignore[arg-type]
    for step in range(25):
        grid.cells[step % 40, step] = 0
        b.tick()
        for item in _drain(fast):
            if isinstance(item, bytes):
                assert page.apply(item)
        assert slow.queued <= 4  # bounded whatever happens
    assert page.gaps == 0 and page.matches(grid)
    assert slow.dropped > 0
    # what the slow one finally reads starts with a full map and then applies in order
    slow_page = mirror()
    packets = _packets(slow)
    assert decode_packet(packets[0]).kind == KIND_FULL
    for p in packets:
        assert slow_page.apply(p)
    assert slow_page.matches(grid)


def test_resync_sends_the_full_map_of_the_last_packet(state, fake_grid, mirror) -> None:
    grid = fake_grid()
    state.map = grid
    b = Broadcaster(state, now_s=Clock())
    viewer = b.add(None, "phone")  # type: ignore[arg-type]
    grid.cells[1, 1] = 100
    b.tick()
    _drain(viewer)
    grid.cells[2, 2] = 100
    b.tick()
    lost = _drain(viewer)  # say the page never saw this delta
    assert len(lost) == 1
    grid.cells[3, 3] = 100
    b.tick()
    page = mirror()
    page.seq, page.epoch = 2, 1  # it had seq 2 and now sees seq 4: a gap
    (after_gap,) = _drain(viewer)
    assert not page.apply(after_gap)
    b.resync(viewer)
    (full,) = _drain(viewer)
    assert decode_packet(full).kind == KIND_FULL and decode_packet(full).seq == 4
    assert page.apply(full) and page.matches(grid)


def test_status_fields_pose_ellipse_trail_path_goal_coverage_speed_and_elapsed(state, fake_grid) -> None:
    clock = Clock()
    b = Broadcaster(state, now_s=clock, trail_points=3)
    viewer = b.add(None, "phone")  # type: ignore[arg-type]
    _drain(viewer)
    state.run_state, state.started_at_s = RunState.EXPLORING, clock.t
    state.odometry = OdometryPose(distance_m=0.0)
    state.pose_covariance = np.diag([0.04, 0.01, 0.0025])
    state.trajectory.extend([(0.0, 0.0), (0.1, 0.0)])
    state.path = [(0.3048, 0.0), (0.3048, 0.3048)]
    state.goal = (0.3048, 0.3048)
    state.coverage = 0.4567
    b.tick()
    clock.t += 0.5
    state.odometry = OdometryPose(distance_m=0.1)
    state.trajectory.append((0.2, 0.01))
    b.tick()
    first, second = (decode_packet(p).status for p in _drain(viewer))
    assert first["state"] == "exploring" and first["trail"] == [0.0, 0.0, 0.1, 0.0]
    assert first["path"] == [0.305, 0.0, 0.305, 0.305] and first["goal"] == [0.305, 0.305]
    assert first["coverage"] == 0.457
    a, b_, angle, theta_std = first["ellipse"]
    assert a == pytest.approx(math.sqrt(5.991) * 0.2, abs=1e-3)
    assert b_ == pytest.approx(math.sqrt(5.991) * 0.1, abs=1e-3)
    assert abs(math.sin(angle)) < 1e-6 and theta_std == pytest.approx(0.05)
    assert second["trail+"] == [0.2, 0.01] and "path" not in second
    assert second["speed_mps"] == pytest.approx(0.2) and second["elapsed_s"] == 0.5
    # the tail a late viewer gets is bounded; a replaced trajectory is sent whole
    late = b.add(None, "late")  # type: ignore[arg-type]
    assert decode_packet(_packets(late)[0]).status["trail"] == [0.0, 0.0, 0.1, 0.0, 0.2, 0.01]
    state.trajectory = deque([(5.0, 5.0)])
    b.tick()
    assert decode_packet(_packets(viewer)[-1]).status["trail"] == [5.0, 5.0]


def test_covariance_ellipse_follows_the_major_axis() -> None:
    c, s = math.cos(0.5), math.sin(0.5)
    rot = np.array([[c, -s], [s, c]])
    cov = np.zeros((3, 3))
    cov[:2, :2] = rot @ np.diag([0.09, 0.01]) @ rot.T
    a, b, angle, _ = covariance_ellipse(cov)
    assert a == pytest.approx(math.sqrt(5.991) * 0.3, abs=1e-3) and b == pytest.approx(math.sqrt(5.991) * 0.1, abs=1e-3)
    assert math.tan(angle) == pytest.approx(math.tan(0.5), abs=1e-3)
    assert covariance_ellipse(None) is None
    assert covariance_ellipse(np.full((3, 3), np.nan)) is None


def test_heartbeats_name_the_last_sequence_number(state) -> None:
    b = Broadcaster(state, now_s=Clock())
    viewer = b.add(None, "phone")  # type: ignore[arg-type]
    _drain(viewer)
    b.heartbeat()
    (text,) = _drain(viewer)
    assert json.loads(text) == {"type": "heartbeat", "seq": b.seq}


def test_a_trajectory_rewritten_in_place_sends_only_the_new_points(state) -> None:
    b = Broadcaster(state, now_s=Clock())
    viewer = b.add(None, "phone")  # type: ignore[arg-type]
    state.trajectory.extend([(0.0, 0.0), (0.1, 0.0)])
    b.tick()
    _drain(viewer)
    # SLAM copies its trajectory into a new deque (new tuple objects), one point longer
    state.trajectory = deque([(0.0, 0.0), (0.1, 0.0), (0.2, 0.0)])
    b.tick()
    (packet,) = _drain(viewer)
    status = decode_packet(packet).status
    assert status["trail+"] == [0.2, 0.0] and "trail" not in status
