"""Keyframes in int16 quarter millimetres: half the memory of float32, a rounding below the lidar's noise."""

from __future__ import annotations

import numpy as np
import pytest

from mazebot.slam.keyframes import NORMAL_STEP, POINT_STEP_M, Keyframe, pack, unpack, unpack_all


def _corridor(n: int = 400, seed: int = 3) -> np.ndarray:
    """Hits (n, 2) on two walls of a corridor 0.15 m either side, 1 % range noise, seen from the origin."""
    rng = np.random.default_rng(seed)
    x = np.linspace(-1.0, 1.0, n // 2)
    left = np.column_stack((x, 0.15 + 0.0015 * rng.standard_normal(x.size)))
    right = np.column_stack((x, -0.15 + 0.0015 * rng.standard_normal(x.size)))
    return np.vstack((left, right))


def _wall_keyframe(hits: np.ndarray | None = None) -> Keyframe:
    hits = _corridor() if hits is None else hits
    rng = np.random.default_rng(5)
    return Keyframe(index=0, time_s=0.0, pose=np.zeros(3), hits=hits, match_points=hits[::4], sensor_xy=np.zeros(2),
                    ray_ends=hits, ray_hit=rng.random(hits.shape[0]) < 0.9, integrated_pose=np.zeros(3))


def test_points_round_to_a_quarter_millimetre() -> None:
    values = np.random.default_rng(1).uniform(-8.0, 8.0, size=(1000, 2))
    packed = pack(values, POINT_STEP_M)
    assert packed.dtype == np.int16
    assert np.max(np.abs(unpack(packed, POINT_STEP_M) - values)) <= POINT_STEP_M / 2 + 1e-12
    normals = np.column_stack((np.cos(values[:, 0]), np.sin(values[:, 0])))
    assert np.max(np.abs(unpack(pack(normals, NORMAL_STEP), NORMAL_STEP) - normals)) <= NORMAL_STEP / 2 + 1e-12


def test_points_beyond_int16_stay_float32() -> None:
    far = np.array([[9.0, 0.0], [0.5, -0.25]])
    packed = pack(far, POINT_STEP_M)
    assert packed.dtype == np.float32
    assert np.array_equal(unpack(packed, POINT_STEP_M), far.astype(np.float32).astype(np.float64))


def test_a_keyframe_holds_half_of_float32() -> None:
    kf = _wall_keyframe()
    kf.surface()
    float32_bytes = 4 * (2 * kf.hits.size + kf.match_points.size + kf.ray_ends.size + 2 * kf.points.size)
    float32_bytes += kf.ray_hit.size
    held = sum(a.nbytes for a in (kf._hits, kf._match, kf._ray_ends, kf._ray_hit_bits, *kf._surface))
    assert held <= 0.52 * float32_bytes
    assert not hasattr(kf, "__dict__")  # slots: no per-keyframe dictionary


def test_packing_keeps_a_walls_direction() -> None:
    """A wall along an axis is not pulled onto the storage grid: over ten noisy scans its direction
    is the float points' one, with no bias (a millimetre's grid pulled it by ~0.014° on average)."""
    diffs = []
    for seed in range(10):
        hits = _corridor(seed=seed)
        exact = _wall_keyframe(np.zeros((0, 2)))
        exact._hits = hits.astype(np.float32)  # the same hits unrounded (float32 is kept as it is)
        direction, strength, count = _wall_keyframe(hits).wall_direction()
        want, _, want_count = exact.wall_direction()
        assert count == want_count and strength > 0.9
        diffs.append(np.degrees(direction - want))
    assert abs(np.mean(diffs)) < 0.005
    assert np.max(np.abs(diffs)) < 0.02


def test_keep_surface_only_lets_go_of_the_hits() -> None:
    kf = _wall_keyframe()
    kf.keep_surface_only()  # no surface yet: the hits stay
    assert kf.hits.shape[0] == 400
    points, normals = kf.surface()
    kf.keep_surface_only()
    assert kf.hits.shape == (0, 2)
    again = kf.surface()
    assert np.array_equal(again[0], points) and np.array_equal(again[1], normals)
    assert kf.ray_hit.shape == (400,) and kf.match_points.shape == (100, 2)


def test_unpack_all_gives_the_values_of_each_part_unpacked_in_turn() -> None:
    near = pack(np.array([[0.5, -1.25], [7.9, 0.0]]), POINT_STEP_M)  # int16
    far = pack(np.array([[9.5, 0.1]]), POINT_STEP_M)  # beyond int16's reach: float32
    assert near.dtype == np.int16 and far.dtype == np.float32
    for parts in ([near, near], [near, far, near]):
        expected = np.concatenate([unpack(part, POINT_STEP_M) for part in parts])
        np.testing.assert_array_equal(unpack_all(parts, POINT_STEP_M), expected)


def _two_boards(near_m: float, near_deg: float, far_m: float, far_deg: float, half_m: float = 0.25) -> np.ndarray:
    """Hits (N, 2) of beams 1° apart from the origin on two boards along x, each ``half_m`` either side of x = 0:
    one ``near_m`` to the left turned ``near_deg``, one ``far_m`` to the right turned ``far_deg`` (no noise)."""
    hits = []
    for angle in np.radians(np.arange(-180.0, 180.0, 1.0)):
        d = np.array([np.cos(angle), np.sin(angle)])
        for offset, turn in ((near_m, near_deg), (-far_m, far_deg)):
            slope = np.tan(np.radians(turn))  # the board: y = offset + slope x
            denominator = d[1] - slope * d[0]
            if abs(denominator) < 1e-9:
                continue
            r = offset / denominator
            if r > 0 and abs(r * d[0]) <= half_m:
                hits.append(r * d)
    return np.array(hits)


def test_a_keyframe_s_faces_count_each_board_by_its_length_not_its_points() -> None:
    # Two boards of one length turned +0.7° and -0.7°, one 0.17 m from the lidar and one 0.5 m: the near one
    # gives about three times the points, and the normals' mean leans to its turn; the faces' mean by length
    # is the boards' mean (0°).
    kf = _wall_keyframe(_two_boards(0.17, 0.7, 0.5, -0.7))
    direction, strength, count = kf.wall_direction()
    assert strength > 0.9 and count > 100
    assert np.degrees(direction) > 0.2
    faces = kf.face_wall_direction()
    assert faces is not None and abs(np.degrees(faces)) < 0.05, np.degrees(faces)


def test_the_wall_prior_takes_the_faces_direction_when_asked() -> None:
    from dataclasses import replace

    from mazebot.slam.slam import SlamParams
    from mazebot.slam.wall_priors import wall_priors

    kf = _wall_keyframe(_two_boards(0.17, 0.7, 0.5, -0.7))
    by_face = kf.face_wall_direction()
    assert by_face is not None
    cases = ((SlamParams(), kf.wall_direction()[0]), (replace(SlamParams(), wall_prior_faces=True), by_face))
    for walls, expected in cases:
        priors, _ = wall_priors([kf, kf], np.zeros((2, 3)), 0.0, walls, None)
        assert priors is not None
        assert priors.z[0, 2] == pytest.approx(-expected, abs=1e-12)  # wall -> keyframe 1: theta - phi
