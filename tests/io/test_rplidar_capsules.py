"""Ultra, dense and ultra-dense capsules and GET_LIDAR_CONF, against bytes laid out by
hand from the layouts of Slamtec's SDK (sdk/include/sl_lidar_cmd.h) and the SDK's
arithmetic (sdk/src/dataunpacker/unpacker/handler_capsules.cpp) redone here, scalar,
sample by sample, independently of the vectorized decoder."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from mazebot.errors import ProtocolError
from mazebot.io import rplidar_protocol as proto


def decode_all(fmt: proto.CapsuleFormat, data: bytes) -> proto.DecodedSamples:
    dec = proto.ExpressScanDecoder(fmt)
    return proto.DecodedSamples.concat([dec.feed(data), dec.flush()])


def with_checksum(body: bytes) -> bytes:
    cs = 0
    for b in body:
        cs ^= b
    return bytes([0xA0 | cs & 0xF, 0x50 | cs >> 4]) + body


# --- ultra capsules (A1/A2/A3 Boost, Sensitivity, Stability) -------------------------


def vbs(scaled: int) -> tuple[int, int]:
    """The SDK's variable bit scale, scalar: (mm, level)."""
    for base, level, target in ((3328, 4, 1 << 14), (1792, 3, 1 << 12), (1280, 2, 1 << 11), (512, 1, 1 << 9)):
        if scaled >= base:
            return target + ((scaled - base) << level), level
    return scaled, 0


def sdk_ultra_offset_q16(dist_q2: int) -> int:
    if dist_q2 >= 200:
        k2 = 98361 // dist_q2
        rad = int(8 * 3.1415926535 * 65536 / 180) - (k2 << 6) - (k2 * k2 * k2) // 98304
    else:
        rad = int(7.5 * 3.1415926535 * 65536 / 180.0)
    return int(rad * 180 / 3.14159265)


def ultra_word(major: int, p1: int, p2: int) -> int:
    return major | (p1 & 0x3FF) << 12 | (p2 & 0x3FF) << 22


def test_ultra_capsule_by_hand() -> None:
    # start 100°, next 112°: diff 3072 q8, increment (3072 << 3) / 3 = 8192 q16 = 0.125°
    words = [ultra_word(300, 5, -3), ultra_word(600, 0, 0)] + [ultra_word(0, -512, -512)] * 30
    a = with_checksum(struct.pack("<H", 100 * 64) + struct.pack("<32I", *words))
    b = with_checksum(struct.pack("<H", 112 * 64) + struct.pack("<32I", *[ultra_word(0, -512, -512)] * 32))
    assert len(a) == 132
    out = decode_all(proto.ULTRA_CAPSULE, a + b)
    assert len(out) == 96
    # cabin 0: major 300 (scale 1: 300 mm), +5 -> 305 mm; the third refers to the next
    # cabin's major 600 = 512 + 88 * 2 = 688 mm at level 1: -3 << 1 + 688 = 682 mm
    assert vbs(600) == (688, 1)
    assert out.dist_mm[:4].tolist() == [300.0, 305.0, 682.0, 688.0]
    # cabin 1: prediction 1 is 0 on its own 688 mm, prediction 2 is 0 on the next
    # cabin's major, which is 0 (no return): 0 + 0 = 0
    assert out.dist_mm[4:6].tolist() == [688.0, 0.0]
    assert not out.dist_mm[6:].any()  # majors 0 and predictions "invalid" (-512)
    for i, d_mm in enumerate([300, 305, 682, 688]):
        raw_q16 = (100 << 16) + i * 8192
        expected_q6 = (raw_q16 - sdk_ultra_offset_q16(d_mm * 4)) >> 10
        assert out.angle_deg[i] == expected_q6 / 64
    # the offset is the triangulation's: 3.5° at 0.3 m, 5.3° at 0.5 m, 6.7° at 1 m,
    # 8° far away (an A1's legacy capsules carry 40-52 q3, 5-6.5°, at 0.5-1 m)
    assert math.isclose(sdk_ultra_offset_q16(300 * 4) / 65536, 3.46, abs_tol=0.01)
    assert math.isclose(sdk_ultra_offset_q16(500 * 4) / 65536, 5.26, abs_tol=0.01)
    assert math.isclose(sdk_ultra_offset_q16(1000 * 4) / 65536, 6.66, abs_tol=0.01)
    assert math.isclose(sdk_ultra_offset_q16(100000 * 4) / 65536, 8.0, abs_tol=0.01)


