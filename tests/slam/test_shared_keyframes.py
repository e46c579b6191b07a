"""Keyframes' arrays in shared memory: the same values on both sides, one copy, bounded, unlinked
when the daemon shuts down and when it is killed."""

from __future__ import annotations

import gc
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mazebot.slam.keyframes import Keyframe
from mazebot.slam.shared_keyframes import KeyframeArena, SegmentReader

SHM = Path("/dev/shm")
pytestmark = pytest.mark.skipif(not SHM.is_dir(), reason="POSIX shared memory in /dev/shm (Linux)")


def _keyframe(index: int, seed: int = 0) -> Keyframe:
    rng = np.random.default_rng(seed + index)
    angle = np.linspace(-np.pi, np.pi, 320, endpoint=False)
    hits = np.column_stack((np.cos(angle), np.sin(angle))) * rng.uniform(0.15, 1.5, size=(320, 1))
    return Keyframe(index=index, time_s=0.1 * index, pose=np.array([0.1 * index, 0.0, 0.0]), hits=hits,
                    match_points=hits[::3], sensor_xy=np.zeros(2), ray_ends=hits,
                    ray_hit=rng.random(320) < 0.9, integrated_pose=np.zeros(3))


def _same(a: Keyframe, b: Keyframe) -> None:
    for name in ("hits", "match_points", "ray_ends", "ray_hit", "points", "normals", "lift_m", "sensor_xy"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def _segments(tag: str) -> list[str]:
    return sorted(p.name for p in SHM.glob(f"{tag}-*"))


def test_the_worker_reads_the_daemons_arrays_not_a_copy() -> None:
    arena = KeyframeArena()
    try:
        kf, twin = _keyframe(0), _keyframe(0)
        kf.surface()
        sent = arena.share(kf)
        _same(kf, twin)  # moving the arrays changed no value
        assert all(not a.flags.writeable for a in kf.packed().values())  # written once, read-only after
        replica = SegmentReader().keyframe(sent)
        _same(replica, twin)
        assert replica.has_surface  # computed by the daemon, not again here
        for name, array in replica.packed().items():  # the replica's arrays are views of the segment
            assert array.base is not None and not array.flags.owndata, name
        assert _segments(arena.tag) == [f"{arena.tag}-0"]
    finally:
        arena.close()


def test_a_keyframe_is_written_once_and_its_later_surface_added() -> None:
    arena = KeyframeArena()
    try:
        kf = _keyframe(1)
        first = arena.share(kf)
        assert "surface_points" not in first.places
        used = arena._used
        assert arena.share(kf).places == first.places and arena._used == used  # sent again: nothing written
        kf.surface()
        later = arena.share(kf)
        assert {"surface_points", "surface_normals"} <= set(later.places)
        assert later.places["hits"] == first.places["hits"]
        _same(SegmentReader().keyframe(later), kf)
    finally:
        arena.close()


def test_a_long_life_takes_what_its_keyframes_hold_and_no_more() -> None:
    """Two thousand keyframes (a 16×16 maze's tour): the segments hold their bytes, plus alignment
    and the last segment's end; each keyframe shared again adds nothing."""
    arena = KeyframeArena(segment_bytes=1024 * 1024)
    try:
        held = 0
        for i in range(2000):
            kf = _keyframe(i)
            kf.surface()
            held += sum(a.nbytes for a in kf.packed().values())
            arena.share(kf)
            arena.share(kf)
        count = len(arena.segment_names)
        assert held <= count * arena.segment_bytes
        assert count * arena.segment_bytes <= held + 2000 * 6 * 16 + 2 * arena.segment_bytes
        assert len(_segments(arena.tag)) == count
    finally:
        arena.close()
    assert _segments(arena.tag) == []


def test_closing_unlinks_and_the_arrays_stay_readable() -> None:
    arena = KeyframeArena()
    kf, twin = _keyframe(2), _keyframe(2)
    arena.share(kf)
    assert _segments(arena.tag)
    arena.close()
    arena.close()  # idempotent
    assert _segments(arena.tag) == []
    with pytest.raises(RuntimeError, match="closed"):
        arena.share(kf)
    del arena
    gc.collect()
    _same(kf, twin)  # the arena gone, the mapping lives as long as the keyframe's arrays do


KILLED = r"""
import json, os, signal, sys
import numpy as np
sys.path.insert(0, sys.argv[1])
from test_shared_keyframes import _keyframe
from mazebot.slam.shared_keyframes import KeyframeArena

arena = KeyframeArena()
for i in range(50):
    arena.share(_keyframe(i))
print(json.dumps({"tag": arena.tag, "segments": arena.segment_names}), flush=True)
os.kill(os.getpid(), signal.SIGKILL)  # no clean-up of ours runs
"""


def test_a_killed_daemon_leaves_no_segment(tmp_path: Path) -> None:
    script = tmp_path / "daemon.py"
    script.write_text(KILLED)
    out = subprocess.run([sys.executable, str(script), str(Path(__file__).parent)], capture_output=True, text=True,
                         timeout=60)
    seen = json.loads(out.stdout.splitlines()[0])
    assert seen["segments"]
    deadline = time.monotonic() + 20.0  # multiprocessing's resource tracker unlinks them once the daemon is gone
    while _segments(seen["tag"]) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _segments(seen["tag"]) == []
