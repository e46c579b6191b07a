"""Keyframes' arrays in shared memory: written once by the daemon, read by its loop-closure worker.

The loop-closure worker keeps every keyframe (:mod:`mazebot.slam.loop_worker`), and so does the
daemon: a second copy of a few kilobytes per keyframe, thousands of keyframes in a 16×16 maze,
which grew the worker by about 20 MB over a 1 000 s run of a contest maze (``tools/pss_by_process.py``).
A keyframe's scan arrays never change once it is made (only its pose does), so both processes can
read one copy: the daemon moves each keyframe's packed arrays (hits, match points, rays, the surface
once computed: :meth:`mazebot.slam.keyframes.Keyframe.packed`) into shared-memory segments the
first time it ships the keyframe, and holds read-only views of them from then on; the worker gets
where they are (:class:`SharedKeyframe`, a few hundred bytes) instead of the arrays, and maps
the segments read-only. A page of a segment is counted once, split between the two processes
(``Pss``: kernel documentation, ``Documentation/filesystems/proc.rst``).

One writer: only the daemon's :class:`KeyframeArena` creates and writes segments, append-only,
never rewriting a byte once a keyframe is placed. Lifetime: the arena unlinks its segments when
the loop-closure executor shuts down; if the daemon dies without that (killed, crashed),
multiprocessing's resource tracker, a process of its own with which every segment is registered
at creation, unlinks them when the daemon's processes are gone (Python's
:mod:`multiprocessing.shared_memory`). A worker that dies leaves the segments to the daemon;
its successor maps them again.

Example::

    arena = KeyframeArena()
    shared = arena.share(keyframe)        # in the daemon: its arrays now live in shared memory
    replica = SegmentReader().keyframe(shared)   # in the worker: the same arrays, not copied
    arena.close()                          # the segments are unlinked
"""

from __future__ import annotations

import contextlib
import os
import uuid
from dataclasses import dataclass
from multiprocessing.shared_memory import SharedMemory
from typing import Any

import numpy as np

from mazebot.slam.keyframes import Keyframe
from mazebot.slam_config import NormalParams

#: Bytes of one segment: about 700 keyframes of a maze (~6 kB each). Pages are taken from the
#: kernel only when written, so the last segment's unused end costs nothing.
SEGMENT_BYTES = 4 * 1024 * 1024
#: Every array starts on a multiple of this many bytes (the widest element kept, float64, and more).
ALIGN_BYTES = 16
#: Segment names start with this (``/dev/shm/mazebot-kf-PID-...`` on Linux).
NAME_PREFIX = "mazebot-kf-"


class _Segment(SharedMemory):
    """A segment whose arrays may outlive this object: a close refused for them is no error.

    The views are made with :func:`numpy.frombuffer`, which holds an export of the segment's
    buffer for as long as the array (or a view of it) lives, so the mapping cannot be closed
    under them (:meth:`close` refuses with a ``BufferError``); it goes when the last of them does.
    """

    def __del__(self) -> None:
        try:
            self.close()
        except BufferError:  # arrays still read it: they keep the mapping, which needs no descriptor
            fd: int = getattr(self, "_fd", -1)
            with contextlib.suppress(OSError):
                if fd >= 0:
                    os.close(fd)
                self._fd = -1
        except OSError:
            pass


def _view(segment: _Segment, offset: int, dtype: np.dtype[Any], shape: tuple[int, ...]) -> np.ndarray:
    """An array over the segment's bytes at ``offset`` that keeps the mapping alive while it lives."""
    count = int(np.prod(shape, dtype=np.int64))
    buffer = segment.buf
    assert buffer is not None, "the segment is closed"
    return np.frombuffer(buffer, dtype=dtype, count=count, offset=offset).reshape(shape)


#: Where one array lives: (segment name, byte offset, dtype string, shape).
Place = tuple[str, int, str, tuple[int, ...]]


@dataclass(frozen=True)
class SharedKeyframe:
    """A keyframe as shipped to the worker: its small fields, and where its arrays are."""

    index: int
    time_s: float
    pose: np.ndarray
    sensor_xy: np.ndarray
    integrated_pose: np.ndarray
    normal_params: NormalParams
    ray_count: int
    caches: dict[str, Any]
    places: dict[str, Place]


