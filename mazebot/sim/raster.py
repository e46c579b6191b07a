"""Ground-truth occupancy rasters of a world, at any resolution.

SLAM builds its map from lidar hits, so a wall shows up in every map cell it passes
through, however thin it is. The truth raster used to score a map therefore marks a
cell occupied when any part of it (a positive area) lies inside a wall or cylinder:
the ``"touch"`` rule. The ``"centre"`` rule (occupied when the cell centre is inside)
keeps areas unbiased but loses walls thinner than a cell; it is there for area checks.

Grids are indexed ``grid[row, col]``; row 0 is the southern row and cell (row, col)
spans ``origin + (col, row) * resolution`` to one resolution step further (the
orientation of ROS ``map_server`` data, origin bottom-left).

Walls are filled by the non-zero winding rule from the world's segments, which works
because the worlds built in :mod:`mazebot.sim` store closed outlines with the solid on
their left (see :mod:`mazebot.sim.world`): a point inside is wound round once, or more
where the boards and posts of a hand-built maze (:mod:`mazebot.sim.hand_maze`) overlap,
which the even-odd rule would count as free. An open polyline is drawn as a line of
touched cells only.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from scipy import ndimage

from mazebot.sim.raycast import distance_to_obstacles
from mazebot.sim.world import World

Rule = Literal["touch", "centre"]


def grid_frame(
    world: World,
    resolution_m: float,
    origin_m: tuple[float, float] | None = None,
    shape: tuple[int, int] | None = None,
) -> tuple[tuple[float, float], tuple[int, int]]:
    """The origin and (rows, cols) shape of a raster, defaulting to the world's bounds."""
    if resolution_m <= 0:
        raise ValueError(f"resolution must be positive, got {resolution_m} m")
    xmin, ymin, xmax, ymax = world.bounds_m
    origin = (float(xmin), float(ymin)) if origin_m is None else (float(origin_m[0]), float(origin_m[1]))
    if shape is None:
        rows = int(np.ceil((ymax - origin[1]) / resolution_m - 1e-9))
        cols = int(np.ceil((xmax - origin[0]) / resolution_m - 1e-9))
        shape = (max(rows, 1), max(cols, 1))
    return origin, (int(shape[0]), int(shape[1]))


def true_occupancy(
    world: World,
    resolution_m: float,
    origin_m: tuple[float, float] | None = None,
    shape: tuple[int, int] | None = None,
    rule: Rule = "touch",
) -> tuple[np.ndarray, tuple[float, float]]:
    """The occupancy of ``world`` on a grid: ``(grid, origin_m)``, grid bool (rows, cols).

    By default the grid covers ``world.bounds_m`` with its origin at the bounds' corner;
    pass ``origin_m`` and ``shape`` to match another map's frame. ``rule`` is ``"touch"``
    (any part of the cell covered: thin walls never vanish) or ``"centre"`` (the cell
    centre covered: unbiased area).
    """
    if rule not in ("touch", "centre"):
        raise ValueError(f"rule must be 'touch' or 'centre', got {rule!r}")
    origin, (rows, cols) = grid_frame(world, resolution_m, origin_m, shape)
    grid = _winding_fill(world.segments, resolution_m, origin, rows, cols)
    if rule == "touch":
        _draw_segments(grid, world.segments, resolution_m, origin)
    _draw_circles(grid, world.circles, resolution_m, origin, touch=rule == "touch")
    return grid, origin


