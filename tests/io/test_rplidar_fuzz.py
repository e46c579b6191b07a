"""Random and mangled byte streams thrown at every RPLidar decoder (hypothesis).

A serial line to a lidar drops, repeats, flips and inserts bytes; a stranger's device
may answer anything. Whatever arrives, the pure decoders of ``mazebot.io.rplidar_protocol``
must never raise anything but their documented ``ProtocolError``, never hand on a sample
the device could not have measured (angle outside [0, 360), a distance outside the
16-bit field, a quality the format cannot hold, NaN), account for every byte, and give
the same samples however the stream is cut into reads.

The suite runs a moderate number of examples per property; ``bench/fuzz.py`` runs the
same properties at the issue's scale (``MAZEBOT_FUZZ_LIDAR_EXAMPLES``).
"""

from __future__ import annotations

import json
import os
from collections import Counter

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from mazebot.clock import RealClock
from mazebot.errors import MazebotError, ProtocolError
from mazebot.io import rplidar_protocol as proto
from mazebot.io.rplidar import RPLidar, _RevolutionBuilder

#: Examples per property: moderate in the suite, the issue's scale under bench/fuzz.py.
EXAMPLES = int(os.environ.get("MAZEBOT_FUZZ_LIDAR_EXAMPLES", "80"))
FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=None,
    database=None,
    derandomize=os.environ.get("MAZEBOT_FUZZ_RANDOM") != "1",  # the suite is repeatable; the bench explores
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
#: Buffers each property was run on (bench/fuzz.py reads them from $MAZEBOT_FUZZ_REPORT).
BUFFERS: Counter[str] = Counter()

#: What the wire formats can carry: a standard distance is a u16 of quarter millimetres,
#: an express one 14 bits of millimetres; standard quality 6 bits, express 0/1.
MAX_STANDARD_DIST_MM = 0xFFFF / 4.0
MAX_EXPRESS_DIST_MM = (1 << 14) - 1


def report_counts() -> None:
    """Append the counts so far to ``$MAZEBOT_FUZZ_REPORT`` (one line per call; the last one of
    each process is its total, so an interrupted run still says how far it got)."""
    path = os.environ.get("MAZEBOT_FUZZ_REPORT")
    if path:
        with open(path, "a", encoding="utf-8") as f:
            f.write(json.dumps({"suite": "lidar", "pid": os.getpid(), "buffers": dict(BUFFERS)}) + "\n")


@pytest.fixture(scope="module", autouse=True)
def _report_counts():
    yield
    report_counts()


def assert_physical(samples: proto.DecodedSamples, express: bool) -> None:
    """Every sample is one the A1 could have sent in that format."""
    n = len(samples)
    assert samples.dist_mm.shape == samples.quality.shape == samples.start.shape == (n,)
    assert samples.start.dtype == bool and samples.quality.dtype == np.uint8
    assert np.all(np.isfinite(samples.angle_deg)) and np.all(np.isfinite(samples.dist_mm))
    assert np.all((samples.angle_deg >= 0.0) & (samples.angle_deg < 360.0)), samples.angle_deg
    top = MAX_EXPRESS_DIST_MM if express else MAX_STANDARD_DIST_MM
    assert np.all((samples.dist_mm >= 0.0) & (samples.dist_mm <= top)), samples.dist_mm
    assert np.all(samples.quality <= (1 if express else 63))
    # the device's quantisation: 1/64 degree; 1/4 mm standard, whole mm express
    assert np.all(samples.angle_deg * 64 == np.rint(samples.angle_deg * 64))
    assert np.all(samples.dist_mm * (1 if express else 4) == np.rint(samples.dist_mm * (1 if express else 4)))


def tuples(s: proto.DecodedSamples) -> list[tuple[float, float, int, bool]]:
    return list(zip(s.angle_deg.tolist(), s.dist_mm.tolist(), s.quality.tolist(), s.start.tolist(), strict=True))


def decode_in_pieces(
    decoder: proto.StandardScanDecoder | proto.ExpressScanDecoder, data: bytes, cuts: list[int]
) -> proto.DecodedSamples:
    """Feed ``data`` cut at ``cuts`` (sorted offsets), then flush; every piece's output checked."""
    express = isinstance(decoder, proto.ExpressScanDecoder)
    parts = []
    begin = 0
    for end in [*cuts, len(data)]:
        out = decoder.feed(data[begin:end])
        assert_physical(out, express)
        parts.append(out)
        begin = end
    out = decoder.flush()
    assert_physical(out, express)
    parts.append(out)
    return proto.DecodedSamples.concat(parts)


