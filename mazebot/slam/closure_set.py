"""Loop closures verified as a set: closures that agree with each other, and a look-alike that does not.

:func:`mazebot.slam.loop_closure.verify` judges each candidate alone, by hard thresholds on
its match (inlier ratio, residual). On a building's laser log about half the closures it
refuses are right (ICP ended within 0.1 m and 1° of the reference's relative pose: branch
``reallogs4``), mostly just under the inlier ratio (0.51 median against 0.6) or just over
the residual limit: a doorway, furniture, a corridor seen from its other end. A wrong
closure, on the other hand, can pass every threshold where two places look alike.

What tells them apart is agreement. Two closures ``a`` (keyframe ``i_a`` sees ``j_a``,
measured ``z_a``) and ``b`` close one loop with the chain of sequential edges between their
old ends and between their new ends:

    z_a ⊕ c(j_a → j_b)  =  c(i_a → i_b) ⊕ z_b

(``c`` a chain of sequential measurements). Two right closures satisfy it within their
uncertainty; a wrong one and a right one do not, unless the chain is so uncertain that it
cannot tell (which is why only pairs whose ends lie within ``set_window_keyframes`` of each
other are compared: a short chain is sure). The loop's residual and its covariance
(first-order propagation through the compositions, :func:`pair_chi2`) give a chi² of 3
degrees of freedom per pair, the pairwise consistency of Olson, "Recognizing places using
spectrally clustered local matches" (RAS 2009), and his single-cluster graph partitioning
(SCGP): the pairs form an affinity matrix ``A``; its dominant eigenvector is the set that
agrees most, and the ratio of its two largest eigenvalues says whether that set stands out
from any other set that agrees within itself (two groups of look-alikes, each consistent,
give a ratio near 1: nothing is decided). Olson weighs each pair by its likelihood; here
``A`` is 1 where the pair agrees (``χ² ≤ gate_chi2``) and 0 elsewhere (not comparable, or
on the diagonal), so that two groups of look-alikes equally consistent within themselves
tie whatever the noise of their residuals, and a group of ``n`` that all agree has ``λ₁ =
n − 1``. The method and the confidence test are Olson's; the hypotheses, the windows and
what is done with the result are this module's:

- a **tentative** closure (it passed every test of the chain, the degeneracy and the
  ambiguity, but its match fell short of a quality threshold by less than the set's margin,
  ``set_fitness_ratio`` / ``set_rmse_ratio``) is accepted when it belongs to the dominant
  set, that set has ``set_min_size`` members, stands out by ``set_confidence``, and the
  closure agrees (``χ² ≤ gate_chi2``) with at least ``set_min_size − 1`` of them;
- a closure accepted by the thresholds in this same job (not yet in the pose graph) is
  refused when such a set stands without it and it disagrees with most of the set's
  members it is compared with: a look-alike that fits locally but not with the others.

Closures already in the pose graph count as members (support) but are not judged again
(the robust optimization of :mod:`mazebot.slam.robust_closures` still weighs them).
Latif, Cadena & Neira's RRR (IJRR 2013) judges clusters of closures by the optimized
graph's residuals instead; the pairwise test needs no optimization per hypothesis.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from mazebot.geometry import compose, inverse, relative_pose, wrap_angle
from mazebot.slam.loop_closure import LoopClosureParams, Verdict

#: the reason of a closure accepted by the thresholds and refused by the set
REFUSED_BY_SET = "inconsistent with the set"
#: the reason of a tentative closure the set accepted
ACCEPTED_BY_SET = "accepted as a set"


@dataclass(frozen=True)
class Chain:
    """The sequential edges ``k → k + 1``: measurements (K, 3) and covariances (K, 3, 3) in their ends' frames."""

    z: np.ndarray
    covariance: np.ndarray

    @classmethod
    def from_edges(cls, edges: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], count: int) -> Chain:
        """The chain of ``count`` keyframes from a pose graph's edges ``(i, j, z, Ω)`` (other edges ignored)."""
        ei, ej, z, omega = edges
        ei, ej = np.asarray(ei, dtype=np.intp), np.asarray(ej, dtype=np.intp)
        seq = (ej == ei + 1) & (ej < count)
        meas = np.zeros((max(count - 1, 0), 3))
        cov = np.tile(np.eye(3), (max(count - 1, 0), 1, 1))
        k = ei[seq]
        meas[k] = np.asarray(z)[seq]
        cov[k] = np.linalg.pinv(np.asarray(omega)[seq], hermitian=True)
        return cls(meas, cov)


