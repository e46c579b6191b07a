"""Which world a simulated run happens in: a maze file, or a maze generated from a seed."""

from __future__ import annotations

from pathlib import Path

from mazebot.config import Config
from mazebot.errors import UsageError
from mazebot.sim.maze_file import load_maze
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.world import World, world_from_layout


def make_world(config: Config, maze_path: str | None, seed: int | None, size: tuple[int, int] | None) -> World:
    """The world a sim run uses: a maze file, or a maze generated from a seed and size."""
    sim = config.sim
    path = maze_path or (sim.maze or None)
    if path is not None:
        if seed is not None or size is not None:
            raise UsageError("give either --maze or --seed/--size, not both")
        if not Path(path).is_file():
            raise UsageError(f"maze file {path} not found")
        return load_maze(path, cell_size_m=sim.cell_size_m, wall_thickness_m=sim.wall_thickness_m)
    width, height = size or (sim.maze_width, sim.maze_height)
    maze_seed = sim.seed if seed is None else seed
    layout = generate_maze(width, height, maze_seed, kind=sim.maze_kind, cell_size_m=sim.cell_size_m)
    return world_from_layout(
        layout, wall_thickness_m=sim.wall_thickness_m, name=f"{sim.maze_kind}-{width}x{height}-seed{maze_seed}"
    )
