"""Fixtures for the web tests: a grid whose cells a test sets, and a client that mirrors the map."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from mazebot.web.protocol import KIND_FULL, CellsSection, GridSection, decode_packet, three_state_to_codes


class FakeGrid:
    """Shaped like :class:`mazebot.slam.grid.OccupancyGrid` for the web layer: cells set by the test."""

    def __init__(self, rows: int = 40, cols: int = 60, resolution_m: float = 0.02,
                 origin_m: tuple[float, float] = (-0.6, -0.4)) -> None:
        self.cells = np.full((rows, cols), -1, dtype=np.int8)
        self.resolution_m = resolution_m
        self.origin_m = origin_m
        self.generation = 0

    @property
    def shape(self) -> tuple[int, int]:
        return self.cells.shape  # type: ignore[return-value]

    def three_state(self) -> np.ndarray:
        return self.cells.copy()

    def grow(self, rows: int, cols: int, shift: tuple[int, int] = (5, 5)) -> None:
        grown = np.full((rows, cols), -1, dtype=np.int8)
        r, c = self.cells.shape
        grown[shift[0] : shift[0] + r, shift[1] : shift[1] + c] = self.cells
        self.cells = grown
        res = self.resolution_m
        self.origin_m = (self.origin_m[0] - shift[1] * res, self.origin_m[1] - shift[0] * res)
        self.generation += 1


class Mirror:
    """What a correct page does: apply full maps, apply deltas only in sequence, else want a resync."""

    def __init__(self) -> None:
        self.seq: int | None = None
        self.epoch: int | None = None
        self.codes: np.ndarray | None = None
        self.status: dict[str, Any] = {}
        self.kinds: list[tuple[int, int]] = []  # (seq, kind) of every packet applied
        self.gaps = 0

    def apply(self, data: bytes) -> bool:
        """Apply one packet; False if it revealed a gap (the page would send resync)."""
        p = decode_packet(data)
        if p.kind == KIND_FULL:
            self.status = {}
            if isinstance(p.map, GridSection):
                self.epoch, self.codes = p.map.epoch, p.map.codes.copy()
            else:
                self.epoch, self.codes = None, None
        else:
            if self.seq is None or p.seq != self.seq + 1:
                self.gaps += 1
                return False
            if isinstance(p.map, CellsSection):
                assert p.map.epoch == self.epoch and self.codes is not None
                self.codes.reshape(-1)[p.map.indices] = p.map.codes
        for key, value in p.status.items():
            if key == "trail+":
                self.status["trail"] = self.status.get("trail", []) + value
            else:
                self.status[key] = value
        self.seq = p.seq
        self.kinds.append((p.seq, p.kind))
        return True

    def matches(self, grid: FakeGrid) -> bool:
        return self.codes is not None and np.array_equal(self.codes, three_state_to_codes(grid.three_state()))


@pytest.fixture
def fake_grid() -> type[FakeGrid]:
    return FakeGrid


@pytest.fixture
def mirror() -> type[Mirror]:
    return Mirror
