"""The angle at which each beam meets the surface it hits, and how far short of it the beam may clear.

The occupancy grid marks free every cell a beam crosses before its endpoint's cell (the
inverse sensor model of Thrun, Burgard & Fox, *Probabilistic Robotics*, ch. 9). Cells are
squares and a wall is rarely on their edges: a maze built by hand stands a little turned,
and without the lattice priors nothing moves the cells onto the walls. A cell the wall's
face passes through is partly wall, and a beam that crosses its free part clears all of it.
A beam meeting the face at the angle ``α`` runs within ``d`` of the face for the last
``d / sin α`` of its length; with ``d`` a cell's diagonal (no cell crossed farther from the
face can hold it) that is 4 cm at 45°, 8 cm at 20° and 0.8 m at 2° with 2 cm cells. A steep
beam crosses a cell or two such cells, and its own hit, which wins within a revolution, marks
the face. A grazing one clears every cell the face passes through along that stretch while
its hit marks one, or none at all when it is too far to mark (:func:`mazebot.slam.keyframes.map_rays`):
revolution after revolution such beams wear away a wall the robot later drives beside, and a
robot that sees it there looks lost. Measured: the hand-built contest maze apec2011 with the
lattice priors off, a 1 m wall turned about 1° to the cells, seen from 0.5-3 m away along its
corridor at 1-15°: 812 revolutions cleared its face's cells against 254 that hit them, and the
whole wall was free in the map when the robot drove beside it.

The angle comes from the chords to the neighbouring hits in scan order. A straight face seen
at a grazing angle has its neighbouring hits far apart along it (1.5 m at 3 m and 2° with one
sample a degree), beyond any fitting radius, but the chord between two of them still lies
along the face. Of the two chords the steeper is taken: at a face's end the other one jumps to
whatever stands behind, nearly along the beam, and would call a steep beam grazing; where the
two chords are two surfaces (a corner) the steeper one says less grazing than the truth, and
the beam clears as it always did.
"""

from __future__ import annotations

import numpy as np


def incidence_sin(points_xy: np.ndarray, origins_xy: np.ndarray, circular: bool = True) -> np.ndarray:
    """``sin α`` (N,) of the angle at which each beam from ``origins_xy`` meets the surface at its hit.

    ``points_xy`` (N, 2) are hits in scan order; ``circular``: one full turn of the head,
    so the first and last are neighbours. A hit with no neighbour, or whose neighbours lie on
    it, gets 1 (steep: nothing is known against it).
    """
    pts = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    beams = pts - np.asarray(origins_xy, dtype=np.float64).reshape(-1, 2)
    n = pts.shape[0]
    out = np.ones(n)
    if n < 2:
        return out
    range_m = np.hypot(beams[:, 0], beams[:, 1])
    before = pts - np.roll(pts, 1, axis=0)  # chord from the previous hit
    after = np.roll(pts, -1, axis=0) - pts  # chord to the next hit
    sines = []
    for chord, edge in ((before, 0), (after, n - 1)):
        length = np.hypot(chord[:, 0], chord[:, 1])
        cross = np.abs(beams[:, 0] * chord[:, 1] - beams[:, 1] * chord[:, 0])
        ok = (length > 0) & (range_m > 0)
        if not circular:
            ok[edge] = False
        sines.append(np.where(ok, cross / np.maximum(length * range_m, 1e-300), -1.0))
    steeper = np.maximum(sines[0], sines[1])
    known = steeper >= 0.0
    out[known] = np.minimum(steeper[known], 1.0)
    return out


def free_stop_m(sin_incidence: np.ndarray, clearance_m: float) -> np.ndarray:
    """How far short of its hit each beam must stop clearing: where it comes within ``clearance_m`` of the surface."""
    return clearance_m / np.maximum(np.asarray(sin_incidence, dtype=np.float64), 1e-9)