def test_ultra_encoder_round_trips_within_the_scale() -> None:
    rng = np.random.default_rng(4)
    dists = [np.clip(2000 + np.cumsum(rng.normal(0, 15, 96)), 200, 12000) for _ in range(6)]
    caps = b"".join(proto.encode_ultra_capsule((10 + 12 * k) % 360, dists[k], start=k == 0) for k in range(6))
    out = decode_all(proto.ULTRA_CAPSULE, caps)
    assert len(out) == 5 * 96
    got = out.dist_mm.reshape(5, 96)
    want = np.array(dists[:5])
    valid = got > 0
    assert valid.mean() > 0.95  # only the last sample of each capsule may be lost
    np.testing.assert_allclose(got[valid], want[valid], atol=4.0)  # 2 mm units below 4 m


# --- dense capsules (C1, S1/S2 DenseBoost) --------------------------------------------


def test_dense_capsule_by_hand() -> None:
    # start 200°, next 208°: diff 2048 q8, increment (2048 << 8) / 40 = 13107 q16
    dists = list(range(1000, 1040))
    a = with_checksum(struct.pack("<H", 200 * 64) + struct.pack("<40H", *dists))
    b = with_checksum(struct.pack("<H", 208 * 64) + bytes(80))
    out = decode_all(proto.DENSE_CAPSULE, a + b)
    assert out.dist_mm.tolist() == [float(d) for d in dists]
    assert out.angle_deg.tolist() == [(((200 << 16) + i * 13107) >> 10) / 64 for i in range(40)]
    assert out.angle_deg[39] == 207.796875  # no compensation: a time-of-flight head
    assert not out.start.any()


def test_dense_sync_flag_is_set_once_per_revolution() -> None:
    # start 356°, next 4°: increment (2048 << 8) / 40 = 13107 q16, a hair under 0.2°
    # (C division truncates), so sample 19 + inc stays below 360° and the SDK's test
    # ((raw + inc) mod 360 < 2 inc) first holds for samples 20 and 21; its edge
    # detection keeps only the first
    a = with_checksum(struct.pack("<H", 356 * 64) + struct.pack("<40H", *[500] * 40))
    b = with_checksum(struct.pack("<H", 4 * 64) + struct.pack("<40H", *[500] * 40))
    c = with_checksum(struct.pack("<H", 12 * 64) + bytes(80))
    out = decode_all(proto.DENSE_CAPSULE, a + b + c)
    assert np.flatnonzero(out.start).tolist() == [20]
    assert out.angle_deg[20] == (((356 << 16) + 20 * 13107) >> 10) / 64 == 359.984375


# --- ultra-dense capsules -------------------------------------------------------------


def test_ultra_dense_capsule_by_hand() -> None:
    # scale 0: 2 mm units; scale 1: 3 mm above 2046 mm; scale 2: 4 mm above 8187 mm
    def word(scale: int, units: int, quality: int) -> int:
        return units << 2 | scale | quality << (12 + scale)

    w = [word(0, 250, 10), word(1, 1000, 5), word(2, 100, 3), word(3, 7, 1)] + [0] * 60
    cabins = b"".join(
        struct.pack("<HHB", w[2 * k] & 0xFFFF, w[2 * k + 1] & 0xFFFF, (w[2 * k] >> 16) | (w[2 * k + 1] >> 16) << 4)
        for k in range(32)
    )
    a = with_checksum(struct.pack("<IHH", 123456, 0, 50 * 64) + cabins)
    b = with_checksum(struct.pack("<IHH", 123999, 0, 54 * 64) + bytes(160))
    assert len(a) == 170
    out = decode_all(proto.ULTRA_DENSE_CAPSULE, a + b)
    assert len(out) == 64
    assert out.dist_mm[:4].tolist() == [500.0, 2046 + 3000.0, 8187 + 400.0, 24567 + 35.0]
    # start 50°, next 54°: increment (1024 << 8) / 64 = 4096 q16 = 1/16°
    assert out.angle_deg[:3].tolist() == [50.0, 50.0625, 50.125]


