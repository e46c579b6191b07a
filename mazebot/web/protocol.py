"""The websocket protocol between the daemon and the page, as pure functions (``docs/protocol.md``).

Server → client, one binary frame per packet::

    offset  size  field
    0       2     magic b"MZ"
    2       1     protocol version (1)
    3       1     kind: 1 full, 2 delta
    4       4     sequence number, uint32 little-endian
    8       ...   zlib stream (RFC 1950) of the body

    body:   uint32 JSON length, JSON (UTF-8, the status), then an optional map section:
    grid    uint8 1, 3 pad, uint32 epoch, uint32 rows, uint32 cols,
            float64 resolution_m, float64 origin_x_m, float64 origin_y_m,
            rows × cols uint8 cell codes, row-major, row 0 south
    cells   uint8 2, 3 pad, uint32 epoch, uint32 count,
            count × uint32 index gaps (flat index row × cols + col; the first is absolute),
            count × uint8 cell codes

Cell codes: 0 unknown, 1 free, 2 occupied. ``epoch`` names the grid geometry a delta's
indices refer to; it changes whenever the grid is reallocated or rebuilt, after which
only a full map makes sense.

Client → server and the server's replies are small JSON text frames (see
:func:`parse_client_message`). Nothing here touches a socket.
"""

from __future__ import annotations

import json
import struct
import zlib
from dataclasses import dataclass, field
from typing import Any

import numpy as np

PROTOCOL_VERSION = 1
MAGIC = b"MZ"
KIND_FULL = 1
KIND_DELTA = 2
SECTION_GRID = 1
SECTION_CELLS = 2

CODE_UNKNOWN = 0
CODE_FREE = 1
CODE_OCCUPIED = 2

#: Client → server message types; start and stop need the control token.
CLIENT_TYPES = frozenset({"start", "stop", "resync"})

_HEADER = struct.Struct("<2sBBI")
_GRID = struct.Struct("<B3xIIIddd")
_CELLS = struct.Struct("<B3xII")
_U32 = struct.Struct("<I")


class ProtocolError(ValueError):
    """A packet or message that does not follow ``docs/protocol.md``."""


@dataclass(frozen=True)
class GridSection:
    """A whole map: ``codes`` uint8 (rows, cols), row 0 south, in the frame of ``epoch``."""

    epoch: int
    resolution_m: float
    origin_m: tuple[float, float]
    codes: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.codes.shape


@dataclass(frozen=True)
class CellsSection:
    """Changed cells: flat indices (uint32, ascending) into the grid of ``epoch``, new codes (uint8)."""

    epoch: int
    indices: np.ndarray
    codes: np.ndarray

    def __len__(self) -> int:
        return int(self.indices.shape[0])


@dataclass(frozen=True)
class Packet:
    """One server → client packet: a full map (``KIND_FULL``) or a delta (``KIND_DELTA``)."""

    kind: int
    seq: int
    status: dict[str, Any] = field(default_factory=dict)
    map: GridSection | CellsSection | None = None


def three_state_to_codes(three_state: np.ndarray) -> np.ndarray:
    """Wire codes (uint8) of an occupancy grid's three-state array (-1 unknown, 0 free, 100 occupied)."""
    t = np.asarray(three_state)
    codes = np.zeros(t.shape, dtype=np.uint8)
    codes[t == 0] = CODE_FREE
    codes[t == 100] = CODE_OCCUPIED
    return codes


def encode_packet(packet: Packet, level: int = 6) -> bytes:
    """The bytes of one binary websocket frame."""
    if packet.kind not in (KIND_FULL, KIND_DELTA):
        raise ProtocolError(f"packet kind must be {KIND_FULL} (full) or {KIND_DELTA} (delta), got {packet.kind}")
    if packet.kind == KIND_DELTA and isinstance(packet.map, GridSection):
        raise ProtocolError("a delta packet carries changed cells, not a whole grid")
    if packet.kind == KIND_FULL and isinstance(packet.map, CellsSection):
        raise ProtocolError("a full packet carries the whole grid, not changed cells")
    status = json.dumps(packet.status, separators=(",", ":"), allow_nan=False).encode()
    parts = [_U32.pack(len(status)), status]
    section = packet.map
    if isinstance(section, GridSection):
        rows, cols = section.shape
        ox, oy = section.origin_m
        parts.append(_GRID.pack(SECTION_GRID, section.epoch, rows, cols, section.resolution_m, ox, oy))
        parts.append(np.ascontiguousarray(section.codes, dtype=np.uint8).tobytes())
    elif isinstance(section, CellsSection):
        idx = np.asarray(section.indices, dtype=np.int64)
        if idx.size and (idx[0] < 0 or np.any(np.diff(idx) <= 0)):
            raise ProtocolError("cell indices must be non-negative and strictly ascending")
        gaps = np.diff(idx, prepend=0).astype("<u4")  # small numbers: deflate shrinks them well
        parts.append(_CELLS.pack(SECTION_CELLS, section.epoch, idx.size))
        parts.append(gaps.tobytes())
        parts.append(np.asarray(section.codes, dtype=np.uint8).tobytes())
    elif section is not None:
        raise ProtocolError(f"unknown map section {type(section).__name__}")
    header = _HEADER.pack(MAGIC, PROTOCOL_VERSION, packet.kind, packet.seq & 0xFFFFFFFF)
    return header + zlib.compress(b"".join(parts), level)


