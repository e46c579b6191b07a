"""The RPLidar byte protocol, checked against byte strings written from the protocol spec."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from mazebot.errors import ProtocolError
from mazebot.io import rplidar_protocol as proto

# --- helpers -------------------------------------------------------------------------


def sweep(n: int, step_deg: float = 0.99, start_deg: float = 0.0, seed: int = 0) -> tuple[np.ndarray, ...]:
    """A regular sweep like a spinning head's: angles, distances, qualities, start flags."""
    rng = np.random.default_rng(seed)
    angle = (start_deg + np.arange(n) * step_deg) % 360.0
    q6 = np.rint(angle * 64) % (360 * 64)
    angle = q6 / 64.0  # exactly representable, so comparisons are exact
    dist = np.rint(rng.uniform(150, 8000, n) * 4) / 4
    quality = rng.integers(0, 64, n)
    start = np.zeros(n, dtype=bool)
    start[1:] = np.diff(angle) < 0
    return angle, dist, quality, start


def decode_all(decoder: proto.StandardScanDecoder | proto.ExpressScanDecoder, data: bytes) -> proto.DecodedSamples:
    return proto.DecodedSamples.concat([decoder.feed(data), decoder.flush()])


def as_tuples(s: proto.DecodedSamples) -> list[tuple[float, float, int, bool]]:
    return list(zip(s.angle_deg.tolist(), s.dist_mm.tolist(), s.quality.tolist(), s.start.tolist(), strict=True))


def expected_tuples(
    angle: np.ndarray, dist: np.ndarray, quality: np.ndarray, start: np.ndarray
) -> list[tuple[float, float, int, bool]]:
    return [(float(a), float(d), int(q), bool(s)) for a, d, q, s in zip(angle, dist, quality, start, strict=True)]


# --- requests ------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("cmd", "wire"),
    [
        (proto.CMD_STOP, b"\xa5\x25"),
        (proto.CMD_RESET, b"\xa5\x40"),
        (proto.CMD_SCAN, b"\xa5\x20"),
        (proto.CMD_FORCE_SCAN, b"\xa5\x21"),
        (proto.CMD_GET_INFO, b"\xa5\x50"),
        (proto.CMD_GET_HEALTH, b"\xa5\x52"),
        (proto.CMD_GET_SAMPLERATE, b"\xa5\x59"),
    ],
)
def test_requests_without_payload_are_two_bytes(cmd: int, wire: bytes) -> None:
    assert proto.build_request(cmd) == wire
    assert proto.parse_request(wire + b"\xa5") == (cmd, b"", 2)


def test_express_scan_request_carries_size_payload_and_xor_checksum() -> None:
    # A5 82 05 00 00 00 00 00 checksum: A5 ^ 82 ^ 05 = 0x22
    wire = b"\xa5\x82\x05\x00\x00\x00\x00\x00\x22"
    assert proto.build_request(proto.CMD_EXPRESS_SCAN, proto.EXPRESS_SCAN_PAYLOAD) == wire
    assert proto.parse_request(wire) == (proto.CMD_EXPRESS_SCAN, bytes(5), 9)


def test_parse_request_waits_for_a_complete_request() -> None:
    wire = proto.build_request(proto.CMD_EXPRESS_SCAN, proto.EXPRESS_SCAN_PAYLOAD)
    for cut in range(len(wire)):
        assert proto.parse_request(wire[:cut]) is None


def test_parse_request_rejects_bad_checksum_and_missing_sync() -> None:
    wire = bytearray(proto.build_request(proto.CMD_EXPRESS_SCAN, proto.EXPRESS_SCAN_PAYLOAD))
    wire[-1] ^= 0xFF
    with pytest.raises(ProtocolError, match="expected checksum 0x22, found 0xdd"):
        proto.parse_request(bytes(wire))
    with pytest.raises(ProtocolError, match="expected sync byte 0xa5, found 0x25"):
        proto.parse_request(b"\x25")


def test_build_request_refuses_payload_mismatch() -> None:
    with pytest.raises(ValueError, match="takes no payload"):
        proto.build_request(proto.CMD_SCAN, b"\x00")
    with pytest.raises(ValueError, match="needs a payload"):
        proto.build_request(proto.CMD_EXPRESS_SCAN)


# --- descriptors ---------------------------------------------------------------------


