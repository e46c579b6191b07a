"""Which world a simulated run happens in: a maze file, a maze generated from a seed, or a room."""

from __future__ import annotations

from pathlib import Path

from mazebot.config import Config
from mazebot.errors import UsageError
from mazebot.sim.hand_maze import HandBuild, hand_built_world
from mazebot.sim.maze_file import load_maze
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.room import make_room
from mazebot.sim.world import World, world_from_layout


def make_world(config: Config, maze_path: str | None, seed: int | None, size: tuple[int, int] | None) -> World:
    """The world a sim run uses: a maze file, a maze generated from a seed and size, or the room."""
    sim = config.sim
    if sim.world == "room":
        if maze_path or size is not None:
            raise UsageError("the room world takes no --maze or --size; its size is [sim] room_width_m/room_height_m")
        return make_room(
            sim.room_width_m,
            sim.room_height_m,
            cylinders=sim.room_cylinders,
            cylinder_diameter_m=sim.room_cylinder_diameter_m,
            seed=sim.seed if seed is None else seed,
            wall_thickness_m=sim.wall_thickness_m,
            footprint_radius_m=config.robot.footprint_radius_m,
        )
    path = maze_path or (sim.maze or None)
    if path is not None:
        if seed is not None or size is not None:
            raise UsageError("give either --maze or --seed/--size, not both")
        if not Path(path).is_file():
            raise UsageError(f"maze file {path} not found")
        world = load_maze(path, cell_size_m=sim.cell_size_m, wall_thickness_m=sim.wall_thickness_m)
        if sim.maze_build == "hand":
            assert world.maze is not None
            maze_seed = sim.seed if seed is None else seed
            return hand_built_world(world.maze, HandBuild.from_sim(sim), maze_seed, name=f"hand-{world.name}")
        return world
    width, height = size or (sim.maze_width, sim.maze_height)
    maze_seed = sim.seed if seed is None else seed
    layout = generate_maze(width, height, maze_seed, kind=sim.maze_kind, cell_size_m=sim.cell_size_m)
    name = f"{sim.maze_kind}-{width}x{height}-seed{maze_seed}"
    if sim.maze_build == "hand":
        return hand_built_world(layout, HandBuild.from_sim(sim), maze_seed, name=f"hand-{name}")
    return world_from_layout(layout, wall_thickness_m=sim.wall_thickness_m, name=name)
