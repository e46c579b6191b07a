"""SE(2) helpers: composition, inverse and relative pose agree with homogeneous matrices, and
points move between frames as poses do."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mazebot.geometry import compose, inverse, relative_pose, transform_points, wrap_angle


def _matrix(pose: np.ndarray) -> np.ndarray:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.array([[c, -s, pose[0]], [s, c, pose[1]], [0.0, 0.0, 1.0]])


def _pose(matrix: np.ndarray) -> np.ndarray:
    return np.array([matrix[0, 2], matrix[1, 2], math.atan2(matrix[1, 0], matrix[0, 0])])


POSES = np.random.default_rng(7).uniform([-3, -3, -math.pi], [3, 3, math.pi], size=(20, 3))


@pytest.mark.parametrize("k", range(0, 20, 2))
def test_compose_inverse_and_relative_pose_are_the_matrix_products(k: int) -> None:
    a, b = POSES[k], POSES[k + 1]
    np.testing.assert_allclose(compose(a, b), _pose(_matrix(a) @ _matrix(b)), atol=1e-12)
    np.testing.assert_allclose(inverse(a), _pose(np.linalg.inv(_matrix(a))), atol=1e-12)
    np.testing.assert_allclose(relative_pose(a, b), _pose(np.linalg.inv(_matrix(a)) @ _matrix(b)), atol=1e-12)
    np.testing.assert_allclose(compose(a, relative_pose(a, b)), b, atol=1e-12)


def test_the_helpers_broadcast_over_stacks_of_poses() -> None:
    got = relative_pose(POSES[0], POSES)
    for pose, rel in zip(POSES, got, strict=True):
        np.testing.assert_allclose(rel, relative_pose(POSES[0], pose), atol=1e-12)


def test_points_move_between_frames_as_poses_do() -> None:
    points = np.random.default_rng(8).uniform(-2, 2, size=(50, 2))
    for pose in POSES[:5]:
        moved = transform_points(pose, points)
        as_poses = compose(pose, np.column_stack((points, np.zeros(len(points)))))[:, :2]
        np.testing.assert_allclose(moved, as_poses, atol=1e-12)


def test_headings_wrap_to_minus_pi_inclusive_pi_exclusive() -> None:
    np.testing.assert_allclose(wrap_angle([math.pi, -math.pi, 3 * math.pi / 2, 0.5]),
                               [-math.pi, -math.pi, -math.pi / 2, 0.5])
