"""The trajectory metrics against trajectories whose errors are known by construction."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mazebot.geometry import compose, wrap_angle
from mazebot.slam.trajectory_metrics import aligned_error, anchored_error, relative_error, rigid_alignment


def _loop(n: int = 200) -> np.ndarray:
    """A reference: a 10 m × 4 m rectangle-ish loop with headings along the path."""
    t = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    x, y = 5.0 * np.cos(t), 2.0 * np.sin(t)
    th = np.arctan2(np.gradient(y), np.gradient(x))
    return np.column_stack((x, y, th))


def test_rigid_motion_of_the_whole_trajectory_is_aligned_away_but_not_in_the_headline() -> None:
    ref = _loop()
    motion = np.array([0.3, -0.2, math.radians(0.7)])
    est = compose(motion, ref)
    fit = rigid_alignment(est, ref)
    # the fit undoes the motion exactly
    back = compose(fit, est)
    assert np.allclose(back[:, :2], ref[:, :2], atol=1e-9)
    assert np.allclose(wrap_angle(back[:, 2] - ref[:, 2]), 0.0, atol=1e-9)
    aligned = aligned_error(est, ref)
    assert aligned["rms_m"] < 1e-6 and aligned["heading_rms_deg"] < 1e-6
    assert aligned["rotation_deg"] == pytest.approx(-0.7, abs=1e-3)
    headline = anchored_error(est, ref)
    assert headline["rms_m"] > 0.3  # the shift alone is 0.36 m
    # a rigid motion leaves every relative displacement as it was
    rel = relative_error(est, ref)
    assert rel["trans_mean_m"] < 1e-9 and rel["rot_mean_deg"] < 1e-9 and rel["pairs"] == len(ref) - 1


def test_relative_error_measures_each_increment() -> None:
    ref = np.column_stack((np.arange(11.0), np.zeros(11), np.zeros(11)))
    est = ref.copy()
    est[5:, 0] += 0.1  # one increment 10 cm too long: one pair wrong by 0.1 m
    rel = relative_error(est, ref)
    assert rel["pairs"] == 10
    assert rel["trans_mean_m"] == pytest.approx(0.01)
    assert anchored_error(est, ref)["max_m"] == pytest.approx(0.1)
    turned = ref.copy()
    turned[3:, 2] += math.radians(2.0)  # a heading error swings every later displacement
    rel_turned = relative_error(turned, ref)
    assert rel_turned["rot_mean_deg"] == pytest.approx(0.2, abs=1e-6)


def test_bad_input_is_refused() -> None:
    with pytest.raises(ValueError, match="same"):
        aligned_error(np.zeros((3, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="lag"):
        relative_error(np.zeros((3, 3)), np.zeros((3, 3)), lag=0)
    assert relative_error(np.zeros((1, 3)), np.zeros((1, 3)))["pairs"] == 0