class KeyframeArena:
    """The daemon's side: shared segments, appended to, that keyframes' arrays are moved into."""

    def __init__(self, segment_bytes: int = SEGMENT_BYTES) -> None:
        self.segment_bytes = segment_bytes
        self.tag = f"{NAME_PREFIX}{os.getpid()}-{uuid.uuid4().hex[:8]}"
        self._segments: list[_Segment] = []
        self._used = segment_bytes  # no segment yet: the first array opens one
        self._places: dict[int, dict[str, Place]] = {}  # id(keyframe) -> its arrays' places
        self._kept: dict[int, Keyframe] = {}  # the keyframes placed (so their ids stay theirs)
        self.closed = False

    @property
    def segment_names(self) -> list[str]:
        return [s.name for s in self._segments]

    def share(self, keyframe: Keyframe) -> SharedKeyframe:
        """``keyframe`` as the worker is sent it; its arrays are moved here first if they are not yet.

        A surface computed since the keyframe was first shared is moved too. The keyframe then
        holds read-only views of the shared copies (the values are the same).
        """
        if self.closed:
            raise RuntimeError("the keyframe arena is closed")
        key = id(keyframe)
        places = self._places.setdefault(key, {})
        self._kept[key] = keyframe
        arrays = keyframe.packed()
        moved = {}
        for name, array in arrays.items():
            if name not in places:
                places[name], moved[name] = self._write(array)
        if moved:
            keyframe.use_packed(moved)
        caches = keyframe.caches()
        return SharedKeyframe(
            index=keyframe.index,
            time_s=keyframe.time_s,
            pose=keyframe.pose.copy(),
            sensor_xy=keyframe.sensor_xy,
            integrated_pose=keyframe.integrated_pose.copy(),
            normal_params=keyframe.normal_params,
            ray_count=keyframe.ray_count,
            caches=caches,
            places=dict(places),
        )

    def _write(self, array: np.ndarray) -> tuple[Place, np.ndarray]:
        array = np.ascontiguousarray(array)
        size = array.nbytes
        start = -(-self._used // ALIGN_BYTES) * ALIGN_BYTES
        if start + size > self.segment_bytes or not self._segments:
            if size > self.segment_bytes:
                raise ValueError(f"an array of {size} bytes does not fit a segment of {self.segment_bytes}")
            name = f"{self.tag}-{len(self._segments)}"
            self._segments.append(_Segment(name=name, create=True, size=self.segment_bytes))
            start = 0
        segment = self._segments[-1]
        view = _view(segment, start, array.dtype, tuple(array.shape))
        view[...] = array
        view.flags.writeable = False
        self._used = start + size
        return (segment.name, start, array.dtype.str, tuple(array.shape)), view

    def close(self) -> None:
        """Unlink every segment (idempotent). The keyframes' views stay readable until they are gone."""
        if self.closed:
            return
        self.closed = True
        for segment in self._segments:
            with contextlib.suppress(FileNotFoundError):
                segment.unlink()
        self._places.clear()
        self._kept.clear()


class SegmentReader:
    """The worker's side: the daemon's segments mapped (each once), keyframes made of views into them."""

    def __init__(self) -> None:
        self._segments: dict[str, _Segment] = {}

    def keyframe(self, shared: SharedKeyframe) -> Keyframe:
        arrays = {name: self._view(place) for name, place in shared.places.items()}
        kf = Keyframe.from_packed(
            shared.index, shared.time_s, shared.pose, shared.sensor_xy, shared.integrated_pose,
            shared.normal_params, shared.ray_count, arrays,
        )
        kf.use_caches(shared.caches)
        return kf

    def _view(self, place: Place) -> np.ndarray:
        name, offset, dtype, shape = place
        segment = self._segments.get(name)
        if segment is None:
            segment = _Segment(name=name)  # also registered with the daemon's resource tracker: harmless
            self._segments[name] = segment
        view = _view(segment, offset, np.dtype(dtype), shape)
        view.flags.writeable = False
        return view

    def forget(self) -> None:
        """Drop the mappings (a new owner's keyframes are coming); the views still held keep theirs."""
        self._segments = {}