def decode_packet(data: bytes) -> Packet:
    """Parse one binary frame (the page does the same in ``static/app.js``)."""
    if len(data) < _HEADER.size:
        raise ProtocolError(f"packet of {len(data)} bytes is shorter than its {_HEADER.size}-byte header")
    magic, version, kind, seq = _HEADER.unpack_from(data)
    if magic != MAGIC:
        raise ProtocolError(f"packet starts with {magic!r}, expected {MAGIC!r}")
    if version != PROTOCOL_VERSION:
        raise ProtocolError(f"protocol version {version}, this side speaks {PROTOCOL_VERSION}")
    if kind not in (KIND_FULL, KIND_DELTA):
        raise ProtocolError(f"unknown packet kind {kind}")
    try:
        body = zlib.decompress(data[_HEADER.size :])
    except zlib.error as exc:
        raise ProtocolError(f"packet body is not a zlib stream ({exc})") from None
    if len(body) < 4:
        raise ProtocolError("packet body has no status length")
    (json_len,) = _U32.unpack_from(body)
    end = 4 + json_len
    if end > len(body):
        raise ProtocolError(f"status of {json_len} bytes overruns a body of {len(body)}")
    status = json.loads(body[4:end])
    section: GridSection | CellsSection | None = None
    rest = body[end:]
    if rest:
        section = _decode_section(rest)
    if (kind == KIND_FULL and isinstance(section, CellsSection)) or (
        kind == KIND_DELTA and isinstance(section, GridSection)
    ):
        raise ProtocolError(f"packet kind {kind} cannot carry map section {type(section).__name__}")
    return Packet(kind, seq, status, section)


def _decode_section(rest: bytes) -> GridSection | CellsSection:
    if rest[0] == SECTION_GRID:
        if len(rest) < _GRID.size:
            raise ProtocolError("grid section header is truncated")
        _, epoch, rows, cols, res, ox, oy = _GRID.unpack_from(rest)
        cells = rest[_GRID.size :]
        if len(cells) != rows * cols:
            raise ProtocolError(f"grid of {rows}x{cols} needs {rows * cols} cell bytes, got {len(cells)}")
        codes = np.frombuffer(cells, dtype=np.uint8).reshape(rows, cols)
        return GridSection(epoch, res, (ox, oy), codes)
    if rest[0] == SECTION_CELLS:
        if len(rest) < _CELLS.size:
            raise ProtocolError("cells section header is truncated")
        _, epoch, count = _CELLS.unpack_from(rest)
        payload = rest[_CELLS.size :]
        if len(payload) != 5 * count:
            raise ProtocolError(f"{count} changed cells need {5 * count} bytes, got {len(payload)}")
        gaps = np.frombuffer(payload[: 4 * count], dtype="<u4").astype(np.int64)
        codes = np.frombuffer(payload[4 * count :], dtype=np.uint8)
        return CellsSection(epoch, np.cumsum(gaps), codes)
    raise ProtocolError(f"unknown map section type {rest[0]}")


@dataclass(frozen=True)
class ClientMessage:
    """A parsed client → server message: ``type`` is start, stop or resync."""

    type: str
    token: str | None = None


def parse_client_message(text: str) -> ClientMessage:
    """``{"type": "start"|"stop", "token": "…"}`` or ``{"type": "resync"}``; anything else raises."""
    try:
        obj = json.loads(text)
    except ValueError:
        raise ProtocolError("message is not JSON; expected {\"type\": \"start\"|\"stop\"|\"resync\", …}") from None
    except RecursionError:  # "[[[[…" nested deeper than Python's recursion limit
        raise ProtocolError("message is nested too deeply; expected a flat JSON object") from None
    if not isinstance(obj, dict):
        raise ProtocolError(f"message must be a JSON object, got {type(obj).__name__}")
    kind = obj.get("type")
    if kind is not None and not isinstance(kind, str):  # a list or object there is not even hashable
        raise ProtocolError(f"message type must be a string, got {type(kind).__name__}")
    if kind not in CLIENT_TYPES:
        shown = kind if kind is None else _shown(kind)
        raise ProtocolError(f"unknown message type {shown!r}; expected start, stop or resync")
    token = obj.get("token")
    if token is not None and not isinstance(token, str):
        raise ProtocolError("token must be a string")
    return ClientMessage(kind, token)


#: The longest the client's own words may be in an error, quoted and escaped ('x' * 40 + "…").
SHOWN_CHARS = 43


def _shown(text: str) -> str:
    """``text`` cut (with "…") so that its repr fits in :data:`SHOWN_CHARS`: the client's own words,
    kept short even when each of them is a control or an unprintable character (``\\U000e0001``)."""
    if len(repr(text)) <= SHOWN_CHARS:
        return text
    lo, hi = 0, min(len(text), SHOWN_CHARS)  # the longest prefix whose repr, with "…", fits
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if len(repr(text[:mid] + "…")) <= SHOWN_CHARS:
            lo = mid
        else:
            hi = mid - 1
    return text[:lo] + "…"


def server_message(kind: str, **fields: Any) -> str:
    """A JSON text frame from the server (hello, reply, heartbeat, error)."""
    return json.dumps({"type": kind, **fields}, separators=(",", ":"))
