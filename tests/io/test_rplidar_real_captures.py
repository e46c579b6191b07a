"""Capsules and answers recorded from real RPLidar units, decoded by the project's decoders
and checked against Slamtec's SDK arithmetic redone here, scalar, sample by sample (read
from sdk/src/dataunpacker/unpacker/handler_capsules.cpp, vendored in Slamtec/rplidar_ros),
and against the samples the bytes' publisher printed for them.

Where the bytes come from, and what is and is not known about the units: data/README.md.
"""

from __future__ import annotations

import csv
import itertools
import math
import struct
from pathlib import Path

import numpy as np
import pytest

from mazebot.io import rplidar_models
from mazebot.io import rplidar_protocol as proto

DATA = Path(__file__).parent / "data"
FULL_TURN_Q6 = 360 << 6
FULL_TURN_Q16 = 360 << 16
#: The SDK's quality for a capsule sample with a distance (0x2F << 2).
SDK_QUALITY = 0x2F << 2
#: Published angles are angle_z_q14 = (angle_q6 << 8) / 90, truncated: at most 1/64° off.
ONE_Q6_DEG = 1 / 64


def load_capsules(name: str) -> list[bytes]:
    lines = (DATA / name).read_text().splitlines()
    return [bytes.fromhex(line) for line in lines if line and not line.startswith("#")]


def load_expected(name: str) -> np.ndarray:
    """(flag, quality, angle_z_q14, dist_mm_q2) rows."""
    lines = [line for line in (DATA / name).read_text().splitlines() if not line.startswith("#")]
    rows = list(csv.reader(lines))
    assert rows[0] == ["flag", "quality", "angle_z_q14", "dist_mm_q2"]
    return np.array(rows[1:], dtype=np.int64)


def start_q6(capsule: bytes) -> int:
    return (capsule[2] | capsule[3] << 8) & 0x7FFF


def interpolation(prev: bytes, cur: bytes, num: int, den: int) -> tuple[int, int]:
    """The SDK's first raw angle (q16) and increment per sample: start angles to q8, the
    difference wrapped once, times num / den."""
    prev_q8, cur_q8 = start_q6(prev) << 2, start_q6(cur) << 2
    diff_q8 = cur_q8 - prev_q8 + ((360 << 8) if prev_q8 > cur_q8 else 0)
    return prev_q8 << 8, (diff_q8 << 3) * num // den


def revolution_flag(raw_q16: int, inc_q16: int) -> int:
    """1 on the sample whose successor's uncompensated angle has passed 360°."""
    return 1 if (raw_q16 + inc_q16) % FULL_TURN_Q16 < inc_q16 else 0


def sdk_legacy(prev: bytes, cur: bytes) -> list[tuple[int, int, int]]:
    """(flag, angle_q6, dist_q2) of capsule ``prev``'s 32 samples, as
    UnpackerHandler_CapsuleNode::_onScanNodeCapsuleData makes them: 16 cabins of two
    distance words (low 2 bits: the compensation's bits 4-5) and one byte holding both
    compensations' low nibbles; the compensation is unsigned q3 and subtracted."""
    raw, inc = interpolation(prev, cur, 1, 1)
    out = []
    for cabin in range(16):
        c = prev[4 + 5 * cabin : 9 + 5 * cabin]
        words = (c[0] | c[1] << 8, c[2] | c[3] << 8)
        comps = ((c[4] & 0xF) | (words[0] & 0x3) << 4, (c[4] >> 4) | (words[1] & 0x3) << 4)
        for word, comp_q3 in zip(words, comps, strict=True):
            angle_q6 = ((raw - (comp_q3 << 13)) >> 10) % FULL_TURN_Q6
            out.append((revolution_flag(raw, inc), angle_q6, word & 0xFFFC))
            raw += inc
    return out


