"""Draws the page's home-screen icons (static/icons/*.png) with mazebot's own PNG encoder.

A small maze in the page's colours with the robot as a green dot: walls on the page's
dark background, full bleed, everything inside the central 80 % circle so the icon can be
cropped to any shape (a "maskable" icon, W3C Web App Manifest, "purpose" member). Drawn
from rectangles and one disc on an integer grid, so the bytes are the same on every
machine; ``tests/web/test_manifest.py`` checks the committed files equal this output.

    python tools/make_icons.py          # rewrites static/icons/icon-{180,192,512}.png
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from mazebot.files import write_atomic  # noqa: E402
from mazebot.png import encode_png  # noqa: E402

#: 180 for iOS' apple-touch-icon, 192 and 512 for the manifest (what Chrome asks for)
SIZES = (180, 192, 512)
BACKGROUND = (29, 36, 48)  # --bg of style.css
WALL = (242, 244, 247)  # --fg
ROBOT = (31, 157, 85)  # --go
CELLS = 4  # the maze is CELLS x CELLS
#: wall segments in cell units, (x0, y0, x1, y1), y down: the outline with an opening, and a few inner walls
WALLS = (
    (0, 0, 4, 0), (0, 0, 0, 4), (4, 0, 4, 3), (0, 4, 4, 4),
    (1, 0, 1, 2), (2, 1, 2, 3), (1, 3, 3, 3), (3, 1, 4, 1), (3, 2, 3, 3),
)
ROBOT_CELL = (0, 3)  # (column, row) of the cell the robot stands in


def render_icon(size: int) -> np.ndarray:
    """The (size, size, 3) RGB icon."""
    img = np.empty((size, size, 3), np.uint8)
    img[:] = BACKGROUND
    span = round(size * 0.52)  # the maze's side: its corners stay inside the 80 % safe circle
    cell = span // CELLS
    span = cell * CELLS
    x0 = y0 = (size - span) // 2
    half = max(1, round(cell * 0.09))  # half the wall thickness
    for ax, ay, bx, by in WALLS:
        c0, c1 = x0 + min(ax, bx) * cell - half, x0 + max(ax, bx) * cell + half
        r0, r1 = y0 + min(ay, by) * cell - half, y0 + max(ay, by) * cell + half
        img[r0:r1, c0:c1] = WALL
    cx = x0 + ROBOT_CELL[0] * cell + cell / 2
    cy = y0 + ROBOT_CELL[1] * cell + cell / 2
    rr, cc = np.mgrid[0:size, 0:size]
    img[(rr + 0.5 - cy) ** 2 + (cc + 0.5 - cx) ** 2 <= (cell * 0.28) ** 2] = ROBOT
    return img


def icon_png(size: int) -> bytes:
    return encode_png(render_icon(size))


def icon_path(size: int) -> Path:
    return REPO / "static" / "icons" / f"icon-{size}.png"


def main() -> int:
    for size in SIZES:
        write_atomic(icon_path(size), icon_png(size))
        print(icon_path(size).relative_to(REPO), icon_path(size).stat().st_size, "bytes")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
