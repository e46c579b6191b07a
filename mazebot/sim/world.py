"""The geometry of a simulated world: wall surfaces as segments, posts as circles.

Everything the simulator needs to know about a world (ray casting, collisions, ground
truth rasters) reads these arrays; loaders and generators only have to produce them.
The frame is the world frame: x east, y north, metres; angles counter-clockwise.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class MazeLayout:
    """The cell structure of a maze world, for ground truth and scripted routes.

    Cell (col, row) has its south-west corner at ``origin + (col, row) * cell_size_m``;
    row 0 is the southern row. ``walls_east[row, col]`` is True when there is a wall on
    the east side of that cell, ``walls_north[row, col]`` on its north side; the outer
    boundary is included (west of column 0 is ``walls_west_edge``, south of row 0 is
    ``walls_south_edge``).
    """

    width: int
    height: int
    cell_size_m: float
    walls_east: np.ndarray  # bool (height, width)
    walls_north: np.ndarray  # bool (height, width)
    walls_west_edge: np.ndarray  # bool (height,)
    walls_south_edge: np.ndarray  # bool (width,)
    start_cell: tuple[int, int]  # (col, row)
    goal_cells: tuple[tuple[int, int], ...] = ()
    origin_m: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class World:
    """A static 2D world.

    ``segments`` are the surfaces a lidar ray can hit and the robot can touch:
    shape (N, 4) rows of ``x1, y1, x2, y2`` in metres. ``circles`` are cylinders:
    shape (M, 3) rows of ``cx, cy, radius`` in metres. ``start_pose`` is where the robot
    is put down, ``(x_m, y_m, theta_rad)``.
    """

    name: str
    segments: np.ndarray
    circles: np.ndarray
    start_pose: tuple[float, float, float]
    bounds_m: tuple[float, float, float, float]  # xmin, ymin, xmax, ymax
    maze: MazeLayout | None = None
    meta: dict[str, object] = field(default_factory=dict)

    def __post_init__(self) -> None:
        segs = np.asarray(self.segments, dtype=np.float64).reshape(-1, 4)
        circ = np.asarray(self.circles, dtype=np.float64).reshape(-1, 3)
        object.__setattr__(self, "segments", segs)
        object.__setattr__(self, "circles", circ)