def sdk_varbitscale(scaled: int) -> tuple[int, int]:
    """(mm, scale level): thresholds and bases of RPLIDAR_VARBITSCALE_* in sl_lidar_cmd.h."""
    for base, level, target in ((3328, 4, 1 << 14), (1792, 3, 1 << 12), (1280, 2, 1 << 11), (512, 1, 1 << 9)):
        if scaled >= base:
            return target + ((scaled - base) << level), level
    return scaled, 0


def signed10(x: int) -> int:
    return x - 1024 if x & 0x200 else x


def sdk_ultra_offset_q16(dist_q2: int) -> int:
    """The SDK's angle offset for an ultra sample, from its range (radians q16 turned to
    degrees q16 with the SDK's own constants and truncations)."""
    rad_q16 = int(7.5 * 3.1415926535 * (1 << 16) / 180.0)
    if dist_q2 >= 50 * 4:
        k2 = 98361 // dist_q2
        rad_q16 = int(8 * 3.1415926535 * (1 << 16) / 180) - (k2 << 6) - (k2 * k2 * k2) // 98304
    return int(rad_q16 * 180 / 3.14159265)


def sdk_ultra(prev: bytes, cur: bytes) -> list[tuple[int, int, int]]:
    """(flag, angle_q6, dist_q2) of capsule ``prev``'s 96 samples, as
    UnpackerHandler_UltraCapsuleNode::_onScanNodeUltraCapsuleData makes them: 32 words of
    a 12-bit scaled major distance and two signed 10-bit predictions (0x1FF and -512: no
    return). The first prediction builds on this major, or on the next one where this one
    is 0; the second on the next major (the next capsule's first after the 32nd word)."""
    raw, inc = interpolation(prev, cur, 1, 3)
    words = struct.unpack("<32I", prev[4:132])
    first_next = struct.unpack_from("<I", cur, 4)[0]
    out = []
    for pos, word in enumerate(words):
        major, level1 = sdk_varbitscale(word & 0xFFF)
        major2, level2 = sdk_varbitscale((words[pos + 1] if pos < 31 else first_next) & 0xFFF)
        base1, base2 = major, major2
        if major == 0 and major2 != 0:
            base1, level1 = major2, level2
        dists = [major << 2]
        for predict, base, level in ((signed10(word >> 12 & 0x3FF), base1, level1),
                                     (signed10(word >> 22 & 0x3FF), base2, level2)):
            dists.append(0 if predict in (-512, 511) else ((predict << level) + base) << 2)
        for dist_q2 in dists:
            flag = revolution_flag(raw, inc)
            angle_q6 = ((raw - sdk_ultra_offset_q16(dist_q2)) >> 10) % FULL_TURN_Q6
            out.append((flag, angle_q6, dist_q2))
            raw += inc
    return out


def decode(fmt: proto.CapsuleFormat, data: bytes, chunk: int | None = None) -> tuple[proto.DecodedSamples, int]:
    """Every sample of ``data`` (fed ``chunk`` bytes at a time), and the bytes dropped."""
    dec = proto.ExpressScanDecoder(fmt)
    step = chunk or len(data)
    parts = [dec.feed(data[i : i + step]) for i in range(0, len(data), step)]
    parts.append(dec.flush())
    return proto.DecodedSamples.concat(parts), dec.bytes_dropped


def sdk_reference(recipe, capsules: list[bytes]) -> np.ndarray:
    """The SDK's samples of every capsule that has a successor: (flag, angle_q6, dist_q2) rows."""
    return np.array([s for prev, cur in itertools.pairwise(capsules) for s in recipe(prev, cur)])


def angle_error_deg(a_deg: np.ndarray, b_deg: np.ndarray) -> np.ndarray:
    return np.abs((np.asarray(a_deg) - np.asarray(b_deg) + 180.0) % 360.0 - 180.0)


CAPTURES = {
    # name: (format, capsule file, expected file, the SDK's recipe redone here)
    "express": (proto.LEGACY_CAPSULE, "pyrplidar_express_capsules.txt", "pyrplidar_express_expected.csv", sdk_legacy),
    "ultra": (proto.ULTRA_CAPSULE, "pyrplidar_ultra_capsules.txt", "pyrplidar_ultra_expected.csv", sdk_ultra),
}