def test_ultra_dense_encoder_round_trips() -> None:
    rng = np.random.default_rng(2)
    dists = [rng.integers(0, 3000, 64) * 10.0 for _ in range(4)]
    caps = b"".join(proto.encode_ultra_dense_capsule(5.0 * k, dists[k], start=k == 0) for k in range(4))
    out = decode_all(proto.ULTRA_DENSE_CAPSULE, caps)
    np.testing.assert_allclose(out.dist_mm, np.concatenate(dists[:3]), atol=5.0)


# --- GET_LIDAR_CONF -------------------------------------------------------------------


def test_conf_request_is_what_the_sdk_sends() -> None:
    # type u32 + 32 reserved bytes (mode id in the first two), as sl_lidar_driver.cpp
    req = proto.build_conf_request(proto.CONF_SCAN_MODE_NAME, 3)
    assert req[:3] == bytes([0xA5, 0x84, 36])
    assert req[3:7] == b"\x7f\x00\x00\x00" and req[7:9] == b"\x03\x00" and req[9:39] == bytes(30)
    cmd, payload, used = proto.parse_request(req)
    assert (cmd, used) == (0x84, len(req))
    assert proto.parse_conf_request(payload) == (0x7F, 3)


def test_conf_answers_of_a_real_a1() -> None:
    # GET_LIDAR_CONF answers of an A1M8, firmware 1.29, as listed in the comment of
    # thijses/rplidar, thijs_rplidar.h (read from a unit bought in 2022):
    # Standard 130048 q8 us = 508 us, max 3072 q8 m = 12 m, answer 0x81; Boost 32512 = 127 us
    assert proto.decode_mode_conf(proto.CONF_SCAN_MODE_US_PER_SAMPLE, struct.pack("<I", 130048)) == 508.0
    assert proto.decode_mode_conf(proto.CONF_SCAN_MODE_US_PER_SAMPLE, struct.pack("<I", 32512)) == 127.0
    assert proto.decode_mode_conf(proto.CONF_SCAN_MODE_MAX_DISTANCE, struct.pack("<I", 3072)) == 12.0
    assert proto.decode_mode_conf(proto.CONF_SCAN_MODE_NAME, b"Sensitivity\0") == "Sensitivity"
    answer = proto.encode_conf_answer(proto.CONF_SCAN_MODE_COUNT, struct.pack("<H", 5))
    assert proto.decode_mode_conf(proto.CONF_SCAN_MODE_COUNT,
                                  proto.parse_conf_answer(answer, proto.CONF_SCAN_MODE_COUNT)) == 5
    with pytest.raises(ProtocolError, match="expected type 0x70, found 0x7c"):
        proto.parse_conf_answer(proto.encode_conf_answer(0x7C, b"\0\0"), 0x70)


def test_scan_decoder_by_answer_type() -> None:
    assert isinstance(proto.scan_decoder(0x81), proto.StandardScanDecoder)
    for t, fmt in ((0x82, proto.LEGACY_CAPSULE), (0x84, proto.ULTRA_CAPSULE), (0x85, proto.DENSE_CAPSULE),
                   (0x86, proto.ULTRA_DENSE_CAPSULE)):
        dec = proto.scan_decoder(t)
        assert isinstance(dec, proto.ExpressScanDecoder) and dec.format is fmt
    with pytest.raises(ProtocolError, match="0x83"):
        proto.scan_decoder(0x83)
