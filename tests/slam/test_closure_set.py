"""Loop closures verified as a set: pairwise consistency through the chain, and the set that agrees."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from mazebot.geometry import compose, relative_pose
from mazebot.slam.closure_set import (
    ACCEPTED_BY_SET,
    REFUSED_BY_SET,
    Chain,
    chain_segments,
    dominant_set,
    judge,
    pair_chi2,
)
from mazebot.slam.loop_closure import Candidate, LoopClosureParams, Verdict

PARAMS = LoopClosureParams(set_verify=True)
#: a sequential edge's std (m, m, rad) and a closure's
EDGE_STD = np.array([0.01, 0.01, 0.005])
CLOSURE_STD = np.array([0.03, 0.03, 0.01])


def _loop_truth(count: int = 80) -> np.ndarray:
    """Poses round a 6 m × 2 m loop: out along y = 0, back along y = 2 (keyframes 0-19 and 60-79 side by side)."""
    poses = []
    for k in range(count):
        if k < 40:
            poses.append([0.15 * k, 0.0, 0.0])
        else:
            poses.append([0.15 * (79 - k), 2.0, np.pi])
    return np.array(poses)


def _chain(truth: np.ndarray, rng: np.random.Generator) -> Chain:
    z = relative_pose(truth[:-1], truth[1:]) + rng.standard_normal((truth.shape[0] - 1, 3)) * EDGE_STD
    return Chain(z, np.tile(np.diag(EDGE_STD**2), (truth.shape[0] - 1, 1, 1)))


def _closure(truth: np.ndarray, old: int, new: int, rng: np.random.Generator, off=(0.0, 0.0, 0.0),
             accepted: bool = False) -> Verdict:
    z = compose(relative_pose(truth[old], truth[new]), np.asarray(off) + rng.standard_normal(3) * CLOSURE_STD)
    cand = Candidate(old, new, z.copy(), np.eye(3) * 0.01, 0.0)
    reason = "accepted" if accepted else "low inlier ratio"
    return Verdict(cand, accepted, reason, z, np.diag(1.0 / CLOSURE_STD**2), tentative=not accepted)


def test_a_chain_segment_and_its_covariance_match_a_monte_carlo_of_the_edges() -> None:
    rng = np.random.default_rng(0)
    truth = _loop_truth()
    chain = Chain(relative_pose(truth[:-1], truth[1:]), np.tile(np.diag(EDGE_STD**2), (truth.shape[0] - 1, 1, 1)))
    pose, cov = chain_segments(chain, np.array([30, 48]), np.array([48, 30]))
    np.testing.assert_allclose(pose[0], relative_pose(truth[30], truth[48]), atol=1e-9)
    np.testing.assert_allclose(pose[1], relative_pose(truth[48], truth[30]), atol=1e-9)
    samples = np.zeros((20000, 3))
    for k in range(30, 48):  # the true pose with each edge perturbed, in the frame of the segment's end
        samples = compose(samples, compose(chain.z[k], rng.standard_normal((20000, 3)) * EDGE_STD))
    err = relative_pose(np.broadcast_to(pose[0], samples.shape), samples)
    np.testing.assert_allclose(np.cov(err.T), cov[0], rtol=0.1, atol=1e-7)


def test_two_right_closures_agree_and_a_wrong_one_does_not() -> None:
    rng = np.random.default_rng(1)
    truth = _loop_truth()
    chain = _chain(truth, rng)
    right = [_closure(truth, 10 + d, 69 - d, rng) for d in range(4)]
    wrong = _closure(truth, 12, 67, rng, off=(0.4, 0.0, 0.0))
    chi2 = pair_chi2(chain, [right[0], right[0], right[1], right[0]], [right[1], right[2], right[3], wrong])
    assert np.all(chi2[:3] < 11.34)
    assert chi2[3] > 30.0


def test_right_closures_are_calibrated_over_many_pairs() -> None:
    """The chi² of pairs of right closures (independent noise, the stated covariances) has the median of
    3 degrees of freedom, 2.37, within sampling: the propagation is neither too sure nor too loose."""
    rng = np.random.default_rng(2)
    truth = _loop_truth()
    values = []
    for _ in range(200):
        chain = _chain(truth, rng)
        a, b = _closure(truth, 8, 71, rng), _closure(truth, 14, 65, rng)
        values.append(float(pair_chi2(chain, [a], [b])[0]))
    assert 1.9 < float(np.median(values)) < 2.9


def test_tentative_closures_that_agree_are_accepted_and_a_look_alike_among_them_is_refused() -> None:
    rng = np.random.default_rng(3)
    truth = _loop_truth()
    chain = _chain(truth, rng)
    member = _closure(truth, 9, 70, rng, accepted=True)
    waiting = [_closure(truth, 10 + d, 69 - d, rng) for d in range(3)]
    look_alike = _closure(truth, 14, 65, rng, off=(0.0, 0.4, 0.0), accepted=True)
    decision = judge([member], waiting, [look_alike], chain, PARAMS)
    assert sorted(v.candidate.new for v in decision.accepted) == [67, 68, 69]
    assert all(v.accepted and v.reason == ACCEPTED_BY_SET for v in decision.accepted)
    assert [(v.candidate.new, v.reason, v.accepted) for v in decision.refused] == [(65, REFUSED_BY_SET, False)]


def test_two_groups_that_each_agree_within_themselves_decide_nothing() -> None:
    """Identical corridors: one group of closures at the right offset, another as large one corridor over,
    each consistent within itself. The set does not stand out: no tentative closure is accepted."""
    rng = np.random.default_rng(4)
    truth = _loop_truth()
    chain = _chain(truth, rng)
    right = [_closure(truth, 10 + d, 69 - d, rng) for d in range(0, 8, 2)]
    wrong = [_closure(truth, 11 + d, 68 - d, rng, off=(0.3048, 0.0, 0.0)) for d in range(0, 8, 2)]
    decision = judge([], right + wrong, [], chain, PARAMS)
    assert decision.accepted == [] and decision.refused == []


def test_too_few_closures_or_closures_far_apart_decide_nothing() -> None:
    rng = np.random.default_rng(5)
    truth = _loop_truth()
    chain = _chain(truth, rng)
    pair = [_closure(truth, 10, 69, rng), _closure(truth, 11, 68, rng)]
    assert judge([], pair, [], chain, PARAMS).accepted == []
    # three that agree, but their ends 20 keyframes apart: a long chain cannot tell, so they are not compared
    apart = [_closure(truth, 2 + 20 * d, 77 - d, rng) for d in range(3)]
    assert judge([], apart, [], chain, replace(PARAMS, set_window_keyframes=10)).accepted == []


def test_the_dominant_set_and_its_confidence() -> None:
    a = np.zeros((5, 5))
    a[np.ix_([0, 1, 2], [0, 1, 2])] = 1.0
    np.fill_diagonal(a, 0.0)
    chosen, ratio = dominant_set(a)
    assert chosen.tolist() == [True, True, True, False, False]
    assert ratio == float("inf")  # no second set
    a[3, 4] = a[4, 3] = 1.0
    chosen, ratio = dominant_set(a)
    assert chosen.tolist() == [True, True, True, False, False]
    assert abs(ratio - 2.0) < 1e-9  # a group of three against a pair
