"""The literature's trajectory error metrics, next to the project's anchored one.

``mazebot slam run`` compares its trajectory with a log's corrected poses. Those poses
are another SLAM system's output in its own frame, so three figures say different
things:

- **anchored** (the headline, :func:`anchored_error`): pose by pose, both trajectories
  starting at the log's first pose. A map turned by 0.5° about the start shows up here
  as decimetres at the far end of a building, however consistent the map is in itself.
- **aligned ATE** (:func:`aligned_error`): the absolute trajectory error after the
  rigid SE(2) transform that best fits the whole estimate onto the reference (least
  squares on the positions, closed form: Horn, JOSA A 1987; Umeyama, PAMI 1991, without
  scale), as the TUM benchmark defines it (Sturm et al., "A benchmark for the evaluation
  of RGB-D SLAM systems", IROS 2012). It says how consistent the map is, whatever
  orientation the first scans gave it; it never replaces the anchored figure.
- **relative error** (:func:`relative_error`): Kümmerle et al., "On measuring the
  accuracy of SLAM algorithms" (Autonomous Robots 2009): for pairs of poses ``(i, j)``
  the relative displacement ``δ_ij = x_i⁻¹ x_j`` of the estimate against the
  reference's, ``ε = δ_ij ⊖ δ*_ij``, reported as the mean and standard deviation of its
  translational (m) and rotational (°) parts. Pairs here: every scan with the one
  ``lag`` scans later (1: consecutive scans, the local accuracy a robot navigates by).

All take trajectories ``(N, 3)`` of ``(x, y, θ)`` in one order, pose ``k`` of one
matching pose ``k`` of the other.
"""

from __future__ import annotations

import math

import numpy as np

from mazebot.geometry import compose, relative_pose, wrap_angle


def _as_trajectories(estimate: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    est = np.asarray(estimate, dtype=np.float64).reshape(-1, 3)
    ref = np.asarray(reference, dtype=np.float64).reshape(-1, 3)
    if est.shape != ref.shape or est.shape[0] == 0:
        raise ValueError(f"need two trajectories of the same, non-zero length, got {est.shape[0]} and {ref.shape[0]}")
    return est, ref


def anchored_error(estimate: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    """Position RMS / max (m) and heading RMS (°) of ``estimate − reference``, pose by pose, no alignment."""
    est, ref = _as_trajectories(estimate, reference)
    err = est - ref
    err[:, 2] = wrap_angle(err[:, 2])
    dist = np.hypot(err[:, 0], err[:, 1])
    return {
        "rms_m": round(float(np.sqrt(np.mean(dist**2))), 4),
        "max_m": round(float(dist.max()), 4),
        "heading_rms_deg": round(float(np.degrees(np.sqrt(np.mean(err[:, 2] ** 2)))), 3),
    }


def rigid_alignment(estimate: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """The SE(2) transform ``(x, y, θ)`` that best moves ``estimate``'s positions onto ``reference``'s.

    Least squares ``min Σ |R p_k + t − q_k|²`` in closed form (Umeyama 1991 without
    scale): with both point sets centred, ``θ = atan2(Σ p × q, Σ p · q)``, then
    ``t = q̄ − R p̄``.
    """
    est, ref = _as_trajectories(estimate, reference)
    p_mean, q_mean = est[:, :2].mean(axis=0), ref[:, :2].mean(axis=0)
    p, q = est[:, :2] - p_mean, ref[:, :2] - q_mean
    theta = math.atan2(float(np.sum(p[:, 0] * q[:, 1] - p[:, 1] * q[:, 0])), float(np.sum(p * q)))
    c, s = math.cos(theta), math.sin(theta)
    t = q_mean - np.array([c * p_mean[0] - s * p_mean[1], s * p_mean[0] + c * p_mean[1]])
    return np.array([t[0], t[1], theta])


def aligned_error(estimate: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    """:func:`anchored_error` after :func:`rigid_alignment`, plus the alignment's rotation (°) and shift (m)."""
    est, ref = _as_trajectories(estimate, reference)
    fit = rigid_alignment(est, ref)
    moved = compose(fit, est).reshape(-1, 3)
    out = anchored_error(moved, ref)
    out["rotation_deg"] = round(math.degrees(float(fit[2])), 3)
    out["shift_m"] = round(math.hypot(float(fit[0]), float(fit[1])), 4)
    return out


def relative_error(estimate: np.ndarray, reference: np.ndarray, lag: int = 1) -> dict[str, float]:
    """Kümmerle et al.'s relative displacement error over the pairs ``(k, k + lag)``.

    Returns the mean and standard deviation of the translational (m) and rotational (°)
    error and the number of pairs; NaN figures if the trajectories are shorter than ``lag + 1``.
    """
    est, ref = _as_trajectories(estimate, reference)
    if lag < 1:
        raise ValueError(f"lag must be at least 1, got {lag}")
    n = est.shape[0] - lag
    if n <= 0:
        nan = float("nan")
        return {"trans_mean_m": nan, "trans_std_m": nan, "rot_mean_deg": nan, "rot_std_deg": nan, "pairs": 0}
    d_est = relative_pose(est[:-lag], est[lag:]).reshape(-1, 3)
    d_ref = relative_pose(ref[:-lag], ref[lag:]).reshape(-1, 3)
    eps = relative_pose(d_ref, d_est).reshape(-1, 3)  # δ* ⁻¹ δ: the estimate's displacement seen from the truth's
    trans = np.hypot(eps[:, 0], eps[:, 1])
    rot = np.degrees(np.abs(wrap_angle(eps[:, 2])))
    return {
        "trans_mean_m": round(float(trans.mean()), 4),
        "trans_std_m": round(float(trans.std()), 4),
        "rot_mean_deg": round(float(rot.mean()), 3),
        "rot_std_deg": round(float(rot.std()), 3),
        "pairs": int(n),
    }
