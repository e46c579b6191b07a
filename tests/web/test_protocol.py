"""The websocket packet format: round trips, the documented byte layout, and refusals."""

from __future__ import annotations

import json
import struct
import zlib

import numpy as np
import pytest

from mazebot.web.protocol import (
    CODE_FREE,
    CODE_OCCUPIED,
    CODE_UNKNOWN,
    KIND_DELTA,
    KIND_FULL,
    CellsSection,
    GridSection,
    Packet,
    ProtocolError,
    decode_packet,
    encode_packet,
    parse_client_message,
    three_state_to_codes,
)


def test_full_packet_round_trips_map_and_status() -> None:
    rng = np.random.default_rng(4)
    codes = rng.integers(0, 3, size=(37, 53), dtype=np.uint8)
    status = {"state": "exploring", "pose": [0.1, -0.25, 1.5],
              "fault": {"source": "lidar", "message": "no data – check"}}
    packet = Packet(KIND_FULL, 4_000_000_000, status, GridSection(7, 0.02, (-1.04, -0.98), codes))
    back = decode_packet(encode_packet(packet))
    assert back.kind == KIND_FULL and back.seq == 4_000_000_000
    assert back.status == status
    assert isinstance(back.map, GridSection)
    assert back.map.epoch == 7 and back.map.resolution_m == 0.02 and back.map.origin_m == (-1.04, -0.98)
    np.testing.assert_array_equal(back.map.codes, codes)


def test_delta_packet_round_trips_changed_cells() -> None:
    indices = np.array([0, 5, 6, 70_000, 70_001, 1_000_000])
    codes = np.array([CODE_FREE, CODE_OCCUPIED, CODE_UNKNOWN, CODE_FREE, CODE_FREE, CODE_OCCUPIED], dtype=np.uint8)
    back = decode_packet(encode_packet(Packet(KIND_DELTA, 12, {"trail+": [0.1, 0.2]}, CellsSection(3, indices, codes))))
    assert back.kind == KIND_DELTA and back.seq == 12 and back.status == {"trail+": [0.1, 0.2]}
    assert isinstance(back.map, CellsSection) and back.map.epoch == 3
    np.testing.assert_array_equal(back.map.indices, indices)
    np.testing.assert_array_equal(back.map.codes, codes)


def test_packets_without_a_map_carry_only_status() -> None:
    for kind in (KIND_FULL, KIND_DELTA):
        back = decode_packet(encode_packet(Packet(kind, 1, {"state": "idle"})))
        assert back.map is None and back.status == {"state": "idle"}
    empty = decode_packet(encode_packet(Packet(KIND_DELTA, 2, {}, CellsSection(0, np.zeros(0, int), np.zeros(0, int)))))
    assert isinstance(empty.map, CellsSection) and len(empty.map) == 0


def test_byte_layout_is_the_one_docs_protocol_md_and_app_js_read() -> None:
    """Header: "MZ", version 1, kind, uint32 LE seq; then zlib(uint32 JSON length, JSON, section)."""
    codes = np.array([[0, 1], [2, 1]], dtype=np.uint8)
    data = encode_packet(Packet(KIND_FULL, 0x01020304, {"a": 1}, GridSection(9, 0.05, (1.5, -2.0), codes)))
    assert data[:8] == b"MZ\x01\x01\x04\x03\x02\x01"
    body = zlib.decompress(data[8:])
    (json_len,) = struct.unpack_from("<I", body)
    assert json.loads(body[4 : 4 + json_len]) == {"a": 1}
    section = body[4 + json_len :]
    assert section[:4] == b"\x01\x00\x00\x00"
    assert struct.unpack_from("<IIIddd", section, 4) == (9, 2, 2, 0.05, 1.5, -2.0)
    assert section[40:] == bytes([0, 1, 2, 1])  # row-major, row 0 (south) first

    delta = encode_packet(Packet(KIND_DELTA, 5, {}, CellsSection(9, np.array([3, 10, 11]), np.array([2, 1, 0]))))
    body = zlib.decompress(delta[8:])
    section = body[4 + struct.unpack_from("<I", body)[0] :]
    assert section[:4] == b"\x02\x00\x00\x00"
    assert struct.unpack_from("<II", section, 4) == (9, 3)
    assert struct.unpack_from("<3I", section, 12) == (3, 7, 1)  # index gaps, the first absolute
    assert section[24:] == bytes([2, 1, 0])


