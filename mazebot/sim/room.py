"""A rectangular room with cylindrical obstacles: the simplest world that is not a maze.

Mapping an open room tests what a maze does not: long ranges, few straight walls to
match against, and round obstacles. Cylinders are placed at random (seeded) but never
so close to each other or to a wall that the robot could not drive between them, so
the whole floor stays reachable.
"""

from __future__ import annotations

import numpy as np

from mazebot.sim.world import World, rectangles_outline

#: Extra gap (metres) beyond the robot's diameter left between obstacles.
PASSAGE_MARGIN_M = 0.04


def make_room(
    width_m: float = 2.0,
    height_m: float = 1.2,
    cylinders: int = 4,
    cylinder_diameter_m: float = 0.08,
    seed: int = 0,
    wall_thickness_m: float = 0.012,
    footprint_radius_m: float = 0.1,
) -> World:
    """A ``width_m`` x ``height_m`` room (inside dimensions) with ``cylinders`` posts.

    The floor spans ``[0, width_m] x [0, height_m]``; walls ``wall_thickness_m`` thick
    stand outside it. The robot starts near the south-west corner facing east, two
    footprint radii from each wall. Every gap (cylinder to cylinder, cylinder to wall,
    cylinder to start pose) is at least the robot's diameter plus
    ``PASSAGE_MARGIN_M``, so the robot fits everywhere between obstacles.

    Raises ValueError when the cylinders cannot be placed that way (the room is too
    small for them); placement is random rejection sampling seeded by ``seed``.
    """
    if width_m <= 0 or height_m <= 0 or wall_thickness_m <= 0:
        raise ValueError(
            f"room size and wall thickness must be positive, got {width_m} x {height_m} m, walls {wall_thickness_m} m"
        )
    t = wall_thickness_m
    walls = np.array(
        [
            (-t, -t, width_m + t, 0.0),  # south
            (-t, height_m, width_m + t, height_m + t),  # north
            (-t, -t, 0.0, height_m + t),  # west
            (width_m, -t, width_m + t, height_m + t),  # east
        ]
    )
    start = (2.0 * footprint_radius_m, 2.0 * footprint_radius_m, 0.0)
    if start[0] >= width_m - footprint_radius_m or start[1] >= height_m - footprint_radius_m:
        raise ValueError(f"a {width_m} x {height_m} m room is too small for a robot of radius {footprint_radius_m} m")
    circles = _place_cylinders(
        np.random.default_rng(seed),
        width_m,
        height_m,
        cylinders,
        cylinder_diameter_m / 2.0,
        footprint_radius_m,
        start,
    )
    return World(
        name=f"room-{width_m:g}x{height_m:g}-{cylinders}cyl-seed{seed}",
        segments=rectangles_outline(walls),
        circles=circles,
        start_pose=start,
        bounds_m=(-t, -t, width_m + t, height_m + t),
        meta={
            "wall_thickness_m": t,
            "footprint_radius_m": footprint_radius_m,
            "seed": seed,
        },
    )


def _place_cylinders(
    rng: np.random.Generator,
    width_m: float,
    height_m: float,
    count: int,
    radius_m: float,
    footprint_radius_m: float,
    start_xy: tuple[float, float, float],
    attempts: int = 10_000,
) -> np.ndarray:
    """Rejection-sample ``count`` cylinder centres that leave robot-sized passages.

    A centre must be a passage (robot diameter plus margin) plus its radius away from
    every wall, a passage plus two radii from other cylinders, and its radius plus a
    footprint plus margin from the start pose. Non-overlapping obstacles with passages
    at least a robot wide leave the robot's free space connected.
    """
    if count < 0 or radius_m <= 0:
        raise ValueError(f"need a non-negative cylinder count and positive diameter, got {count}, {2 * radius_m} m")
    passage = 2.0 * footprint_radius_m + PASSAGE_MARGIN_M
    lo = passage + radius_m
    if count and (width_m - lo <= lo or height_m - lo <= lo):
        raise ValueError(
            f"no cylinder of diameter {2 * radius_m} m fits in a {width_m} x {height_m} m room "
            f"with {passage:.2f} m passages"
        )
    centres: list[tuple[float, float]] = []
    for _ in range(attempts):
        if len(centres) == count:
            break
        x = rng.uniform(lo, width_m - lo)
        y = rng.uniform(lo, height_m - lo)
        if np.hypot(x - start_xy[0], y - start_xy[1]) < radius_m + footprint_radius_m + PASSAGE_MARGIN_M:
            continue
        if any(np.hypot(x - cx, y - cy) < passage + 2.0 * radius_m for cx, cy in centres):
            continue
        centres.append((x, y))
    if len(centres) < count:
        raise ValueError(
            f"could place only {len(centres)} of {count} cylinders (diameter {2 * radius_m} m) "
            f"in a {width_m} x {height_m} m room with {passage:.2f} m passages; "
            "use fewer cylinders or a larger room"
        )
    return np.array([(x, y, radius_m) for x, y in centres], dtype=np.float64).reshape(-1, 3)