# -- streams: random bytes, and real streams mangled the way a serial line mangles them --------


def _standard_stream(draw: st.DrawFn) -> bytes:
    n = draw(st.integers(0, 400))
    step = draw(st.sampled_from([0.99, 0.5, 1.8, 0.13, 7.0]))
    start_deg = draw(st.floats(0, 359.9))
    angle = (start_deg + np.arange(n) * step) % 360.0
    seed = draw(st.integers(0, 2**16))
    rng = np.random.default_rng(seed)
    dist = rng.uniform(0, 16383, n)
    quality = rng.integers(0, 64, n)
    start = np.zeros(n, dtype=bool)
    start[1:] = np.diff(angle) < 0
    return proto.encode_standard_samples(angle, dist, quality, start)


def _express_stream(draw: st.DrawFn) -> bytes:
    count = draw(st.integers(0, 12))
    start_deg = draw(st.floats(0, 359.9))
    step = draw(st.sampled_from([11.0, 20.0, 31.5]))
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    return b"".join(
        proto.encode_express_capsule((start_deg + i * step) % 360.0, rng.integers(0, 16384, 32),
                                     rng.uniform(0, 3.875, 32), start=(i == 0))
        for i in range(count)
    )


@st.composite
def mangled(draw: st.DrawFn, express: bool) -> bytes:
    """A scan stream (maybe behind its descriptor) with flipped bits, inserted, deleted,
    repeated and truncated stretches, and stray descriptors."""
    data = bytearray(_express_stream(draw) if express else _standard_stream(draw))
    if draw(st.booleans()):
        data[:0] = (proto.EXPRESS_DESCRIPTOR if express else proto.SCAN_DESCRIPTOR).encode()
    for _ in range(draw(st.integers(0, 8))):
        kind = draw(st.sampled_from(["flip", "insert", "delete", "repeat", "descriptor", "truncate"]))
        at = draw(st.integers(0, len(data)))
        if kind == "flip" and data:
            at = min(at, len(data) - 1)
            data[at] ^= 1 << draw(st.integers(0, 7))
        elif kind == "insert":
            data[at:at] = draw(st.binary(min_size=1, max_size=40))
        elif kind == "delete":
            del data[at : at + draw(st.integers(1, 90))]
        elif kind == "repeat":
            data[at:at] = data[at : at + draw(st.integers(1, 90))]
        elif kind == "descriptor":
            d = draw(st.sampled_from([proto.SCAN_DESCRIPTOR, proto.EXPRESS_DESCRIPTOR, proto.HEALTH_DESCRIPTOR]))
            data[at:at] = d.encode()[: draw(st.integers(1, proto.DESCRIPTOR_LEN))]
        elif kind == "truncate":
            del data[at:]
    return bytes(data)


def any_stream(express: bool) -> st.SearchStrategy[bytes]:
    return st.one_of(st.binary(max_size=2048), mangled(express))


def cut_points(data: bytes, draw_cuts: list[int]) -> list[int]:
    return sorted({c % (len(data) + 1) for c in draw_cuts})


# -- the scan decoders -----------------------------------------------------------------------------


@FUZZ
@given(data=any_stream(express=False), cuts=st.lists(st.integers(0, 1 << 16), max_size=12))
@example(data=b"\xa5\x5a\x05\x00\x00\x40" + b"\x81" * 50, cuts=[6])
@example(data=bytes(range(256)) * 4, cuts=[1, 2, 3, 4, 5])
def test_standard_decoder_survives_any_stream_and_cutting_it_changes_nothing(data: bytes, cuts: list[int]) -> None:
    BUFFERS["standard"] += 1
    if sum(BUFFERS.values()) % 1000 == 0:
        report_counts()
    whole = proto.StandardScanDecoder()
    one = decode_in_pieces(whole, data, [])
    pieces = proto.StandardScanDecoder()
    cut = decode_in_pieces(pieces, data, cut_points(data, cuts))
    assert tuples(cut) == tuples(one)
    for dec in (whole, pieces):  # every byte is a sample, a skipped descriptor or dropped
        assert dec.samples_decoded == len(one)
        assert 5 * dec.samples_decoded + 7 * dec.descriptors_skipped + dec.bytes_dropped == len(data)
        assert dec.pending_bytes == 0