@pytest.mark.parametrize(
    ("descriptor", "wire"),
    [
        (proto.INFO_DESCRIPTOR, b"\xa5\x5a\x14\x00\x00\x00\x04"),
        (proto.HEALTH_DESCRIPTOR, b"\xa5\x5a\x03\x00\x00\x00\x06"),
        (proto.SAMPLERATE_DESCRIPTOR, b"\xa5\x5a\x04\x00\x00\x00\x15"),
        (proto.SCAN_DESCRIPTOR, b"\xa5\x5a\x05\x00\x00\x40\x81"),
        (proto.EXPRESS_DESCRIPTOR, b"\xa5\x5a\x54\x00\x00\x40\x82"),
    ],
)
def test_descriptors_match_the_spec(descriptor: proto.Descriptor, wire: bytes) -> None:
    assert descriptor.encode() == wire
    assert proto.encode_descriptor(descriptor.length, descriptor.mode, descriptor.dtype) == wire
    assert proto.parse_descriptor(wire) == descriptor
    assert proto.parse_descriptor(wire, expected=descriptor) == descriptor


def test_descriptor_length_is_30_bits_and_mode_the_top_2() -> None:
    wire = proto.encode_descriptor((1 << 30) - 1, 1, 0x99)
    assert wire == b"\xa5\x5a\xff\xff\xff\x7f\x99"
    d = proto.parse_descriptor(wire)
    assert (d.length, d.mode, d.dtype) == ((1 << 30) - 1, proto.SendMode.MULTIPLE, 0x99)


def test_parse_descriptor_says_what_was_expected_and_found() -> None:
    with pytest.raises(ProtocolError) as err:
        proto.parse_descriptor(proto.HEALTH_DESCRIPTOR.encode(), expected=proto.INFO_DESCRIPTOR)
    message = str(err.value)
    assert "\n" not in message
    assert "expected descriptor (length 20, single, type 0x04)" in message
    assert "found (length 3, single, type 0x06)" in message
    with pytest.raises(ProtocolError, match="starting a5 5a, found a5 a5"):
        proto.parse_descriptor(b"\xa5\xa5\x05\x00\x00\x40\x81")
    with pytest.raises(ProtocolError, match="7-byte descriptor"):
        proto.parse_descriptor(b"\xa5\x5a\x05")
    with pytest.raises(ProtocolError, match="send mode 0 or 1, found mode 2"):
        proto.parse_descriptor(b"\xa5\x5a\x05\x00\x00\x80\x81")


# --- single responses ----------------------------------------------------------------


def test_info_layout() -> None:
    wire = bytes([0x18, 29, 1, 7]) + bytes(range(16))
    info = proto.parse_info(wire)
    assert info == proto.DeviceInfo(0x18, 29, 1, 7, bytes(range(16)))
    assert info.model_name == "A1M8"
    assert info.firmware_version == "1.29"
    assert info.serial_hex == "000102030405060708090A0B0C0D0E0F"
    assert proto.encode_info(info) == wire
    with pytest.raises(ProtocolError, match="expected 20 bytes, found 3"):
        proto.parse_info(wire[:3])


def test_health_layout_is_status_and_little_endian_code() -> None:
    health = proto.parse_health(b"\x02\x01\x80")
    assert health == proto.DeviceHealth(2, 0x8001)
    assert health.status_name == "error"
    assert proto.encode_health(health) == b"\x02\x01\x80"
    assert proto.parse_health(b"\x00\x00\x00").status_name == "good"
    assert proto.parse_health(b"\x01\x00\x00").status_name == "warning"
    with pytest.raises(ProtocolError, match="status 0, 1 or 2, found 7"):
        proto.parse_health(b"\x07\x00\x00")


def test_samplerate_layout() -> None:
    rate = proto.parse_samplerate(b"\xfc\x01\xfe\x00")
    assert rate == proto.SampleRate(standard_us=508, express_us=254)
    assert proto.encode_samplerate(rate) == b"\xfc\x01\xfe\x00"


# --- standard samples ----------------------------------------------------------------


def test_standard_sample_bytes_follow_the_spec() -> None:
    # 90° = 5760 q6 = 0x1680; 1000 mm = 4000 q2 = 0x0FA0; quality 15, start
    wire = proto.encode_standard_sample(90.0, 1000.0, 15, True)
    assert wire == bytes([15 << 2 | 0b01, (0x1680 & 0x7F) << 1 | 1, 0x1680 >> 7, 0xA0, 0x0F])
    wire = proto.encode_standard_sample(359.984375, 0.25, 63, False)
    assert wire == bytes([63 << 2 | 0b10, (23039 & 0x7F) << 1 | 1, 23039 >> 7, 0x01, 0x00])
    # one lone sample: believed at the end of the stream (nothing contradicts it)
    assert as_tuples(decode_all(proto.StandardScanDecoder(), wire)) == [(359.984375, 0.25, 63, False)]


def test_clean_stream_decodes_exactly() -> None:
    angle, dist, quality, start = sweep(2000)
    dec = proto.StandardScanDecoder()
    out = decode_all(dec, proto.encode_standard_samples(angle, dist, quality, start))
    assert as_tuples(out) == expected_tuples(angle, dist, quality, start)
    assert (dec.bytes_dropped, dec.samples_decoded) == (0, 2000)