def end_jacobian(b: np.ndarray) -> np.ndarray:
    """``M(b)`` (N, 3, 3): a perturbation ``δ`` of ``a`` moves ``a ⊕ b`` by ``M(b) δ`` in the frame of its end.

    First order of ``b⁻¹ ⊕ δ ⊕ b``: the position error turned into ``b``'s axes, and a
    heading error swinging ``b``'s translation by its lever arm.
    """
    b = np.atleast_2d(np.asarray(b, dtype=np.float64))
    c, s = np.cos(b[:, 2]), np.sin(b[:, 2])
    m = np.zeros((b.shape[0], 3, 3))
    m[:, 0, 0], m[:, 0, 1], m[:, 1, 0], m[:, 1, 1] = c, s, -s, c
    m[:, 0, 2] = -c * b[:, 1] + s * b[:, 0]
    m[:, 1, 2] = s * b[:, 1] + c * b[:, 0]
    m[:, 2, 2] = 1.0
    return m


def _sandwich(m: np.ndarray, cov: np.ndarray) -> np.ndarray:
    return np.einsum("nij,njk,nlk->nil", m, cov, m)


def chain_segments(chain: Chain, starts: np.ndarray, ends: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Relative poses (S, 3) of keyframe ``ends`` seen from ``starts`` along the chain, and their covariances.

    Composed edge by edge (all segments at once, one step per edge of the longest);
    a segment that runs backwards is the inverse of the forward one.
    """
    starts, ends = np.asarray(starts, dtype=np.intp), np.asarray(ends, dtype=np.intp)
    lo, hi = np.minimum(starts, ends), np.maximum(starts, ends)
    count = starts.size
    pose = np.zeros((count, 3))
    cov = np.zeros((count, 3, 3))
    for step in range(int((hi - lo).max(initial=0))):
        active = lo + step < hi
        k = np.where(active, lo + step, 0)
        inc = chain.z[k]
        moved = compose(pose, inc)
        grown = _sandwich(end_jacobian(inc), cov) + chain.covariance[k]
        pose = np.where(active[:, None], moved, pose)
        cov = np.where(active[:, None, None], grown, cov)
    back = starts > ends
    if back.any():
        inv = inverse(pose[back])
        cov[back] = _sandwich(end_jacobian(inv), cov[back])
        pose[back] = inv
    return pose, cov


def pair_chi2(chain: Chain, a: list[Verdict], b: list[Verdict]) -> np.ndarray:
    """χ² (P,) of the loop each pair ``(a[p], b[p])`` of closures closes with the chain between their ends.

    ``z_a ⊕ c(j_a → j_b)`` against ``c(i_a → i_b) ⊕ z_b``, every part with its covariance
    (a closure's from its information, in its end's frame as the pose graph holds it).
    """
    if not a:
        return np.zeros(0)
    ia = np.array([v.candidate.old for v in a])
    ja = np.array([v.candidate.new for v in a])
    ib = np.array([v.candidate.old for v in b])
    jb = np.array([v.candidate.new for v in b])
    za = np.array([v.measurement for v in a])
    zb = np.array([v.measurement for v in b])
    cov_a = np.linalg.pinv(np.array([v.information for v in a]), hermitian=True)
    cov_b = np.linalg.pinv(np.array([v.information for v in b]), hermitian=True)
    cj, cov_cj = chain_segments(chain, ja, jb)
    ci, cov_ci = chain_segments(chain, ia, ib)
    p1 = compose(za, cj)
    cov1 = _sandwich(end_jacobian(cj), cov_a) + cov_cj
    p2 = compose(ci, zb)
    cov2 = _sandwich(end_jacobian(zb), cov_ci) + cov_b
    # e = p2⁻¹ ⊕ p1: p2's error, inverted and carried to the loop's end, and p1's
    inv2 = inverse(p2)
    cov_inv2 = _sandwich(end_jacobian(inv2), cov2)
    e = relative_pose(p2, p1)
    e[:, 2] = wrap_angle(e[:, 2])
    cov_e = _sandwich(end_jacobian(p1), cov_inv2) + cov1
    return np.einsum("ni,ni->n", e, np.linalg.solve(cov_e, e[:, :, None])[:, :, 0])


def comparable(a: Verdict, b: Verdict, window: int) -> bool:
    """Two closures a short chain links: both ends within ``window`` keyframes, and two different scans."""
    ca, cb = a.candidate, b.candidate
    return ca.new != cb.new and abs(ca.new - cb.new) <= window and abs(ca.old - cb.old) <= window


@dataclass(frozen=True)
class SetDecision:
    """What :func:`judge` decided: tentative closures accepted, new closures refused (both as verdicts)."""

    accepted: list[Verdict]
    refused: list[Verdict]


def judge(
    members: list[Verdict], tentative: list[Verdict], new: list[Verdict], chain: Chain, params: LoopClosureParams
) -> SetDecision:
    """The module docstring's decision on ``tentative`` and ``new`` closures, ``members`` supporting only.

    ``members``: closures in the pose graph already; ``tentative``: closures waiting for
    support; ``new``: closures accepted by the thresholds in this job.
    """
    hyp = members + tentative + new
    n = len(hyp)
    if n < params.set_min_size or not (tentative or new):
        return SetDecision([], [])
    window = params.set_window_keyframes
    pairs = [(a, b) for a in range(n) for b in range(a + 1, n) if comparable(hyp[a], hyp[b], window)]
    chi2 = np.full((n, n), np.inf)
    if pairs:
        values = pair_chi2(chain, [hyp[a] for a, _ in pairs], [hyp[b] for _, b in pairs])
        for (a, b), value in zip(pairs, values, strict=True):
            chi2[a, b] = chi2[b, a] = value
    agree = chi2 <= params.gate_chi2
    affinity = agree.astype(np.float64)
    group = np.zeros(n, dtype=bool)
    for component in _components(np.isfinite(chi2)):
        if component.size < params.set_min_size:
            continue
        chosen, ratio = dominant_set(affinity[np.ix_(component, component)])
        members_ = component[chosen]
        # only members that agree with enough of the others: a set of near-zero affinities is no set
        inner = agree[np.ix_(members_, members_)].sum(axis=1)
        members_ = members_[inner >= params.set_min_size - 1]
        if members_.size >= params.set_min_size and ratio >= params.set_confidence:
            group[members_] = True
    first_tentative, first_new = len(members), len(members) + len(tentative)
    accepted = []
    for k in range(first_tentative, first_new):
        support = int(np.sum(agree[k] & group))
        if group[k] and support >= params.set_min_size - 1:
            v = hyp[k]
            accepted.append(replace(v, accepted=True, reason=ACCEPTED_BY_SET,
                                    detail=f"{v.reason} ({v.detail}); agrees with {support} closures"))
    refused = []
    for k in range(first_new, n):
        if group[k]:
            continue
        compared = group & np.isfinite(chi2[k])
        disagree = int(np.sum(compared & ~agree[k]))
        if compared.sum() >= params.set_min_size and 2 * disagree > int(compared.sum()):
            v = hyp[k]
            refused.append(replace(v, accepted=False, reason=REFUSED_BY_SET, information=np.zeros((3, 3)),
                                   detail=f"disagrees with {disagree} of {int(compared.sum())} closures that agree"))
    return SetDecision(accepted, refused)


def dominant_set(affinity: np.ndarray) -> tuple[np.ndarray, float]:
    """Olson's single-cluster partition of a symmetric affinity matrix: the set, and its confidence.

    The dominant eigenvector ``v`` (non-negative) ranks the hypotheses; the set is the
    top ``k`` of that ranking with the largest ``uᵀAu / uᵀu`` (``u`` its indicator); the
    confidence is ``λ₁ / λ₂``, the two largest eigenvalues (infinite when ``λ₂ ≤ 0``: no
    second set agrees within itself).
    """
    n = affinity.shape[0]
    if n == 0:
        return np.zeros(0, dtype=bool), 0.0
    values, vectors = np.linalg.eigh(affinity)
    lead = np.abs(vectors[:, -1])
    order = np.argsort(-lead, kind="stable")
    ranked = affinity[np.ix_(order, order)]
    sums = np.cumsum(np.cumsum(ranked, axis=0), axis=1).diagonal()  # uᵀAu of each top-k indicator
    k = int(np.argmax(sums / np.arange(1, n + 1))) + 1
    chosen = np.zeros(n, dtype=bool)
    chosen[order[:k]] = True
    second = float(values[-2]) if n > 1 else 0.0
    ratio = float(values[-1]) / second if second > 1e-12 else float("inf")
    return chosen, ratio


def _components(linked: np.ndarray) -> list[np.ndarray]:
    """Connected components (index arrays) of a symmetric boolean adjacency."""
    n = linked.shape[0]
    seen = np.zeros(n, dtype=bool)
    out = []
    for start in range(n):
        if seen[start]:
            continue
        stack, members = [start], []
        seen[start] = True
        while stack:
            k = stack.pop()
            members.append(k)
            for m in np.flatnonzero(linked[k] & ~seen):
                seen[m] = True
                stack.append(int(m))
        out.append(np.array(sorted(members), dtype=np.intp))
    return out