@pytest.mark.parametrize("name", sorted(CAPTURES))
def test_real_capsules_decode_to_the_sdks_samples(name: str) -> None:
    fmt, capsule_file, _, recipe = CAPTURES[name]
    capsules = load_capsules(capsule_file)
    assert len(capsules) == 5 and all(len(c) == fmt.length for c in capsules)
    # the capture as the port delivers it: the scan's descriptor, then the capsules
    out, dropped = decode(fmt, fmt.descriptor.encode() + b"".join(capsules))
    sdk = sdk_reference(recipe, capsules)
    assert dropped == 0
    assert len(out) == len(sdk) == 4 * fmt.samples  # the last capsule waits for a successor
    # angles within 1/64° (in fact to the last q6 bit), distances exactly
    assert np.max(angle_error_deg(out.angle_deg, sdk[:, 1] / 64.0)) <= ONE_Q6_DEG
    assert np.array_equal(np.rint(out.angle_deg * 64).astype(np.int64), sdk[:, 1])
    assert np.array_equal(out.dist_mm, sdk[:, 2] / 4.0)
    assert np.array_equal(out.start, sdk[:, 0] == 1)
    assert np.array_equal(out.quality > 0, sdk[:, 2] > 0)


@pytest.mark.parametrize("name", sorted(CAPTURES))
def test_real_capsules_decode_to_the_samples_their_publisher_printed(name: str) -> None:
    fmt, capsule_file, expected_file, _ = CAPTURES[name]
    expected = load_expected(expected_file)
    out, _ = decode(fmt, b"".join(load_capsules(capsule_file)))
    assert len(out) == len(expected)
    assert np.max(angle_error_deg(out.angle_deg, expected[:, 2] * 90.0 / 16384.0)) <= ONE_Q6_DEG
    assert np.array_equal(out.dist_mm, expected[:, 3] / 4.0)
    assert np.array_equal(out.start, expected[:, 0] == 1)
    assert np.array_equal(np.where(out.quality > 0, SDK_QUALITY, 0), expected[:, 1])


@pytest.mark.parametrize("name", sorted(CAPTURES))
@pytest.mark.parametrize("chunk", [1, 7, 83, 85, 131])
def test_real_capsules_decode_the_same_in_any_read_sizes(name: str, chunk: int) -> None:
    fmt, capsule_file, _, _ = CAPTURES[name]
    data = fmt.descriptor.encode() + b"".join(load_capsules(capsule_file))
    whole, _ = decode(fmt, data)
    pieces, dropped = decode(fmt, data, chunk)
    assert dropped == 0
    assert np.array_equal(pieces.angle_deg, whole.angle_deg) and np.array_equal(pieces.dist_mm, whole.dist_mm)
    assert np.array_equal(pieces.start, whole.start)


def legacy_fields(capsule: bytes) -> tuple[list[int], list[int]]:
    """(dist_q2, compensation q3) of a legacy capsule's 32 samples, from the protocol
    document's cabin layout (LR001 protocol v2.1, Express Scan legacy data response)."""
    dists, comps = [], []
    for cabin in range(16):
        c = capsule[4 + 5 * cabin : 9 + 5 * cabin]
        w1, w2 = c[0] | c[1] << 8, c[2] | c[3] << 8
        dists += [w1 & 0xFFFC, w2 & 0xFFFC]
        comps += [(c[4] & 0xF) | (w1 & 3) << 4, (c[4] >> 4) | (w2 & 3) << 4]
    return dists, comps


