"""The standard-scan decoder's shortcut for clean stretches against its full rhythm check.

``StandardScanDecoder._steady_run`` accepts a block of samples without building a
sorted window per sample, when every step is obviously inside the rhythm. The full
check (``FAST_PATH = False``) is the reference: on clean, noisy, cut, resumed and random
streams both must give the same samples, the same counters and the same split into
``feed`` calls' results.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from mazebot.io import rplidar_protocol as proto


class _ReferenceDecoder(proto.StandardScanDecoder):
    FAST_PATH = False


class _CountingDecoder(proto.StandardScanDecoder):
    """Counts the blocks the shortcut decided, so the tests know they exercised it."""

    shortcuts = 0

    def _steady_run(self, angle: np.ndarray, ok: np.ndarray, size: int) -> int | None:
        r = super()._steady_run(angle, ok, size)
        self.shortcuts += r is not None
        return r


def _revolutions(rng: np.random.Generator, revs: int, per_rev: int = 360, jitter_deg: float = 0.0) -> bytes:
    """A standard-mode stream as the A1 sends it: evenly stepping angles, start flags."""
    parts = []
    for _ in range(revs):
        angle = (np.arange(per_rev) * (360.0 / per_rev) + rng.normal(0, jitter_deg, per_rev)) % 360.0
        dist = np.where(rng.random(per_rev) < 0.05, 0.0, rng.uniform(150, 4000, per_rev))
        quality = np.where(dist > 0, 47, 0)
        start = np.zeros(per_rev, dtype=bool)
        start[0] = True
        parts.append(proto.encode_standard_samples(angle, dist, quality, start))
    return b"".join(parts)


def _damage(rng: np.random.Generator, data: bytes, events: int) -> bytes:
    """Garbage inserted, bytes lost, and a scan descriptor (a restarted scan) in between."""
    out = bytearray(data)
    for _ in range(events):
        at = int(rng.integers(0, len(out)))
        kind = rng.integers(0, 3)
        if kind == 0:
            out[at:at] = rng.integers(0, 256, int(rng.integers(1, 12)), dtype=np.uint8).tobytes()
        elif kind == 1:
            del out[at : at + int(rng.integers(1, 12))]
        else:
            out[at:at] = proto.SCAN_DESCRIPTOR.encode()
    return bytes(out)


def _decode(decoder: proto.StandardScanDecoder, data: bytes, cuts: np.ndarray, synced: bool) -> list:
    decoder.reset(synced=synced)
    results = []
    for lo, hi in itertools.pairwise(cuts):
        results.append(decoder.feed(data[lo:hi]))
    results.append(decoder.flush())
    return results


def _assert_same(data: bytes, rng: np.random.Generator, synced: bool) -> _CountingDecoder:
    cuts = np.unique(np.concatenate([[0, len(data)], rng.integers(0, len(data), len(data) // 150 + 1)]))
    fast, ref = _CountingDecoder(), _ReferenceDecoder()
    got = _decode(fast, data, cuts, synced)
    want = _decode(ref, data, cuts, synced)
    for g, w in zip(got, want, strict=True):
        for field in ("angle_deg", "dist_mm", "quality", "start"):
            np.testing.assert_array_equal(getattr(g, field), getattr(w, field))
    assert (fast.bytes_dropped, fast.samples_decoded, fast.descriptors_skipped) == (
        ref.bytes_dropped,
        ref.samples_decoded,
        ref.descriptors_skipped,
    )
    return fast


@pytest.mark.parametrize("seed", range(6))
def test_clean_stream_round_trips_and_matches_the_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    data = _revolutions(rng, 4)
    fast = _assert_same(data, rng, synced=True)
    assert fast.samples_decoded == 4 * 360
    assert fast.shortcuts > 0
    whole = proto.StandardScanDecoder()
    whole.reset(synced=True)
    samples = proto.DecodedSamples.concat([whole.feed(data), whole.flush()])
    np.testing.assert_allclose(samples.angle_deg, np.tile(np.arange(360.0), 4), atol=1 / 128)
    assert samples.start.sum() == 4


@pytest.mark.parametrize("seed", range(10))
def test_damaged_stream_matches_the_reference(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    jitter_deg = (0.0, 0.01, 0.1)[seed % 3]  # the last is beyond the shortcut's band
    data = _damage(rng, _revolutions(rng, 3, jitter_deg=jitter_deg), events=12)
    fast = _assert_same(data, rng, synced=True)
    assert fast.shortcuts > 0 or jitter_deg > 0.05


@pytest.mark.parametrize("seed", range(6))
def test_mid_stream_start_matches_the_reference(seed: int) -> None:
    rng = np.random.default_rng(200 + seed)
    data = _revolutions(rng, 3, per_rev=int(rng.choice([180, 360, 720])))
    assert _assert_same(data[int(rng.integers(1, 400)) :], rng, synced=False).shortcuts > 0


@pytest.mark.parametrize("seed", range(4))
def test_jittery_and_random_streams_match_the_reference(seed: int) -> None:
    rng = np.random.default_rng(300 + seed)
    _assert_same(_revolutions(rng, 2, jitter_deg=0.3), rng, synced=True)  # no rhythm: form alone
    _assert_same(rng.integers(0, 256, 3000, dtype=np.uint8).tobytes(), rng, synced=False)
