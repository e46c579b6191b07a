"""A maze built by hand from boards and posts: the lattice a maker really gets.

The generated and contest mazes stand on a perfect lattice of exactly the configured
cell size. A maze a maker builds is not that: the posts are set out with a tape measure,
so the pitch is off by a few per cent and every row of posts by a few millimetres; each
board stands a little off the line between its posts and a little turned; boards are cut
short of the posts (a few millimetres of gap at each end) and come in several
thicknesses; the whole maze stands at whatever angle it was put down; and a table leg or
two stands in it. Everything here is drawn from one seed, so a run can be replayed.

What a 2D lidar about 10 cm above the floor sees of the clutter: a table or chair leg
is a small disc (a circle of the world); a cable on the floor is below its plane, and
its bump under a wheel is below what the physics models, so cables are not modelled.

Geometry: every board and every post is its own closed rectangle, oriented with the
solid on its left (the convention of :mod:`mazebot.sim.world`). Boards and posts may
overlap where a thick board meets a post's corner; the truth raster fills by the
non-zero winding rule (:mod:`mazebot.sim.raster`), so an overlap stays solid, and a
face hidden inside the solid is never the first surface a ray from free space meets.

The ground truth follows the real walls: the world's :class:`HandLayout` puts cell
centres between the true rows of posts, in the maze's true direction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from mazebot.sim.world import MazeLayout, World, start_heading_rad

if TYPE_CHECKING:
    from mazebot.config import SimConfig

#: Offsets and turns are drawn from normal distributions clipped at this many std (a board
#: nailed 3 cm off its line is a mistake a maker sees, not a tolerance).
CLIP_STD = 3.0


@dataclass(frozen=True)
class HandBuild:
    """How far a hand-built maze is from the perfect one (``[sim] hand_*`` keys)."""

    pitch_error_max: float = 0.03
    line_jitter_m: float = 0.005
    wall_offset_std_m: float = 0.004
    wall_turn_std_rad: float = math.radians(0.7)
    post_gap_min_m: float = 0.002
    post_gap_max_m: float = 0.006
    wall_thickness_min_m: float = 0.006
    wall_thickness_max_m: float = 0.020
    post_size_m: float = 0.012
    maze_angle_rad: float | None = None  # None: random in [0, 2 pi), seeded
    start_heading_std_rad: float = math.radians(3.0)
    clutter: int = 3
    clutter_diameter_m: float = 0.02

    @classmethod
    def from_sim(cls, sim: SimConfig) -> HandBuild:
        """The build the ``[sim]`` section describes."""
        s = sim
        angle = s.hand_maze_angle_deg
        return cls(
            pitch_error_max=s.hand_pitch_error_max,
            line_jitter_m=s.hand_line_jitter_m,
            wall_offset_std_m=s.hand_wall_offset_std_m,
            wall_turn_std_rad=math.radians(s.hand_wall_turn_std_deg),
            post_gap_min_m=s.hand_post_gap_min_m,
            post_gap_max_m=s.hand_post_gap_max_m,
            wall_thickness_min_m=s.hand_wall_thickness_min_m,
            wall_thickness_max_m=s.hand_wall_thickness_max_m,
            post_size_m=s.hand_post_size_m,
            maze_angle_rad=None if angle < 0 else math.radians(angle),
            start_heading_std_rad=math.radians(s.hand_start_heading_std_deg),
            clutter=s.hand_clutter,
            clutter_diameter_m=s.hand_clutter_diameter_m,
        )


@dataclass(frozen=True, eq=False)
class HandLayout(MazeLayout):
    """A maze layout whose cells lie between the true rows of posts of a hand-built maze.

    ``lines_u_m`` (width + 1) and ``lines_v_m`` (height + 1) are where the columns and
    rows of posts stand along the maze's own axes, measured from ``origin_m`` (world
    frame), the axes turned by ``angle_rad``. ``cell_size_m`` is the true mean pitch.
    """

    angle_rad: float = 0.0
    lines_u_m: tuple[float, ...] = ()
    lines_v_m: tuple[float, ...] = ()

    def _to_world(self, u: float, v: float) -> tuple[float, float]:
        c, s = math.cos(self.angle_rad), math.sin(self.angle_rad)
        return (self.origin_m[0] + c * u - s * v, self.origin_m[1] + s * u + c * v)

    def cell_center_m(self, cell: tuple[int, int]) -> tuple[float, float]:
        u = 0.5 * (self.lines_u_m[cell[0]] + self.lines_u_m[cell[0] + 1])
        v = 0.5 * (self.lines_v_m[cell[1]] + self.lines_v_m[cell[1] + 1])
        return self._to_world(u, v)

    def cell_at(self, x_m: float, y_m: float) -> tuple[int, int] | None:
        c, s = math.cos(self.angle_rad), math.sin(self.angle_rad)
        dx, dy = x_m - self.origin_m[0], y_m - self.origin_m[1]
        u, v = c * dx + s * dy, -s * dx + c * dy
        col = int(np.searchsorted(self.lines_u_m, u, side="right")) - 1
        row = int(np.searchsorted(self.lines_v_m, v, side="right")) - 1
        return (col, row) if self.contains((col, row)) else None


@dataclass(frozen=True)
class HandGeometry:
    """What was drawn, for tests and for the record: one row per board and per post."""

    pitch_m: float
    angle_rad: float
    lines_u_m: np.ndarray  # (W + 1,)
    lines_v_m: np.ndarray  # (H + 1,)
    boards: np.ndarray  # (B, 7): centre u, v (maze frame), along axis (0 = u, 1 = v), offset, turn, thickness, length
    gaps_m: np.ndarray  # (B, 2): the gaps at both ends of each board
    posts_uv: np.ndarray  # (P, 2)
    clutter_uv: np.ndarray  # (C, 2)


def _clipped_normal(rng: np.random.Generator, std: float, size: int) -> np.ndarray:
    return np.clip(rng.normal(0.0, std, size), -CLIP_STD * std, CLIP_STD * std) if std > 0 else np.zeros(size)


def hand_geometry(layout: MazeLayout, build: HandBuild, seed: int) -> HandGeometry:
    """Draw the true places of the posts and boards of ``layout`` built by hand (maze frame, metres)."""
    rng = np.random.default_rng([seed, 0x4A4E44])  # its own stream: the maze's walls stay the generator's
    pitch = layout.cell_size_m * (1.0 + rng.uniform(-build.pitch_error_max, build.pitch_error_max))
    j = build.line_jitter_m
    lines_u = np.arange(layout.width + 1) * pitch + rng.uniform(-j, j, layout.width + 1)
    lines_v = np.arange(layout.height + 1) * pitch + rng.uniform(-j, j, layout.height + 1)
    lines_u -= lines_u[0]
    lines_v -= lines_v[0]  # the south-west post is the maze's origin
    angle = build.maze_angle_rad if build.maze_angle_rad is not None else float(rng.uniform(0.0, math.tau))

    pieces: list[tuple[int, int, int]] = []  # (axis, line index, span index): a board along axis
    for jv in range(layout.height + 1):  # boards along u on row of posts jv
        flags = layout.walls_south_edge if jv == 0 else layout.walls_north[jv - 1]
        pieces += [(0, jv, int(i)) for i in np.flatnonzero(flags)]
    for iu in range(layout.width + 1):  # boards along v on column of posts iu
        flags = layout.walls_west_edge if iu == 0 else layout.walls_east[:, iu - 1]
        pieces += [(1, iu, int(i)) for i in np.flatnonzero(flags)]
    n = len(pieces)
    offset = _clipped_normal(rng, build.wall_offset_std_m, n)
    turn = _clipped_normal(rng, build.wall_turn_std_rad, n)
    thickness = rng.uniform(build.wall_thickness_min_m, build.wall_thickness_max_m, n)
    gaps = rng.uniform(build.post_gap_min_m, build.post_gap_max_m, (n, 2))
    half_post = 0.5 * build.post_size_m
    boards = np.zeros((n, 7))
    for k, (axis, line, span) in enumerate(pieces):
        along_lines, across_lines = (lines_u, lines_v) if axis == 0 else (lines_v, lines_u)
        a = along_lines[span] + half_post + gaps[k, 0]
        b = along_lines[span + 1] - half_post - gaps[k, 1]
        centre_along, across = 0.5 * (a + b), across_lines[line] + offset[k]
        cu, cv = (centre_along, across) if axis == 0 else (across, centre_along)
        boards[k] = (cu, cv, axis, offset[k], turn[k], thickness[k], b - a)
    post_u, post_v = np.meshgrid(np.arange(layout.width + 1), np.arange(layout.height + 1), indexing="ij")
    posts = np.column_stack((lines_u[post_u.ravel()], lines_v[post_v.ravel()]))
    return HandGeometry(pitch, angle, lines_u, lines_v, boards, gaps, posts, _clutter(rng, layout, build, lines_u,
                                                                                      lines_v, half_post))


def _clutter(
    rng: np.random.Generator,
    layout: MazeLayout,
    build: HandBuild,
    lines_u: np.ndarray,
    lines_v: np.ndarray,
    half_post_m: float,
) -> np.ndarray:
    """Table legs in cell corners, clear of the walls by a centimetre, never in the start cell.

    A corner is where a leg leaves a 1 ft corridor passable: the robot's body never
    reaches it, only its lidar sees it.
    """
    cells = [(c, r) for r in range(layout.height) for c in range(layout.width) if (c, r) != layout.start_cell]
    if not cells or build.clutter == 0:
        return np.zeros((0, 2))
    radius = 0.5 * build.clutter_diameter_m
    inset = half_post_m + build.wall_thickness_max_m / 2 + build.wall_offset_std_m * CLIP_STD + 0.01 + radius
    out = []
    for index in rng.choice(len(cells), size=min(build.clutter, len(cells)), replace=False):
        c, r = cells[int(index)]
        east, north = rng.integers(2), rng.integers(2)
        u = lines_u[c + 1] - inset if east else lines_u[c] + inset
        v = lines_v[r + 1] - inset if north else lines_v[r] + inset
        out.append((u, v))
    return np.array(out).reshape(-1, 2)


def _rectangle_ccw(cu: float, cv: float, half_along: float, half_across: float, axis: int, turn: float) -> np.ndarray:
    """The corners (4, 2) of a rectangle, counter-clockwise, in the maze frame."""
    local = np.array([(-half_along, -half_across), (half_along, -half_across),
                      (half_along, half_across), (-half_along, half_across)])
    if axis == 1:  # along v: (along, across) = (v, -u) keeps the order counter-clockwise
        local = np.column_stack((-local[:, 1], local[:, 0]))
    c, s = math.cos(turn), math.sin(turn)
    return np.column_stack((cu + c * local[:, 0] - s * local[:, 1], cv + s * local[:, 0] + c * local[:, 1]))


def hand_built_world(layout: MazeLayout, build: HandBuild, seed: int, name: str = "hand-maze") -> World:
    """The world of ``layout`` built by hand (module docstring), the robot put down in its start cell."""
    if build.wall_thickness_max_m >= layout.cell_size_m / 2:
        raise ValueError(f"boards {build.wall_thickness_max_m} m thick do not fit cells of {layout.cell_size_m} m")
    geo = hand_geometry(layout, build, seed)
    polygons = [
        _rectangle_ccw(cu, cv, 0.5 * length, 0.5 * thick, int(axis), turn)
        for cu, cv, axis, _, turn, thick, length in geo.boards
    ]
    h = 0.5 * build.post_size_m
    polygons += [_rectangle_ccw(u, v, h, h, 0, 0.0) for u, v in geo.posts_uv]
    corners = np.array(polygons)  # (R, 4, 2), maze frame
    c, s = math.cos(geo.angle_rad), math.sin(geo.angle_rad)
    world_xy = np.stack((c * corners[..., 0] - s * corners[..., 1], s * corners[..., 0] + c * corners[..., 1]), -1)
    segments = np.concatenate((world_xy, np.roll(world_xy, -1, axis=1)), axis=-1).reshape(-1, 4)
    clutter_xy = geo.clutter_uv @ np.array([[c, s], [-s, c]])
    circles = np.column_stack((clutter_xy, np.full(len(clutter_xy), 0.5 * build.clutter_diameter_m)))
    hand_layout = HandLayout(
        width=layout.width,
        height=layout.height,
        cell_size_m=float(geo.pitch_m),
        walls_east=layout.walls_east,
        walls_north=layout.walls_north,
        walls_west_edge=layout.walls_west_edge,
        walls_south_edge=layout.walls_south_edge,
        start_cell=layout.start_cell,
        goal_cells=layout.goal_cells,
        origin_m=(0.0, 0.0),
        angle_rad=float(geo.angle_rad),
        lines_u_m=tuple(float(x) for x in geo.lines_u_m),
        lines_v_m=tuple(float(x) for x in geo.lines_v_m),
    )
    rng = np.random.default_rng([seed, 0x5354])
    x, y = hand_layout.cell_center_m(layout.start_cell)
    heading = geo.angle_rad + start_heading_rad(layout, layout.start_cell)
    heading += float(_clipped_normal(rng, build.start_heading_std_rad, 1)[0])
    margin = build.post_size_m + build.wall_thickness_max_m
    pts = segments.reshape(-1, 2)
    bounds = (float(pts[:, 0].min() - margin), float(pts[:, 1].min() - margin),
              float(pts[:, 0].max() + margin), float(pts[:, 1].max() + margin))
    return World(
        name=name,
        segments=segments,
        circles=circles,
        start_pose=(float(x), float(y), math.remainder(heading, math.tau)),
        bounds_m=bounds,
        maze=hand_layout,
        meta={
            "wall_thickness_m": float(np.mean(geo.boards[:, 5])) if len(geo.boards) else build.post_size_m,
            "cell_size_m": float(geo.pitch_m),
            "maze_angle_rad": float(geo.angle_rad),
            "build": "hand",
        },
    )