def test_real_express_capture_is_a_plausible_turn_of_a_triangulation_head() -> None:
    capsules = load_capsules("pyrplidar_express_capsules.txt")
    out, _ = decode(proto.LEGACY_CAPSULE, b"".join(capsules))
    # consecutive capsules 14.8-15.2° apart: about 761 samples a turn (an A-series unit
    # gives 400-2000 in express mode, depending on model and speed)
    steps = np.diff(np.unwrap(np.radians([start_q6(c) / 64.0 for c in capsules])))
    assert np.all((np.degrees(steps) > 14.5) & (np.degrees(steps) < 15.5))
    per_turn = 32 * 2 * math.pi / float(np.mean(steps))
    assert 740 < per_turn < 780
    # a wall 0.59-0.93 m away, a few samples without return at its edges
    valid = out.dist_mm > 0
    assert 118 <= np.count_nonzero(valid) < 128
    assert out.dist_mm[valid].min() > 580 and out.dist_mm[valid].max() < 930
    # the only revolution flag sits where the sweep passes 0°: the 13th sample of the
    # capsule starting at 354.2° (the next starts at 9.05°: 0.463° a sample)
    assert np.flatnonzero(out.start).tolist() == [2 * 32 + 12]
    # every compensation is 5.5-6.5° (q3 44-52): above 4°, where the datasheet's signed
    # reading of the field would put the sample 8° away from where the SDK puts it
    for capsule in capsules:
        dists, comps = legacy_fields(capsule)
        measured = [c for d, c in zip(dists, comps, strict=True) if d]
        assert min(measured) >= 44 and max(measured) <= 52
        # and it follows the range as the SDK's own model of the head's geometry does
        # (the offset it computes for ultra capsules, which carry none): within 0.27°
        for d, c in zip(dists, comps, strict=True):
            if d:
                model_deg = sdk_ultra_offset_q16(d) / 65536
                assert abs(c / 8 - model_deg) < 0.3, (d, c, model_deg)


def test_real_ultra_capture_is_a_plausible_turn() -> None:
    capsules = load_capsules("pyrplidar_ultra_capsules.txt")
    out, _ = decode(proto.ULTRA_CAPSULE, b"".join(capsules))
    steps = np.degrees(np.diff(np.unwrap(np.radians([start_q6(c) / 64.0 for c in capsules]))))
    assert np.all((steps > 36) & (steps < 37.5))
    assert 930 < 96 * 360 / float(np.mean(steps)) < 960
    valid = out.dist_mm > 0
    assert 0.8 * len(out) < np.count_nonzero(valid) < len(out)
    assert out.dist_mm[valid].min() > 250 and out.dist_mm[valid].max() < 1800
    assert not out.start.any()  # 75° to 220°: the sweep does not pass 0°


def test_real_a1_get_info_and_health() -> None:
    lines = (DATA / "a1_get_info_health_adafruit_issue28.txt").read_text().splitlines()
    answers = {w[0]: bytes.fromhex("".join(w[1:])) for w in (line.split() for line in lines if line[:1] != "#")}
    info_bytes, health_bytes = answers["info"], answers["health"]
    assert proto.parse_descriptor(info_bytes[:7], proto.INFO_DESCRIPTOR) == proto.INFO_DESCRIPTOR
    info = proto.parse_info(info_bytes[7:])
    assert info.model == proto.MODEL_A1M8 and info.model_name == "A1M8"
    assert rplidar_models.model_name(info.model) == "A1M8"
    assert (info.firmware_version, info.hardware) == ("1.29", 7)
    # the SDK prints the serial number least significant byte first, as it came
    assert info.serial_hex == "92D8ED93C0EA98C9A5E698F207064669"
    # the emulator's A1 says what this one said (its serial number aside)
    a1 = rplidar_models.MODELS["a1"]
    assert (a1.model_id, a1.firmware, a1.hardware) == (info.model, (1, 29), 7)
    assert proto.parse_descriptor(health_bytes[:7], proto.HEALTH_DESCRIPTOR) == proto.HEALTH_DESCRIPTOR
    health = proto.parse_health(health_bytes[7:])
    assert (health.status, health.error_code, health.status_name) == (0, 0, proto.HEALTH_STATUS_NAMES[0])
