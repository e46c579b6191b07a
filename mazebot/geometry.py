"""Rigid motions of the plane, SE(2): poses ``(x_m, y_m, theta_rad)`` and the points they carry.

One module for the whole robot: the SLAM, the planner and the tools compose, invert and
compare poses and move scan points between frames with these functions only, so every
heading is wrapped the same way (to [-π, π)) and a frame convention is written once.

A pose ``a`` is the frame of a child (the robot, a keyframe, the lidar) in its parent (the
map, the odometry frame): ``compose(a, b)`` is ``b`` (given in ``a``'s frame) in ``a``'s
parent, ``v2t(a) · v2t(b)`` in homogeneous matrices (Grisetti et al., "A Tutorial on
Graph-Based SLAM", 2010, section III).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

TWO_PI = 2.0 * np.pi


def wrap_angle(angle_rad: npt.ArrayLike) -> FloatArray:
    """Wrap angles to [-π, π) radians, element-wise.

    Residual angles must be wrapped, or a heading error of +179° vs -179° would look like
    358° instead of 2°.
    """
    return np.remainder(np.asarray(angle_rad, dtype=np.float64) + np.pi, TWO_PI) - np.pi


def compose(a: npt.ArrayLike, b: npt.ArrayLike) -> FloatArray:
    """Pose composition ``a ⊕ b`` on (..., 3) arrays of (x_m, y_m, theta_rad); broadcasts.

    ``b`` is expressed in the frame of ``a``; the result is in ``a``'s parent frame:
    ``v2t(a) · v2t(b)`` in homogeneous matrices.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    cos_a = np.cos(a[..., 2])
    sin_a = np.sin(a[..., 2])
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.float64)
    out[..., 0] = a[..., 0] + cos_a * b[..., 0] - sin_a * b[..., 1]
    out[..., 1] = a[..., 1] + sin_a * b[..., 0] + cos_a * b[..., 1]
    out[..., 2] = wrap_angle(a[..., 2] + b[..., 2])
    return out


def inverse(a: npt.ArrayLike) -> FloatArray:
    """Pose inverse ``a⁻¹`` on (..., 3) arrays, so that ``compose(a, inverse(a)) == 0``."""
    a = np.asarray(a, dtype=np.float64)
    cos_a = np.cos(a[..., 2])
    sin_a = np.sin(a[..., 2])
    out = np.empty_like(a)
    out[..., 0] = -cos_a * a[..., 0] - sin_a * a[..., 1]
    out[..., 1] = sin_a * a[..., 0] - cos_a * a[..., 1]
    out[..., 2] = wrap_angle(-a[..., 2])
    return out


def relative_pose(a: npt.ArrayLike, b: npt.ArrayLike) -> FloatArray:
    """Pose of ``b`` seen from ``a``: ``a⁻¹ ⊕ b`` on (..., 3) arrays; broadcasts.

    This is the measurement model of a pose-graph edge: ``ẑ_ij = relative_pose(x_i, x_j)``.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    cos_a = np.cos(a[..., 2])
    sin_a = np.sin(a[..., 2])
    dx = b[..., 0] - a[..., 0]
    dy = b[..., 1] - a[..., 1]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.float64)
    out[..., 0] = cos_a * dx + sin_a * dy
    out[..., 1] = -sin_a * dx + cos_a * dy
    out[..., 2] = wrap_angle(b[..., 2] - a[..., 2])
    return out


def transform_points(pose: npt.ArrayLike, points_xy: npt.ArrayLike) -> FloatArray:
    """Points (N, 2) from the frame at ``pose`` (x_m, y_m, theta_rad) into its parent frame."""
    x_m, y_m, theta_rad = (float(v) for v in np.asarray(pose, dtype=np.float64)[:3])
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    p = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    return np.column_stack((c * p[:, 0] - s * p[:, 1] + x_m, s * p[:, 0] + c * p[:, 1] + y_m))

