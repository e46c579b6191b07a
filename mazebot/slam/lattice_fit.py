"""The maze's lattice measured from the walls seen: its pitch, where its lines lie, whether it fits.

A maze built by hand is not the lattice of the configured cell size: the pitch is off
by a few per cent (a 0.29 m or 0.32 m maze configured as 1 ft), and a lattice of the
wrong pitch puts the far walls cells away from its lines. So the pitch is measured, in
two steps, from wall positions along the two grid axes (``u`` for walls whose normal
is along u, ``v`` likewise), the grid's direction being known:

1. **Periodogram.** The positions are binned (a histogram per axis), and for every
   candidate pitch ``p`` within ``search`` of the nominal one the magnitudes of the
   Fourier coefficients ``|Σ h(x) e^{2πi x / p}|`` of both axes are summed: lines that
   lie on a lattice of pitch ``p`` add in phase. This is the projection-profile /
   spectral method of estimating a grid's period (e.g. the "periodogram" of Lomb and
   Scargle for unevenly sampled data; here the samples are wall positions).
2. **Least squares.** Each position within ``tolerance_m`` of a line of the best
   candidate is assigned that line's index ``k``; ``x = φ_class + k p`` is solved for the
   pitch and every class's phase together (weighted), twice.

Each kind of face is a class of its own, with its own phase (:func:`fit_pitch`).

Whether the walls fit a lattice at all: the pitch is *measured* once one axis has
walls on at least ``min_lines`` distinct lines (two lines fit any pitch: a room's
opposite walls are no evidence of a lattice), and the lattice *fits* when both axes
have, and at least ``min_fit`` of the wall weight lies within ``tolerance_m`` of a line. Callers switch their
lattice priors off when it does not (:mod:`mazebot.slam.wall_lattice`,
:mod:`mazebot.planner.maze_graph`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: The periodogram's first pass steps this many fine steps at a time.
COARSE_STEPS = 5

#: A lattice line closer than this share of a cell to a boundary of an occupancy grid's cells
#: moves the cells (:func:`cell_offset_on_lattice`). Set between what was seen on 2 cm cells:
#: lines 0-1.4 mm off a boundary (a 0.32 m maze) painted every 12 mm board two cells thick,
#: and centring them took the maps from 94 % to 99.9 % of the free space; lines 4.9 mm off
#: (a 0.29 m maze) were better left (centred, boards whose map positions scatter by a few
#: millimetres spilled into both neighbours: 99.7 % fell to 98.2 %).
BOUNDARY_CELLS = 0.2


@dataclass(frozen=True)
class PitchFit:
    """A lattice fitted to wall positions (metres, along the grid's u and v axes).

    ``pitch_m`` the spacing of the lines (the nominal one when no axis measures it);
    ``phase_m`` where the lines lie along u and v, modulo the pitch; ``fit`` the share of
    the wall weight within the tolerance of a line; ``lines`` how many distinct lines
    have walls on them, per axis; ``measured`` enough lines on one axis to measure the
    pitch; ``fits`` enough lines on both and ``fit`` at least the minimum; ``line_rms_m``
    how far each line's walls lie off the fitted lattice, the RMS over lines: a few tenths
    of a millimetre on a perfect lattice, several millimetres on a maze built by hand.
    """

    pitch_m: float
    phase_m: tuple[float, float]
    fit: float
    lines: tuple[int, int]
    measured: bool
    fits: bool
    line_rms_m: float = 0.0  # how far the lines' walls lie off the lattice (RMS of each line's mean offset)


def fit_pitch(
    classes: list[tuple[np.ndarray, np.ndarray, int]],
    nominal_m: float,
    search: float = 0.05,
    tolerance_m: float = 0.015,
    min_lines: int = 3,
    min_line_weight: float = 5.0,
    min_line_share: float = 0.03,
    min_fit: float = 0.8,
    bin_m: float = 0.002,
    step_m: float = 0.0002,
) -> PitchFit:
    """The lattice (module docstring) of wall positions near pitch ``nominal_m``.

    ``classes`` are ``(positions_m, weights, axis)``: wall positions along axis 0 (u) or 1
    (v) of the grid, one class per kind of face with its own phase. A face seen from its
    ``+u`` side lies half a wall thickness above its line, one seen from ``−u`` half below:
    pooled, the walls east of a robot (seen from the west) and those west of it would pull
    the pitch short by a wall thickness over the span. ``search`` is the largest relative
    difference from ``nominal_m`` looked at (0: the pitch is taken as given and only the
    phases, the fit and the lines are measured). A line counts when at least
    ``min_line_weight`` and ``min_line_share`` of its class's weight lie on it (the few
    points of a post's or a leg's round side are no wall); an axis's lines are those of
    its class that has most.
    """
    hists = [(*_histogram(np.asarray(x, float).ravel(), np.asarray(w, float).ravel(), bin_m), int(axis))
             for x, w, axis in classes]
    total = sum(float(h.sum()) for _, h, _ in hists)
    if total <= 0:
        return PitchFit(nominal_m, (0.0, 0.0), 0.0, (0, 0), False, False)
    pitch = nominal_m
    if search > 0:
        # coarse then fine: the peak is p^2 / 2L wide (9 mm for walls spread over 5 m), so steps of
        # COARSE_STEPS fine steps find it, and the fine steps around it place it
        lo, hi = nominal_m * (1.0 - search), nominal_m * (1.0 + search)
        coarse = _periodogram(hists, np.linspace(lo, hi, max(3, math.ceil((hi - lo) / (COARSE_STEPS * step_m)) + 1)))
        centre = coarse[0][int(np.argmax(coarse[1]))]
        span = COARSE_STEPS * step_m
        candidates, score = _periodogram(hists, np.linspace(max(lo, centre - span), min(hi, centre + span),
                                                              2 * COARSE_STEPS + 1))
        best = int(np.argmax(score))
        pitch = float(candidates[best])
        if 0 < best < len(candidates) - 1:  # parabola through the peak and its neighbours
            a, b, c = score[best - 1], score[best], score[best + 1]
            denom = a - 2 * b + c
            if denom < 0:
                pitch += float(0.5 * (a - c) / denom) * float(candidates[1] - candidates[0])
    pairs = [(x, h) for x, h, _ in hists]
    phases = [_phase(x, h, pitch) for x, h in pairs]
    if search > 0:
        for _ in range(2):
            pitch, phases = _least_squares(pairs, pitch, phases, tolerance_m)
        pitch = float(np.clip(pitch, nominal_m * (1 - search), nominal_m * (1 + search)))
    inside = 0.0
    lines = [0, 0]
    line_sq = line_weight = 0.0  # where each line's walls lie off the lattice, squared, weighted
    axis_phase: list[list[tuple[float, float]]] = [[], []]
    for (x, h, axis), phase in zip(hists, phases, strict=True):
        if not h.size:
            continue
        k = np.round((x - phase) / pitch)
        near = np.abs(x - phase - k * pitch) <= tolerance_m
        inside += float(h[near].sum())
        per_line: dict[int, float] = {}
        off_line: dict[int, float] = {}
        residual = (x - phase - k * pitch)[near]
        for kk, hh, rr in zip(k[near].astype(int).tolist(), h[near].tolist(), residual.tolist(), strict=True):
            per_line[kk] = per_line.get(kk, 0.0) + hh
            off_line[kk] = off_line.get(kk, 0.0) + hh * rr
        for kk, weight in per_line.items():
            line_sq += (off_line[kk] / weight) ** 2 * weight
            line_weight += weight
        least = max(min_line_weight, min_line_share * float(h.sum()))
        lines[axis] = max(lines[axis], sum(1 for weight in per_line.values() if weight >= least))
        axis_phase[axis].append((phase, float(h.sum())))
    fit = inside / total
    measured = max(lines) >= min_lines
    wrapped = tuple(_mean_phase(items, pitch) for items in axis_phase)
    return PitchFit(float(pitch), (wrapped[0], wrapped[1]), fit, (lines[0], lines[1]), measured,
                    min(lines) >= min_lines and fit >= min_fit, math.sqrt(line_sq / max(line_weight, 1e-300)))


def _mean_phase(items: list[tuple[float, float]], pitch_m: float) -> float:
    """The circular mean of the classes' phases of one axis (where its walls' centre lines lie).

    Each class that saw faces counts once, however many points it has: the faces seen from
    +u lie half a board above the centre line, those seen from -u half below, and a mean
    weighted by their points would lean towards the side seen more (up to half a board).
    """
    z = sum(np.exp(2j * np.pi * phase / pitch_m) for phase, w in items if w > 0) if items else 0.0
    return float(np.remainder(np.angle(z) / (2 * np.pi) * pitch_m, pitch_m)) if abs(z) > 0 else 0.0


def _periodogram(
    hists: list[tuple[np.ndarray, np.ndarray, int]], candidates: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(candidates, score)``: the summed magnitudes of every class's Fourier coefficient at each pitch."""
    score = np.zeros(candidates.size)
    for x, h, _ in hists:
        if h.size:
            score += np.abs(np.exp(2j * np.pi * x[None, :] / candidates[:, None]) @ h)
    return candidates, score