def test_irregular_angles_decode_by_form_alone() -> None:
    # synthetic data with no rhythm at all (e.g. a test's random angles)
    rng = np.random.default_rng(5)
    angle = np.rint(rng.uniform(0, 360, 50) * 64) % 23040 / 64
    dist = np.full(50, 500.0)
    quality = np.full(50, 10)
    start = np.zeros(50, dtype=bool)
    out = decode_all(proto.StandardScanDecoder(), proto.encode_standard_samples(angle, dist, quality, start))
    assert out.angle_deg.tolist() == angle.tolist()


@pytest.mark.parametrize("count", [1, 2, 3, 7])
def test_a_few_samples_come_out_at_the_end_of_the_stream(count: int) -> None:
    angle, dist, quality, start = sweep(count)
    out = decode_all(proto.StandardScanDecoder(), proto.encode_standard_samples(angle, dist, quality, start))
    assert as_tuples(out) == expected_tuples(angle, dist, quality, start)


def test_every_split_point_gives_the_same_samples() -> None:
    angle, dist, quality, start = sweep(60)
    rng = np.random.default_rng(1)
    clean = proto.encode_standard_samples(angle, dist, quality, start)
    # a mid-stream start, garbage in the middle, a partial sample at the end
    data = clean[3:100] + rng.integers(0, 256, 13, dtype=np.uint8).tobytes() + clean[100:] + clean[:2]
    reference = as_tuples(decode_all(proto.StandardScanDecoder(), data))
    assert len(reference) == 59
    for cut in range(len(data) + 1):
        dec = proto.StandardScanDecoder()
        parts = [dec.feed(data[:cut]), dec.feed(data[cut:]), dec.flush()]
        assert as_tuples(proto.DecodedSamples.concat(parts)) == reference, cut
    dec = proto.StandardScanDecoder()
    parts = [dec.feed(data[i : i + 1]) for i in range(len(data))] + [dec.flush()]
    assert as_tuples(proto.DecodedSamples.concat(parts)) == reference


@pytest.mark.parametrize("offset", [1, 2, 3, 4])
def test_mid_stream_start_resynchronises(offset: int) -> None:
    angle, dist, quality, start = sweep(100)
    data = proto.encode_standard_samples(angle, dist, quality, start)
    dec = proto.StandardScanDecoder()
    out = decode_all(dec, data[offset:])
    assert as_tuples(out) == expected_tuples(angle, dist, quality, start)[1:]
    assert dec.bytes_dropped == 5 - offset