def _winding_fill(segments: np.ndarray, res: float, origin: tuple[float, float], rows: int, cols: int) -> np.ndarray:
    """Cells whose centre is inside the closed outlines (non-zero winding rule), all rows at once.

    Each non-horizontal segment crossing the horizontal line through a row of centres
    adds its winding (+1 going south, −1 going north: solid on the left) to every centre
    east of the crossing; the steps are accumulated in a difference array and a
    cumulative sum gives the winding number, non-zero inside. A segment counts for
    ``ymin <= y < ymax`` so a shared vertex is crossed exactly once.
    """
    ox, oy = origin
    segs = segments[segments[:, 1] != segments[:, 3]]
    flips = np.zeros((rows, cols + 1), dtype=np.int32)
    if segs.shape[0]:
        y_rows = oy + (np.arange(rows) + 0.5) * res  # (R,)
        y_lo = np.minimum(segs[:, 1], segs[:, 3])
        y_hi = np.maximum(segs[:, 1], segs[:, 3])
        # Only rows inside each segment's y span can cross it: index range per segment.
        r_lo = np.ceil((y_lo - oy) / res - 0.5).astype(np.int64).clip(0, rows)
        r_hi = np.ceil((y_hi - oy) / res - 0.5).astype(np.int64).clip(0, rows)
        counts = r_hi - r_lo
        seg_index = np.repeat(np.arange(segs.shape[0]), counts)
        row_index = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        row_index += np.repeat(r_lo, counts)
        s = segs[seg_index]
        y = y_rows[row_index]
        keep = (y >= np.minimum(s[:, 1], s[:, 3])) & (y < np.maximum(s[:, 1], s[:, 3]))
        s, y, row_index = s[keep], y[keep], row_index[keep]
        x_cross = s[:, 0] + (y - s[:, 1]) * (s[:, 2] - s[:, 0]) / (s[:, 3] - s[:, 1])
        # first column whose centre lies east of the crossing
        col = np.floor((x_cross - ox) / res - 0.5).astype(np.int64) + 1
        winding = np.where(s[:, 3] < s[:, 1], 1, -1).astype(np.int32)
        np.add.at(flips, (row_index, col.clip(0, cols)), winding)
    return np.cumsum(flips, axis=1)[:, :cols] != 0


def _open_cell_range(lo: float, hi: float, o: float, res: float, n: int) -> tuple[int, int]:
    """Cells ``[a, b)`` along one axis whose open interval meets the open span (lo, hi)."""
    a = int(np.floor((lo - o) / res + 1e-9))
    b = int(np.ceil((hi - o) / res - 1e-9))
    return max(a, 0), min(max(b, a + 1), n)


def _draw_segments(grid: np.ndarray, segments: np.ndarray, res: float, origin: tuple[float, float]) -> None:
    """Mark cells whose interior a segment passes through.

    Axis-aligned segments are exact: a face lying exactly on a cell boundary touches no
    interior and marks nothing (the fill already marks the solid side). Oblique ones are
    sampled every quarter cell, which can miss a cell corner clipped by less than that.
    """
    rows, cols = grid.shape
    ox, oy = origin
    for x1, y1, x2, y2 in segments:
        if y1 == y2 or x1 == x2:
            horizontal = y1 == y2
            line, o_line, n_line = (y1, oy, rows) if horizontal else (x1, ox, cols)
            lo, hi = (min(x1, x2), max(x1, x2)) if horizontal else (min(y1, y2), max(y1, y2))
            o_span, n_span = (ox, cols) if horizontal else (oy, rows)
            pos = (line - o_line) / res
            if abs(pos - round(pos)) < 1e-9 or not 0 <= pos < n_line:
                continue  # on a cell boundary, or off the grid
            k = int(np.floor(pos))
            a, b = _open_cell_range(lo, hi, o_span, res, n_span)
            if a >= b:
                continue
            if horizontal:
                grid[k, a:b] = True
            else:
                grid[a:b, k] = True
            continue
        n = int(np.ceil(np.hypot(x2 - x1, y2 - y1) / (res / 4))) + 1
        u = np.linspace(0.0, 1.0, n)
        c = np.floor((x1 + u * (x2 - x1) - ox) / res).astype(np.int64)
        r = np.floor((y1 + u * (y2 - y1) - oy) / res).astype(np.int64)
        ok = (c >= 0) & (c < cols) & (r >= 0) & (r < rows)
        grid[r[ok], c[ok]] = True


