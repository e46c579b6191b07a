"""The one PNG encoder: greyscale maps and colour figures, read back chunk by chunk."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest

from mazebot.png import encode_png


def _decode(data: bytes) -> tuple[int, np.ndarray]:
    """(colour type, pixels) of a PNG of filter-0 rows, checking every chunk's CRC (ISO/IEC 15948, 5.3)."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, chunks = 8, {}
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length : pos + 12 + length])
        assert crc == zlib.crc32(kind + body) & 0xFFFFFFFF, kind
        chunks[kind] = body
        pos += 12 + length
    assert list(chunks) == [b"IHDR", b"IDAT", b"IEND"]
    w, h, depth, colour, _, _, _ = struct.unpack(">IIBBBBB", chunks[b"IHDR"])
    assert depth == 8
    channels = 1 if colour == 0 else 3
    rows = np.frombuffer(zlib.decompress(chunks[b"IDAT"]), np.uint8).reshape(h, 1 + w * channels)
    assert not rows[:, 0].any()  # filter type 0 on every row
    pixels = rows[:, 1:].reshape(h, w) if channels == 1 else rows[:, 1:].reshape(h, w, 3)
    return colour, pixels


def test_a_greyscale_map_and_a_colour_figure_come_back_as_they_were() -> None:
    rng = np.random.default_rng(1)
    grey = rng.integers(0, 256, (7, 5), dtype=np.uint8)
    rgb = rng.integers(0, 256, (4, 9, 3), dtype=np.uint8)
    colour, back = _decode(encode_png(grey))
    assert colour == 0 and np.array_equal(back, grey)
    colour, back = _decode(encode_png(rgb))
    assert colour == 2 and np.array_equal(back, rgb)


def test_a_greyscale_map_is_a_third_of_its_colour_copy_before_compression() -> None:
    grey = np.full((30, 40), 205, np.uint8)
    assert len(zlib.decompress(_decode_idat(encode_png(grey)))) * 3 - 2 * 30 == len(
        zlib.decompress(_decode_idat(encode_png(np.repeat(grey[..., None], 3, axis=2))))
    )


def _decode_idat(data: bytes) -> bytes:
    pos = 8
    while True:
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        if data[pos + 4 : pos + 8] == b"IDAT":
            return data[pos + 8 : pos + 8 + length]
        pos += 12 + length


@pytest.mark.parametrize("bad", [np.zeros((3, 3), np.float32), np.zeros((3, 3, 4), np.uint8), np.zeros(5, np.uint8)])
def test_what_is_not_an_image_is_refused_by_shape_and_type(bad: np.ndarray) -> None:
    with pytest.raises(ValueError, match="expected an"):
        encode_png(bad)