@FUZZ
@given(data=any_stream(express=True), cuts=st.lists(st.integers(0, 1 << 16), max_size=12))
@example(data=b"\xa5\x5a\x54\x00\x00\x40\x82" + b"\xa5" * 200, cuts=[3])
def test_express_decoder_survives_any_stream_and_cutting_it_changes_nothing(data: bytes, cuts: list[int]) -> None:
    BUFFERS["express"] += 1
    if sum(BUFFERS.values()) % 1000 == 0:
        report_counts()
    whole = proto.ExpressScanDecoder()
    one = decode_in_pieces(whole, data, [])
    pieces = proto.ExpressScanDecoder()
    cut = decode_in_pieces(pieces, data, cut_points(data, cuts))
    assert tuples(cut) == tuples(one)
    for dec in (whole, pieces):  # every capsule accepted is decoded or discarded; the rest dropped
        assert dec.samples_decoded == len(one) == proto.CAPSULE_SAMPLES * dec.capsules_decoded
        accepted = dec.capsules_decoded + dec.capsules_discarded
        assert proto.CAPSULE_LEN * accepted + 7 * dec.descriptors_skipped + dec.bytes_dropped == len(data)


@FUZZ
@given(data=st.binary(max_size=600), synced=st.booleans())
def test_a_decoder_reset_mid_stream_still_only_returns_physical_samples(data: bytes, synced: bool) -> None:
    """The driver resets a decoder when it restarts a scan (``synced``: right after a descriptor)."""
    BUFFERS["reset"] += 1
    if sum(BUFFERS.values()) % 1000 == 0:
        report_counts()
    for dec, express in ((proto.StandardScanDecoder(), False), (proto.ExpressScanDecoder(), True)):
        assert_physical(dec.feed(data[: len(data) // 2]), express)
        dec.reset(synced=synced)
        assert_physical(dec.feed(data[len(data) // 2 :]), express)
        assert_physical(dec.flush(), express)


# -- descriptors, single responses, requests -------------------------------------------------------


def _descriptor_like() -> st.SearchStrategy[bytes]:
    return st.one_of(
        st.binary(max_size=12),
        st.builds(lambda tail: b"\xa5\x5a" + tail, st.binary(min_size=0, max_size=8)),
    )


@FUZZ
@given(data=_descriptor_like(), expected=st.sampled_from([None, proto.SCAN_DESCRIPTOR, proto.HEALTH_DESCRIPTOR,
                                                          proto.INFO_DESCRIPTOR, proto.EXPRESS_DESCRIPTOR]))
def test_descriptor_parsing_only_ever_raises_protocol_error(data: bytes, expected: proto.Descriptor | None) -> None:
    BUFFERS["descriptor"] += 1
    if sum(BUFFERS.values()) % 1000 == 0:
        report_counts()
    try:
        found = proto.parse_descriptor(data, expected)
    except ProtocolError as exc:
        assert "\n" not in str(exc) and "descriptor" in str(exc)
        return
    assert data[:2] == b"\xa5\x5a"
    assert 0 <= found.length < 1 << 30 and found.mode in (proto.SendMode.SINGLE, proto.SendMode.MULTIPLE)
    assert found.encode() == bytes(data[:7])  # nothing read that is not there
    assert expected is None or found == expected


@FUZZ
@given(data=st.one_of(st.binary(max_size=24), st.binary(min_size=3, max_size=3), st.binary(min_size=20, max_size=20),
                      st.binary(min_size=4, max_size=4)))
def test_info_health_and_samplerate_answers_parse_or_raise_protocol_error(data: bytes) -> None:
    BUFFERS["responses"] += 1
    if sum(BUFFERS.values()) % 1000 == 0:
        report_counts()
    for parse in (proto.parse_info, proto.parse_health, proto.parse_samplerate):
        try:
            answer = parse(data)
        except ProtocolError as exc:
            assert "\n" not in str(exc) and "response" in str(exc)
            continue
        if isinstance(answer, proto.DeviceHealth):
            assert answer.status in proto.HEALTH_STATUS_NAMES and 0 <= answer.error_code <= 0xFFFF
            assert answer.status_name in ("good", "warning", "error")
        elif isinstance(answer, proto.DeviceInfo):
            assert len(answer.serial_number) == 16 and len(answer.serial_hex) == 32
            assert answer.model_name.startswith("A") and answer.firmware_version
        else:
            assert 0 <= answer.standard_us <= 0xFFFF and 0 <= answer.express_us <= 0xFFFF


@FUZZ
@given(data=st.one_of(st.binary(max_size=300), st.builds(lambda t: b"\xa5" + t, st.binary(max_size=300))))
def test_request_parsing_resyncs_over_any_bytes(data: bytes) -> None:
    """The emulator's side: parse, and on ProtocolError drop a byte, until the buffer is used up."""
    BUFFERS["requests"] += 1
    if sum(BUFFERS.values()) % 1000 == 0:
        report_counts()
    buf = data
    while buf:
        try:
            parsed = proto.parse_request(buf)
        except ProtocolError as exc:
            assert "\n" not in str(exc)
            buf = buf[1:]
            continue
        if parsed is None:
            break  # the start of a request: wait for more
        cmd, payload, used = parsed
        assert 0 < used <= len(buf) and buf[0] == proto.SYNC_BYTE and buf[1] == cmd
        assert len(payload) == (buf[2] if cmd & proto.CMD_FLAG_HAS_PAYLOAD else 0)
        buf = buf[used:]


# -- the driver's side: decoded samples into revolutions (Scan) ------------------------------------


class _Clock:
    def now_s(self) -> float:
        return 0.0


@FUZZ
@given(data=any_stream(express=False), express_data=any_stream(express=True))
def test_revolutions_built_from_any_stream_hold_only_valid_ranges(data: bytes, express_data: bytes) -> None:
    """What reaches SLAM: angles in [-pi, pi), ranges finite, valid ones inside the configured limits."""
    BUFFERS["revolutions"] += 1
    if sum(BUFFERS.values()) % 1000 == 0:
        report_counts()
    lidar = RPLidar(lambda: None, _Clock(), min_range_m=0.15, max_range_m=12.0)  # type: ignore[arg-type,return-value]
    for dec, stream in ((proto.StandardScanDecoder(), data), (proto.ExpressScanDecoder(), express_data)):
        builder = _RevolutionBuilder(lidar)
        samples = proto.DecodedSamples.concat([dec.feed(stream), dec.flush()])
        for scan in builder.add(samples, np.arange(len(samples), dtype=np.float64)):
            assert np.all((scan.angle_rad >= -np.pi) & (scan.angle_rad < np.pi))
            assert np.all(np.isfinite(scan.range_m)) and np.all(scan.range_m >= 0)
            r = scan.range_m[scan.valid]
            assert np.all((r >= 0.15) & (r <= 12.0))
            assert np.all(np.diff(scan.time_s) > 0)


@settings(FUZZ, max_examples=max(10, EXAMPLES // 4),
          suppress_health_check=[*FUZZ.suppress_health_check, HealthCheck.function_scoped_fixture])
@given(junk=st.one_of(st.binary(max_size=300), st.lists(st.sampled_from(
    [b"\xa5", b"\x5a", b"\xa5\x5a", proto.SCAN_DESCRIPTOR.encode()[:5], b"RP LIDAR System.\r\n"]),
    max_size=20).map(b"".join)))
async def test_the_driver_finds_its_answers_behind_any_junk(lidar_line, junk: bytes) -> None:
    """The real driver on an in-memory line whose device sends ``junk`` before every answer
    (a boot message, stale scan bytes): the right answer, or one line saying what was wrong."""
    BUFFERS["driver"] += 1
    if sum(BUFFERS.values()) % 1000 == 0:
        report_counts()
    lidar_line.device_options["junk_before_answers"] = junk  # the next device plugged in sends it
    lidar = RPLidar(lidar_line, RealClock(), response_timeout_s=0.5, spin_up_s=0.0)
    try:
        try:
            info = await lidar.get_info()
            health = await lidar.get_health()
        except MazebotError as exc:  # a5 5a + a known descriptor inside the junk: the device "answered" wrong
            assert "\n" not in str(exc) and b"\xa5\x5a" in junk, (junk, exc)
            return
        assert info.model == proto.MODEL_A1M8 and health.status == proto.HEALTH_GOOD
    finally:
        await lidar.close()


# -- regressions the fuzzing found --------------------------------------------------------------


def test_a_sample_just_before_a_possible_descriptor_at_the_end_of_a_read_is_not_dropped() -> None:
    """``00 00 01 a5 | 00 00 00 00``: the read ends on 0xA5 (a descriptor may begin there),
    and the well-formed sample at offset 2 could not be judged yet; the decoder used to drop
    it with the bytes before the 0xA5, so cutting the stream there changed the samples."""
    data = b"\x00\x00\x01\xa5\x00\x00\x00\x00"
    whole = decode_in_pieces(proto.StandardScanDecoder(), data, [])
    cut = decode_in_pieces(proto.StandardScanDecoder(), data, [4])
    assert tuples(whole) == tuples(cut) == [(82 / 64, 0.0, 0, True)]