def _draw_circles(grid: np.ndarray, circles: np.ndarray, res: float, origin: tuple[float, float], touch: bool) -> None:
    """Mark cells covered by cylinders: any overlap (``touch``) or the centre inside."""
    rows, cols = grid.shape
    ox, oy = origin
    for cx, cy, radius in circles:
        c0 = max(int(np.floor((cx - radius - ox) / res)), 0)
        c1 = min(int(np.floor((cx + radius - ox) / res)) + 1, cols)
        r0 = max(int(np.floor((cy - radius - oy) / res)), 0)
        r1 = min(int(np.floor((cy + radius - oy) / res)) + 1, rows)
        if c0 >= c1 or r0 >= r1:
            continue
        x_lo = ox + np.arange(c0, c1) * res  # west edges of the cells
        y_lo = oy + np.arange(r0, r1) * res
        if touch:
            # distance from the circle centre to the nearest point of each cell square
            ddx = np.clip(cx, x_lo, x_lo + res) - cx
            ddy = np.clip(cy, y_lo, y_lo + res) - cy
            inside = ddy[:, None] ** 2 + ddx[None, :] ** 2 < radius**2
        else:
            ddx = x_lo + res / 2 - cx
            ddy = y_lo + res / 2 - cy
            inside = ddy[:, None] ** 2 + ddx[None, :] ** 2 <= radius**2
        grid[r0:r1, c0:c1] |= inside


def free_reachable(
    world: World,
    resolution_m: float,
    footprint_radius_m: float,
    origin_m: tuple[float, float] | None = None,
    shape: tuple[int, int] | None = None,
) -> tuple[np.ndarray, tuple[float, float]]:
    """Free cells the robot can map from its start pose: ``(grid, origin_m)``, grid bool.

    The denominator of the coverage metric. First the robot's configuration space: cell
    centres farther than ``footprint_radius_m`` from every obstacle, 4-connected to the
    start pose's cell (gaps narrower than the robot stay shut). Then every free cell
    within ``footprint_radius_m * sqrt(2)`` plus one cell of those centres, measured
    inside free space so it never leaks through a wall: that is the robot's body sweep
    plus the corner pockets only its lidar reaches (a right-angle corner lies
    ``sqrt(2)`` radii from the nearest reachable centre).

    Raises ValueError if the start pose itself is within the footprint of an obstacle.
    """
    occupied, origin = true_occupancy(world, resolution_m, origin_m, shape)
    rows, cols = occupied.shape
    res = resolution_m
    free = ~occupied

    # Clearance of each free cell centre. The distance transform to the nearest occupied
    # cell centre is within res/sqrt(2) of the true clearance; only cells in that band
    # around the footprint radius need the exact (slower) distance.
    approx = ndimage.distance_transform_edt(free) * res
    slack = res / np.sqrt(2.0)
    cspace = free & (approx - slack > footprint_radius_m)
    band = free & ~cspace & (approx + slack > footprint_radius_m)
    band_rows, band_cols = np.nonzero(band)
    if band_rows.size:
        centres = np.column_stack((origin[0] + (band_cols + 0.5) * res, origin[1] + (band_rows + 0.5) * res))
        cspace[band_rows, band_cols] = distance_to_obstacles(centres, world) > footprint_radius_m

    x, y, _ = world.start_pose
    start_col = int(np.floor((x - origin[0]) / res))
    start_row = int(np.floor((y - origin[1]) / res))
    if not (0 <= start_row < rows and 0 <= start_col < cols) or not cspace[start_row, start_col]:
        raise ValueError(
            f"start pose ({x:.3f}, {y:.3f}) m of world {world.name!r} is off the grid or within "
            f"{footprint_radius_m} m of an obstacle; the robot cannot be put down there"
        )
    labels, _ = ndimage.label(cspace)  # default structure: 4-connectivity
    reachable_centres = labels == labels[start_row, start_col]

    # Geodesic dilation inside free space, alternating 4- and 8-neighbour steps so the
    # grown region is an octagon, close to a disc.
    cross = ndimage.generate_binary_structure(2, 1)
    square = ndimage.generate_binary_structure(2, 2)
    steps = int(np.ceil((footprint_radius_m * np.sqrt(2.0) + res) / res))
    grown = reachable_centres
    for i in range(steps):
        grown = ndimage.binary_dilation(grown, structure=square if i % 2 else cross, mask=free)
    return grown, origin