#: Bins a histogram may span beyond four per position before the occupied ones are found by sorting
#: (a maze's walls span a few thousand 2 mm bins; a building's tens of thousands).
DENSE_BINS = 65_536


def _histogram(x: np.ndarray, w: np.ndarray, bin_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Bin centres and weights of the occupied bins (positions to ``bin_m``: the sums stay small)."""
    if x.size == 0:
        return np.zeros(0), np.zeros(0)
    index = np.floor(x / bin_m).astype(np.int64)
    low = int(index.min())
    span = int(index.max()) - low + 1
    if span <= 4 * index.size + DENSE_BINS:
        # positions a few metres across: count into every bin of the span (no sort); the same sums, each
        # bin's weights added in the order given, and the same occupied bins in the same order
        weight = np.bincount(index - low, weights=w, minlength=span)
        keys = np.arange(low, low + span, dtype=np.int64)
    else:
        keys, inverse = np.unique(index, return_inverse=True)
        weight = np.bincount(inverse, weights=w, minlength=keys.size)
    keep = weight > 0
    return (keys[keep] + 0.5) * bin_m, weight[keep]


def _phase(x: np.ndarray, h: np.ndarray, pitch_m: float) -> float:
    """Weighted circular mean of ``x`` modulo ``pitch_m``."""
    z = np.sum(h * np.exp(2j * np.pi * x / pitch_m)) if x.size else 0.0
    return float(np.angle(z) / (2 * np.pi) * pitch_m) if abs(z) > 0 else 0.0


def _least_squares(
    classes: list[tuple[np.ndarray, np.ndarray]], pitch_m: float, phases: list[float], tolerance_m: float
) -> tuple[float, list[float]]:
    """One weighted least-squares step of ``x = φ_class + k p`` over the positions near a line."""
    n = len(classes)
    rows, targets, weights, used = [], [], [], []
    observable = False
    for index, ((x, h), phase) in enumerate(zip(classes, phases, strict=True)):
        if not x.size:
            continue
        k = np.round((x - phase) / pitch_m)
        near = np.abs(x - phase - k * pitch_m) <= tolerance_m
        if not near.any():
            continue
        observable |= bool(np.ptp(k[near]) > 0)
        a = np.zeros((int(near.sum()), 1 + n))
        a[:, 0] = k[near]
        a[:, 1 + index] = 1.0
        rows.append(a)
        targets.append(x[near])
        weights.append(h[near])
        used.append(index)
    if not observable:  # one line per class at most: the pitch is not observable
        return pitch_m, phases
    a, b, w = np.vstack(rows), np.concatenate(targets), np.sqrt(np.concatenate(weights))
    a = a[:, [0, *(1 + i for i in used)]]
    sol, *_ = np.linalg.lstsq(a * w[:, None], b * w, rcond=None)
    out = list(phases)
    for j, i in enumerate(used):
        out[i] = float(sol[1 + j])
    return float(sol[0]), out


def cell_offset_on_lattice(
    fit: PitchFit | None, reference_rad: float | None, resolution_m: float
) -> tuple[float, float] | None:
    """Where an occupancy grid's cell corners go (x, y, modulo the resolution) so that the
    lattice's lines, the walls' centre lines, run along cell centres.

    A thin wall on a cell boundary blackens the cells on both sides of it: the map's wall
    is a cell thicker than the board, and a cell's width of the corridor beside every
    wall is never free (a 0.32 m maze on a 2 cm grid lost 6 % of its free space that way;
    a 1 ft maze's walls happen to fall near cell centres). The phases are the fit's,
    along the grid axes ``u``, ``v`` turned by ``reference_rad`` from the map's: only
    when the lattice fits and is so nearly square to the map that its farthest line
    (``pitch_m`` times its lines away) moves less than a quarter of a cell by the turn,
    and along an axis only where its lines lie within ``BOUNDARY_CELLS`` of a boundary of
    the cells as they are (a 1 ft maze's lie 7.6 mm off and keep their grid). None when
    neither axis moves.
    """
    if fit is None or not fit.fits or reference_rad is None:
        return None
    turn = math.remainder(reference_rad, math.pi / 2)
    span_m = fit.pitch_m * max(fit.lines)
    if abs(turn) * span_m >= resolution_m / 4:
        return None
    offset = np.remainder(np.asarray(fit.phase_m) - resolution_m / 2, resolution_m)
    off_centre = np.abs(np.remainder(offset + resolution_m / 2, resolution_m) - resolution_m / 2)
    offset[resolution_m / 2 - off_centre >= BOUNDARY_CELLS * resolution_m] = 0.0  # off the boundaries: leave them
    if not offset.any():
        return None
    return (float(offset[0]), float(offset[1]))