@pytest.mark.parametrize("seed", range(8))
def test_random_garbage_between_runs_is_dropped_exactly(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    angle, dist, quality, start = sweep(3000, seed=seed)
    wire = proto.encode_standard_samples(angle, dist, quality, start)
    # the stream starts on a run long enough to show the head's rhythm
    pieces, kept, i = [wire[:50]], list(range(10)), 10
    garbage = 0
    while i < 3000:
        run = int(rng.integers(1, 25))
        pieces.append(wire[5 * i : 5 * (i + run)])
        kept.extend(range(i, min(i + run, 3000)))
        i += run
        junk = rng.integers(0, 256, int(rng.integers(1, 40)), dtype=np.uint8).tobytes()
        pieces.append(junk)
        garbage += len(junk)
    dec = proto.StandardScanDecoder()
    out = decode_all(dec, b"".join(pieces))
    everything = expected_tuples(angle, dist, quality, start)
    wanted = [everything[k] for k in kept]
    got = as_tuples(out)
    # The rhythm window spans the 8° a triangulation head's range offsets make a real
    # step deviate; at that width a burst of random bytes now and then holds a sample
    # that passes, and can hide the real one beside it (over the 8 seeds: 3 lost and
    # 2 made up of 24 000). Whatever is made up lies within the window of the sweep.
    lost = set(wanted) - set(got)
    made_up = set(got) - set(wanted)
    assert len(lost) <= 3 and len(made_up) <= 2, (lost, made_up)
    for a, _, _, _ in made_up:
        assert np.min(np.abs((angle - a + 180) % 360 - 180)) <= 8.5
    assert [t for t in got if t not in made_up] == [t for t in wanted if t not in lost]
    assert dec.bytes_dropped == garbage + 5 * (len(lost) - len(made_up))


def test_leftover_of_an_unclean_run_and_a_descriptor_are_skipped() -> None:
    old = proto.encode_standard_samples(*sweep(30, start_deg=200.0, seed=1))
    new = sweep(40, seed=2)
    data = old[:-2] + proto.SCAN_DESCRIPTOR.encode() + proto.encode_standard_samples(*new)
    dec = proto.StandardScanDecoder()
    out = decode_all(dec, data)
    # the old run's whole samples are samples too; its cut last one is dropped
    assert as_tuples(out)[-40:] == expected_tuples(*new)
    assert len(out) == 29 + 40
    assert dec.descriptors_skipped == 1
    assert dec.bytes_dropped == 3


def test_descriptor_at_the_start_of_a_capture_is_not_a_sample() -> None:
    angle, dist, quality, start = sweep(20)
    dec = proto.StandardScanDecoder()
    out = decode_all(dec, proto.SCAN_DESCRIPTOR.encode() + proto.encode_standard_samples(angle, dist, quality, start))
    assert as_tuples(out) == expected_tuples(angle, dist, quality, start)
    assert (dec.bytes_dropped, dec.descriptors_skipped) == (0, 1)


def test_samples_that_break_the_rhythm_are_dropped() -> None:
    angle, dist, quality, start = sweep(40)
    wire = proto.encode_standard_samples(angle, dist, quality, start)
    # well-formed impostors: right form, wrong place in the turn
    impostor = proto.encode_standard_sample(123.0, 500.0, 10, False)
    data = wire[:100] + impostor + wire[100:150] + impostor + impostor + wire[150:]
    dec = proto.StandardScanDecoder()
    assert as_tuples(decode_all(dec, data)) == expected_tuples(angle, dist, quality, start)
    assert dec.bytes_dropped == 15


def test_lost_bytes_resume_on_a_fresh_regular_run() -> None:
    angle, dist, quality, start = sweep(200)
    wire = proto.encode_standard_samples(angle, dist, quality, start)
    data = wire[:500] + wire[512:]  # a serial overrun: 12 bytes (2.4 samples) lost
    out = decode_all(proto.StandardScanDecoder(), data)
    expected = expected_tuples(angle, dist, quality, start)
    assert as_tuples(out) == expected[:100] + expected[103:]


def test_decoder_never_raises_on_random_bytes() -> None:
    rng = np.random.default_rng(7)
    dec = proto.StandardScanDecoder()
    data = rng.integers(0, 256, 20000, dtype=np.uint8).tobytes()
    for i in range(0, len(data), 777):
        dec.feed(data[i : i + 777])
    dec.flush()
    assert dec.bytes_dropped + 5 * dec.samples_decoded == len(data)
    assert dec.samples_decoded < 10  # random bytes have no rhythm: almost nothing believed


# --- express capsules ----------------------------------------------------------------


def sdk_capsule_angles(capsule: bytes, next_capsule: bytes) -> list[float]:
    """The Slamtec SDK's fixed-point recipe, written out sample by sample (scalar)."""
    start = (capsule[2] | capsule[3] << 8) & 0x7FFF
    nxt = (next_capsule[2] | next_capsule[3] << 8) & 0x7FFF
    prev_q8, cur_q8 = start << 2, nxt << 2
    diff_q8 = cur_q8 - prev_q8 + (360 << 8 if prev_q8 > cur_q8 else 0)
    inc_q16 = diff_q8 << 3
    raw_q16 = prev_q8 << 8
    angles = []
    for cabin in range(16):
        c = capsule[4 + 5 * cabin : 9 + 5 * cabin]
        d1, d2 = c[0] | c[1] << 8, c[2] | c[3] << 8
        for dist_word, low in ((d1, c[4] & 0xF), (d2, c[4] >> 4)):
            comp_q3 = low | (dist_word & 0x3) << 4
            angle_q6 = (raw_q16 - (comp_q3 << 13)) >> 10
            angles.append((angle_q6 % (360 << 6)) / 64.0)
            raw_q16 += inc_q16
    return angles


def test_express_capsule_bytes_follow_the_spec() -> None:
    dists = np.arange(32) * 100.0 + 7
    comp = np.zeros(32)
    comp[0] = 0.125  # q3 = 1: low nibble of the first offset byte
    comp[1] = 2.5  # q3 = 20 = 0b010100: bit 4 rides in distance word 2, low nibble 4
    cap = proto.encode_express_capsule(10.0, dists, comp, start=True)
    assert len(cap) == 84
    assert cap[0] >> 4 == 0xA and cap[1] >> 4 == 0x5
    checksum = 0
    for b in cap[2:]:
        checksum ^= b
    assert (cap[0] & 0xF) | (cap[1] & 0xF) << 4 == checksum
    assert cap[2] | cap[3] << 8 == 640 | 0x8000  # 10° in q6, start flag in bit 15
    d1 = cap[4] | cap[5] << 8
    d2 = cap[6] | cap[7] << 8
    assert (d1 >> 2, d1 & 3) == (7, 0)
    assert (d2 >> 2, d2 & 3) == (107, 0b01)
    assert cap[8] == (1 & 0xF) | (20 & 0xF) << 4


def test_express_angles_are_interpolated_to_the_next_capsule_minus_compensation() -> None:
    dists = np.full(32, 1000.0)
    comp = np.zeros(32)
    comp[3] = 1.0
    comp[31] = 3.875
    first = proto.encode_express_capsule(350.0, dists, comp, start=True)
    second = proto.encode_express_capsule(6.0, dists)  # wraps: 16° later
    third = proto.encode_express_capsule(22.0, dists)
    dec = proto.ExpressScanDecoder()
    assert len(dec.feed(first)) == 0  # needs the next start angle
    out = dec.feed(second)
    expected = [(350.0 + 0.5 * i - comp[i]) % 360.0 for i in range(32)]
    assert out.angle_deg.tolist() == pytest.approx(expected, abs=1 / 64)
    assert out.angle_deg.tolist() == sdk_capsule_angles(first, second)
    assert out.angle_deg[3] == 350.5  # 351.5 - 1.0
    assert out.angle_deg[31] == 1.625  # 350 + 15.5 - 3.875, past 360°
    # the SDK flags the last sample before the uncompensated sweep passes 360°:
    # sample 19 at 359.5°, whose successor lies at 350 + 0.5 * 20 = 360°
    assert np.flatnonzero(out.start).tolist() == [19]
    np.testing.assert_array_equal(out.dist_mm, 1000.0)
    np.testing.assert_array_equal(out.quality, 1)
    out = dec.feed(third)
    assert out.angle_deg.tolist() == sdk_capsule_angles(second, third)
    assert not out.start.any()
    assert dec.capsules_decoded == 2


def test_express_angle_by_hand() -> None:
    # start 100°, next 116°: 0.5° a sample; sample 5 at 102.5°, compensation 0.375° (q3 3)
    comp = np.zeros(32)
    comp[5] = 0.375
    a = proto.encode_express_capsule(100.0, np.full(32, 500.0), comp)
    b = proto.encode_express_capsule(116.0, np.full(32, 500.0))
    out = decode_all(proto.ExpressScanDecoder(), a + b)
    assert out.angle_deg[5] == 102.125
    assert out.angle_deg[6] == 103.0


def test_compensation_field_reads_unsigned_and_is_subtracted() -> None:
    # q3 field 0b111111 = 63 = 7.875°, subtracted (the SDK's reading; the datasheet's
    # signed reading would make it -0.125° and put the sample at 100.125°)
    a = bytearray(proto.encode_express_capsule(100.0, np.full(32, 500.0)))
    a[4] |= 0b11  # distance word 1 bits 0-1: compensation bits 4-5
    a[8] |= 0x0F  # low nibble: compensation bits 0-3
    cs = 0
    for x in a[2:]:
        cs ^= x
    a[0] = 0xA0 | (cs & 0xF)
    a[1] = 0x50 | (cs >> 4)
    b = proto.encode_express_capsule(116.0, np.full(32, 500.0))
    out = decode_all(proto.ExpressScanDecoder(), bytes(a) + b)
    assert out.angle_deg[0] == 92.125
    assert out.dist_mm[0] == 500.0


def test_express_round_trip_through_compensation_helper() -> None:
    rng = np.random.default_rng(3)
    starts = [0.0, 16.0, 32.5, 48.0]
    decoded = []
    wanted = []
    caps = b""
    for k in range(3):
        interp = starts[k] + np.arange(32) * (starts[k + 1] - starts[k]) / 32
        target = np.rint((interp - rng.uniform(0, 3.5, 32)) * 64) / 64
        comp = proto.express_compensation_deg(starts[k], starts[k + 1], target)
        caps += proto.encode_express_capsule(starts[k], rng.integers(0, 16000, 32), comp)
        wanted.append(target)
    caps += proto.encode_express_capsule(starts[3], np.zeros(32))
    out = decode_all(proto.ExpressScanDecoder(), caps)
    decoded = out.angle_deg.reshape(3, 32)
    np.testing.assert_allclose(decoded, np.array(wanted) % 360, atol=0.125 + 1 / 64)
    with pytest.raises(ValueError, match=r"0\.\.7\.875"):
        proto.express_compensation_deg(0.0, 16.0, np.arange(32) * 0.5 + 1.0)


def test_express_encoder_refuses_what_decoders_disagree_on() -> None:
    with pytest.raises(ValueError, match="compensation"):
        proto.encode_express_capsule(0.0, np.zeros(32), np.full(32, -0.125))
    with pytest.raises(ValueError, match="16383"):
        proto.encode_express_capsule(0.0, np.full(32, 20000.0))
    with pytest.raises(ValueError, match="32 distances"):
        proto.encode_express_capsule(0.0, np.zeros(31))


def express_stream(n_caps: int, step_deg: float = 16.0) -> list[bytes]:
    """Capsules of a steadily turning head, the first with the start flag."""
    return [
        proto.encode_express_capsule((k * step_deg) % 360, np.arange(32) + 100 * k, start=k == 0)
        for k in range(n_caps)
    ]


def test_express_stream_split_at_every_offset() -> None:
    caps = express_stream(5)
    data = b"\x13\x37" + b"".join(caps)
    reference = as_tuples(decode_all(proto.ExpressScanDecoder(), data))
    assert len(reference) == 4 * 32
    for cut in range(len(data) + 1):
        dec = proto.ExpressScanDecoder()
        parts = [dec.feed(data[:cut]), dec.feed(data[cut:]), dec.flush()]
        assert as_tuples(proto.DecodedSamples.concat(parts)) == reference, cut


def test_express_garbage_costs_the_capsule_before_it() -> None:
    caps = express_stream(8)
    rng = np.random.default_rng(9)
    junk = rng.integers(0, 256, 50, dtype=np.uint8).tobytes()
    # garbage after capsule 2: capsule 2 cannot be interpolated (like the SDK, it is lost)
    data = b"".join(caps[:3]) + junk + b"".join(caps[3:])
    dec = proto.ExpressScanDecoder()
    out = decode_all(dec, data)
    clean = decode_all(proto.ExpressScanDecoder(), b"".join(caps)).angle_deg.reshape(7, 32)
    got = out.angle_deg.reshape(-1, 32)
    np.testing.assert_array_equal(got, np.concatenate([clean[:2], clean[3:]]))
    assert dec.bytes_dropped == 50
    assert dec.capsules_discarded == 2  # capsule 2, and the last one (no successor)


def test_express_corrupted_capsule_is_dropped_and_descriptor_skipped() -> None:
    caps = express_stream(6)
    bad = bytearray(caps[3])
    bad[40] ^= 0x01  # checksum no longer matches
    data = proto.EXPRESS_DESCRIPTOR.encode() + b"".join(caps[:3]) + bytes(bad) + b"".join(caps[4:])
    dec = proto.ExpressScanDecoder()
    out = decode_all(dec, data)
    assert dec.descriptors_skipped == 1
    assert dec.bytes_dropped == 84
    assert len(out) == 2 * 32 + 32  # capsules 0, 1 and 4
    assert dec.capsules_decoded == 3


def test_express_start_flag_begins_a_new_scan() -> None:
    caps = express_stream(3)
    restart = proto.encode_express_capsule(200.0, np.zeros(32), start=True)
    more = proto.encode_express_capsule(216.0, np.zeros(32))
    dec = proto.ExpressScanDecoder()
    out = decode_all(dec, b"".join(caps) + restart + more)
    # capsule 2 had no successor in its scan; the new scan's first capsule decodes
    assert len(out) == 3 * 32
    assert out.angle_deg[64] == 200.0


def test_express_decoder_survives_random_bytes() -> None:
    rng = np.random.default_rng(11)
    dec = proto.ExpressScanDecoder()
    data = rng.integers(0, 256, 50000, dtype=np.uint8).tobytes()
    for i in range(0, len(data), 1000):
        dec.feed(data[i : i + 1000])
    dec.flush()
    assert dec.bytes_dropped + 84 * (dec.capsules_decoded + dec.capsules_discarded) >= len(data) - 84
    assert dec.samples_decoded == 0


def _datasheet_sample(angle_deg: float, dist_mm: float, quality: int, start: bool) -> bytes:
    """One standard sample laid out field by field as the protocol document draws it."""
    angle_q6 = round(angle_deg * 64) % (360 * 64)  # round half to even, like np.rint
    return struct.pack(
        "<BHH", (quality << 2) | ((not start) << 1) | start, (angle_q6 << 1) | 1, round(dist_mm * 4)
    )


def test_batch_encoder_writes_the_datasheet_layout() -> None:
    """``encode_standard_samples`` (the emulator's) byte for byte against the field layout, packed apart."""
    rng = np.random.default_rng(11)
    for _ in range(200):
        n = int(rng.integers(1, 50))
        angle = rng.uniform(0.0, 360.0, n)
        angle[: n // 4] = rng.choice([0.0, 0.0078125, 180.0, 359.99, 359.999], n // 4)  # rounding and wrap
        dist = np.round(rng.uniform(0.0, 16383.75, n) * 4) / 4
        dist[: n // 5] = 0.0
        quality = rng.integers(0, 64, n)
        start = rng.random(n) < 0.2
        want = b"".join(
            _datasheet_sample(float(a), float(d), int(q), bool(s))
            for a, d, q, s in zip(angle, dist, quality, start, strict=True)
        )
        assert proto.encode_standard_samples(angle, dist, quality, start) == want
    for bad in ({"dist": -1.0}, {"dist": 16384.0}, {"quality": 64}, {"quality": -1}):
        with pytest.raises(ValueError):
            proto.encode_standard_samples([1.0], [bad.get("dist", 1.0)], [bad.get("quality", 3)], [True])


def _capsule_by_hand(start_q6: int, words: list[tuple[int, int, int]], start_flag: bool = False) -> bytes:
    """An express capsule laid out from the protocol document (LR001, "express scan
    data response packet"), independently of ``encode_express_capsule``: 16 cabins of
    (distance 1 u16 with dθ1 bits 4-5 in its low 2 bits, distance 2 likewise, one byte
    of the two low nibbles), checksum = XOR of bytes 2..83 split over the sync bytes."""
    assert len(words) == 16
    body = bytearray([start_q6 & 0xFF, (start_q6 >> 8) | (0x80 if start_flag else 0)])
    for d1_mm, d2_mm, comps in words:
        c1, c2 = comps >> 8, comps & 0xFF  # two 6-bit compensations packed as c1 << 8 | c2
        w1 = d1_mm << 2 | c1 >> 4
        w2 = d2_mm << 2 | c2 >> 4
        body += bytes([w1 & 0xFF, w1 >> 8, w2 & 0xFF, w2 >> 8, (c1 & 0xF) | (c2 & 0xF) << 4])
    cs = 0
    for b in body:
        cs ^= b
    return bytes([0xA0 | cs & 0xF, 0x50 | cs >> 4]) + bytes(body)


def test_express_compensations_of_a_real_a1_are_subtracted_unsigned() -> None:
    """Compensations 40-52 (q3), what an A1 sends for walls 0.5-1 m away, are
    5-6.5° subtracted: the SDK's reading (handler_capsules.cpp). Worked out by hand:
    start 100°, next start 116°: sample i sits at 100 + i/2 - comp/8 degrees."""
    comps = [40, 41, 44, 45, 48, 50, 52, 63, 0, 31, 32, 33, 47, 46, 43, 42] * 2
    words = [(500 + 10 * k, 987 + k, comps[2 * k] << 8 | comps[2 * k + 1]) for k in range(16)]
    a = _capsule_by_hand(100 * 64, words)
    b = _capsule_by_hand(116 * 64, [(0, 0, 0)] * 16)
    out = decode_all(proto.ExpressScanDecoder(), a + b)
    expected = [100 + i / 2 - comps[i] / 8 for i in range(32)]
    assert out.angle_deg.tolist() == expected
    assert out.angle_deg[0] == 95.0  # q3 40 = 5°: the signed reading put it at 103°
    assert out.angle_deg[7] == 103.5 - 7.875
    assert out.dist_mm.tolist() == [float(500 + 10 * (i // 2) if i % 2 == 0 else 987 + i // 2) for i in range(32)]
    assert not out.start.any()


def test_express_sync_flag_sits_where_the_sdk_puts_it() -> None:
    """Start 352°, next start 8° (16° later, 0.5° a sample): the SDK flags the sample
    whose successor's uncompensated angle passes 360°, 352 + 0.5 * 15 = 359.5°."""
    a = _capsule_by_hand(352 * 64, [(1000, 1000, 45 << 8 | 45)] * 16)
    b = _capsule_by_hand(8 * 64, [(0, 0, 0)] * 16)
    out = decode_all(proto.ExpressScanDecoder(), a + b)
    assert np.flatnonzero(out.start).tolist() == [15]
    assert out.angle_deg[15] == 359.5 - 45 / 8
    assert out.angle_deg[16] == (360.0 - 45 / 8) % 360


# --- the angles Slamtec's SDK gives, worked out by hand from its code ------------------
#
# Standard nodes (sl_lidar_driver.cpp ``convert``, the SDK 2 unpacker the same):
#     angle_z_q14 = ((angle_q6_checkbit >> 1) << 8) / 90        (C integer division)
# and the caller's degrees are angle_z_q14 * 90 / 16384. Legacy express capsules
# (handler_capsules.cpp ``_onScanNodeCapsuleData``): the capsule's samples are spread from
# its start angle to the next capsule's, q16, then
#     angle_q6 = (raw_q16 - (offset_q3 << 13)) >> 10            (arithmetic shift: floor)
# wrapped into 0..360°, the 6-bit offset read unsigned: bits 0-3 from the cabin's offset
# byte (low nibble for the cabin's first sample, high for its second), bits 4-5 from the low
# two bits of that sample's own distance word.


def _hand_capsule(start_q6: int, dist_mm: int, offsets_q3: dict[int, int]) -> bytes:
    """A legacy express capsule written byte by byte from the protocol's layout (not our encoder)."""
    body = bytearray(struct.pack("<H", start_q6))
    for cabin in range(16):
        o1, o2 = offsets_q3.get(2 * cabin, 0), offsets_q3.get(2 * cabin + 1, 0)
        words = ((dist_mm << 2) | (o1 >> 4), (dist_mm << 2) | (o2 >> 4))
        body += struct.pack("<HHB", *words, (o1 & 0xF) | (o2 & 0xF) << 4)
    checksum = 0
    for b in body:
        checksum ^= b
    return bytes((0xA0 | (checksum & 0xF), 0x50 | (checksum >> 4))) + bytes(body)


def test_express_angles_are_the_sdks_to_the_bit_floor_and_wrap_included() -> None:
    # Capsule 643 q6 (10.046875°), the next 1162 q6: prev_q8 2572, cur_q8 4648, diff_q8 2076,
    # angleInc_q16 = 2076 << 3 = 16608, raw_q16 of sample i = (2572 << 8) + 16608 i = 658432 + 16608 i.
    #   sample 1, offset 0:   675040 >> 10 = 659 (659.22)            -> 10.296875°
    #   sample 2, offset 63:  (691648 - 516096) >> 10 = 171 (171.44) -> 2.671875°
    #   sample 3, offset 17:  (708256 - 139264) >> 10 = 555 (555.66: floor, not 556) -> 8.671875°
    first = _hand_capsule(643, 500, {2: 63, 3: 17})
    second = _hand_capsule(1162, 500, {1: 40})
    # Capsule 1162 (q8 4648) before 1679 q6 (q8 6716): diff_q8 2068, angleInc_q16 16544.
    # Its sample 1: raw 4648 << 8 + 16544 = 1206432, offset 40 (5°): (1206432 - 327680) >> 10 = 858 (858.16)
    third = _hand_capsule(1679, 500, {})
    out = decode_all(proto.ExpressScanDecoder(), first + second + third)
    assert out.angle_deg[1:4].tolist() == [659 / 64, 171 / 64, 555 / 64]
    assert out.angle_deg[33] == 858 / 64
    # before 0°: capsule 64 q6 (q8 256) before 581 q6 (q8 2324): angleInc_q16 = 2068 << 3 = 16544;
    # sample 1: 65536 + 16544 = 82080, offset 40: (82080 - 327680) >> 10 = -240 (-239.84, floor),
    # + 360 << 6 -> 22800 -> 356.25° (truncation towards zero would give 356.265625°)
    out = decode_all(proto.ExpressScanDecoder(), _hand_capsule(64, 500, {1: 40}) + _hand_capsule(581, 500, {})
                     + _hand_capsule(1098, 500, {}))
    assert out.angle_deg[1] == 22800 / 64
    assert out.dist_mm[1] == 500.0


def test_standard_angles_are_the_sdks_q6_before_its_q14_truncation() -> None:
    # An A1's standard samples step irregularly (each range's angle offset is taken off on the
    # device): 1234 mm at 68.578125° (q6 4389), 315 mm at 72.515625° (q6 4641), 298 mm at
    # 73.453125° (q6 4701); quality 47, the first opens a revolution.
    wire = bytes([47 << 2 | 0b01, (4389 << 1 | 1) & 0xFF, (4389 << 1 | 1) >> 8, (1234 * 4) & 0xFF, (1234 * 4) >> 8,
                  47 << 2 | 0b10, (4641 << 1 | 1) & 0xFF, (4641 << 1 | 1) >> 8, (315 * 4) & 0xFF, (315 * 4) >> 8,
                  47 << 2 | 0b10, (4701 << 1 | 1) & 0xFF, (4701 << 1 | 1) >> 8, (298 * 4) & 0xFF, (298 * 4) >> 8])
    out = decode_all(proto.StandardScanDecoder(), wire)
    assert as_tuples(out) == [(4389 / 64, 1234.0, 47, True), (4641 / 64, 315.0, 47, False),
                              (4701 / 64, 298.0, 47, False)]
    # the SDK's q14: (4389 << 8) / 90 = 12484 (12484.27), 68.5766°; (4641 << 8) / 90 = 13201
    # (13201.07); (4701 << 8) / 90 = 13371 (13371.73): the device's q6 lies at most one q14
    # step (90/16384°) above what the SDK hands its caller
    sdk_deg = np.array([12484, 13201, 13371]) * 90 / 16384
    assert np.all(out.angle_deg - sdk_deg >= 0) and np.all(out.angle_deg - sdk_deg < 90 / 16384)