def test_three_state_values_become_wire_codes() -> None:
    three = np.array([[-1, 0], [100, 0]], dtype=np.int8)
    np.testing.assert_array_equal(three_state_to_codes(three), [[CODE_UNKNOWN, CODE_FREE], [CODE_OCCUPIED, CODE_FREE]])


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (b"MZ\x01", "shorter than"),
        (b"XX\x01\x01\x00\x00\x00\x00" + zlib.compress(b"\x02\x00\x00\x00{}"), "starts with"),
        (b"MZ\x02\x01\x00\x00\x00\x00" + zlib.compress(b"\x02\x00\x00\x00{}"), "protocol version 2"),
        (b"MZ\x01\x07\x00\x00\x00\x00" + zlib.compress(b"\x02\x00\x00\x00{}"), "unknown packet kind"),
        (b"MZ\x01\x01\x00\x00\x00\x00" + b"not zlib", "zlib"),
        (b"MZ\x01\x01\x00\x00\x00\x00" + zlib.compress(b"\xff\x00\x00\x00{}"), "overruns"),
        (b"MZ\x01\x01\x00\x00\x00\x00" + zlib.compress(b"\x02\x00\x00\x00{}\x09"), "unknown map section"),
    ],
)
def test_malformed_packets_are_refused_with_a_reason(data: bytes, match: str) -> None:
    with pytest.raises(ProtocolError, match=match):
        decode_packet(data)


def test_truncated_grid_and_kind_mismatches_are_refused() -> None:
    full = encode_packet(Packet(KIND_FULL, 1, {}, GridSection(1, 0.02, (0, 0), np.zeros((4, 4), np.uint8))))
    body = zlib.decompress(full[8:])
    with pytest.raises(ProtocolError, match="cell bytes"):
        decode_packet(full[:8] + zlib.compress(body[:-1]))
    with pytest.raises(ProtocolError, match="full packet carries the whole grid"):
        encode_packet(Packet(KIND_FULL, 1, {}, CellsSection(1, np.array([1]), np.array([1]))))
    with pytest.raises(ProtocolError, match="delta packet carries changed cells"):
        encode_packet(Packet(KIND_DELTA, 1, {}, GridSection(1, 0.02, (0, 0), np.zeros((1, 1), np.uint8))))
    with pytest.raises(ProtocolError, match="ascending"):
        encode_packet(Packet(KIND_DELTA, 1, {}, CellsSection(1, np.array([5, 3]), np.array([1, 1]))))
    with pytest.raises(ProtocolError, match="cannot carry"):  # a full header over a cells section
        delta = encode_packet(Packet(KIND_DELTA, 1, {}, CellsSection(1, np.array([1]), np.array([1]))))
        decode_packet(delta[:3] + bytes([KIND_FULL]) + delta[4:])


def test_client_messages_parse_and_bad_ones_say_what_is_expected() -> None:
    assert parse_client_message('{"type":"resync"}').type == "resync"
    msg = parse_client_message('{"type":"start","token":"1234"}')
    assert (msg.type, msg.token) == ("start", "1234")
    assert parse_client_message('{"type":"stop"}').token is None
    for text, match in [
        ("start", "not JSON"),
        ("[1]", "JSON object"),
        ('{"type":"fly"}', "unknown message type 'fly'"),
        ('{"type":"stop","token":1234}', "token must be a string"),
    ]:
        with pytest.raises(ProtocolError, match=match):
            parse_client_message(text)
