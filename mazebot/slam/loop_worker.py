"""Loop-closure jobs on a core of their own: a worker process that keeps the keyframes.

A loop-closure job (:class:`mazebot.slam.slam.LoopClosureJob`: verification ICP,
pose-graph optimization, grid rebuild) is tens of milliseconds of mostly small numpy
operations. In a thread it holds the GIL for most of that time, so the event loop, and
with it the control loop and the per-scan SLAM update, waits behind it. In a worker
process it runs beside them (the Pi 4 has four cores).

Shipping a job to another process means pickling it, and a job refers to every keyframe
(a few kilobytes each, thousands in a big maze). A keyframe's scan data never change once
it is made (only its pose does, and a job carries its own copy of the poses), so the
worker keeps a replica of the keyframe list and each job carries only the keyframes
added since the previous one (:class:`JobShipper`). A worker that lacks keyframes (a
fresh process, a job that was cancelled before it ran) says so, and gets them all.

Example::

    executor = LoopClosureExecutor("process")
    future = executor.submit(update.loop_job)    # concurrent.futures.Future
    slam.apply(future.result())
    executor.shutdown()
"""

from __future__ import annotations

import contextlib
import gc
import logging
import multiprocessing
import os
import signal
import threading
import time
import uuid
from collections.abc import Callable
from concurrent.futures import Executor, Future, ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace
from typing import Any

from mazebot.fork_server import FORKSERVER_PRELOAD as FORKSERVER_PRELOAD  # what the fork server imports
from mazebot.malloc_tuning import give_back_free_memory
from mazebot.slam.keyframes import Keyframe
from mazebot.slam.shared_keyframes import KeyframeArena, SegmentReader, SharedKeyframe
from mazebot.slam.slam import LoopClosureJob, LoopClosureResult

log = logging.getLogger(__name__)

#: Where loop-closure jobs can run (``[slam] loop_closure_executor``).
EXECUTOR_KINDS = ("process", "thread")


class MissingKeyframes(RuntimeError):
    """The worker's replica is shorter than the job assumes: ship every keyframe again."""


@dataclass(frozen=True)
class ShippedJob:
    """A job as sent to the worker: ``job`` without its keyframes, plus the ones the worker lacks.

    ``owner`` names the :class:`JobShipper` (one per SLAM instance and worker); ``fresh``
    are the keyframes from index ``first`` on: where their arrays are in shared memory
    (:class:`~mazebot.slam.shared_keyframes.SharedKeyframe`), or the keyframes themselves
    where shared memory is not to be had. ``surfaces`` are keyframes sent before without a
    surface that have one now (position in the list, where its arrays are).
    """

    owner: str
    first: int
    fresh: list[SharedKeyframe] | list[Keyframe]
    count: int
    job: LoopClosureJob
    surfaces: tuple[tuple[int, SharedKeyframe], ...] = ()


class _Replica:
    """The worker process's copy of one owner's keyframes (only the newest owner is kept)."""

    def __init__(self) -> None:
        self.owner: str | None = None
        self.keyframes: list[Keyframe] = []
        self.segments = SegmentReader()

    def _keyframe(self, sent: SharedKeyframe | Keyframe) -> Keyframe:
        return self.segments.keyframe(sent) if isinstance(sent, SharedKeyframe) else sent

    def run(self, shipped: ShippedJob) -> LoopClosureResult:
        if self.owner != shipped.owner:
            if shipped.first > 0:
                raise MissingKeyframes(f"the worker holds no keyframes of this SLAM, the job starts at {shipped.first}")
            self.owner, self.keyframes = shipped.owner, []
            self.segments.forget()
        store = self.keyframes
        if len(store) < shipped.first:
            raise MissingKeyframes(f"the worker holds {len(store)} keyframes, the job starts at {shipped.first}")
        del store[shipped.first :]
        store.extend(self._keyframe(sent) for sent in shipped.fresh)
        for position, shared in shipped.surfaces:  # the daemon's copy replaces the one made here, if any
            if position < len(store):
                store[position].use_packed(self._keyframe(shared).packed())
        result = replace(shipped.job, keyframes=store[: shipped.count]).run()
        for kf in store:  # the jobs made their surfaces: the hits are not read again here
            kf.keep_surface_only()
        give_back_free_memory()  # the job's temporaries, before the worker waits for the next one
        return result


#: In a worker process: the keyframes it was sent (the state a worker exists to keep).
_REPLICA = _Replica()


def run_shipped(shipped: ShippedJob) -> LoopClosureResult:
    """Run a shipped job in the worker process against its keyframe replica."""
    return _REPLICA.run(shipped)


def _warm_up() -> None:
    """Nothing: the first task makes the pool start its worker while the daemon starts."""


def _watch_daemon(daemon_pid: int, nice: int = 0, period_s: float = 1.0) -> None:
    """Worker initializer: lower the worker's priority by ``nice``, and exit when the daemon is gone.

    Jobs ran 0.5-1.1 s each late in a 16x16 run under a 25 % quota. Where the worker shares a CPU with the
    daemon (a Pi with its other cores busy, a CPU quota) it took half of it whenever both
    were ready, and the revolutions that arrived meanwhile piled up behind SLAM until the
    oldest were dropped. At nice 19 the scheduler gives the worker what the daemon leaves
    (a weight of 15 against the daemon's 1024: the kernel's ``sched_prio_to_weight``) and a
    closure lands later. Not enough under a quota, which counts the CPU of every core while
    nice weighs the tasks of one: the worker spent the budget while the main thread slept, so
    SLAM also pauses it while it is behind (:meth:`LoopClosureExecutor.pause`). With a core to
    itself nothing changes.

    A pool's worker waits on a pipe whose both ends it inherited, so a daemon killed
    without its clean-up (SIGKILL, a crash) would leave it waiting for ever. The objects
    inherited from the fork server are kept out of the garbage collector's passes, whose
    writes would copy their pages into this process (``gc.freeze``).
    """
    gc.freeze()
    _die_with_parent()
    if nice > os.getpriority(os.PRIO_PROCESS, 0):  # lowered only: raising it needs privileges
        try:
            os.setpriority(os.PRIO_PROCESS, 0, nice)
        except OSError as exc:  # never fatal: the jobs run at the daemon's priority
            log.warning("the loop-closure worker keeps the daemon's priority (nice %d refused: %s)", nice, exc)

    def watch() -> None:
        while True:
            time.sleep(period_s)
            try:
                os.kill(daemon_pid, 0)
            except ProcessLookupError:
                os._exit(0)

    threading.Thread(target=watch, name="mazebot-daemon-watch", daemon=True).start()


#: prctl(2)'s option that sends this process a signal when its parent ends (linux/prctl.h).
PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    """Have the kernel kill this worker when its parent (the fork server) ends (prctl(2), Linux only).

    The watch thread below cannot run while the daemon has paused the worker
    (:meth:`LoopClosureExecutor.pause`); the fork server ends with the daemon, and SIGKILL
    ends even a stopped process. Best effort: without it the watch thread still acts on a
    worker that is not paused.
    """
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except (OSError, AttributeError):  # not Linux, or no libc to be found
        pass


class JobShipper:
    """The main process's side of the replica: which keyframes the worker has been sent.

    With ``share`` the keyframes' arrays go into shared memory the first time they are sent
    (:class:`~mazebot.slam.shared_keyframes.KeyframeArena`), and the worker is sent where they
    are; where shared memory cannot be had, the keyframes themselves are sent, as without.
    """

    def __init__(self, share: bool = False) -> None:
        self.owner = uuid.uuid4().hex
        self.shipped = 0
        self.arena: KeyframeArena | None = KeyframeArena() if share else None
        self._no_surface: dict[int, Keyframe] = {}  # sent before their surface was computed, by position

    def pack(self, job: LoopClosureJob) -> ShippedJob:
        count = len(job.keyframes)
        first = min(self.shipped, count)
        self.shipped = count
        fresh = job.keyframes[first:]
        if self.arena is not None:
            try:
                return self._pack_shared(job, first, count, self.arena)
            except OSError as exc:  # no /dev/shm, or full: the arrays go with the job, as before
                log.warning("keyframes cannot be shared with the loop-closure worker (%s); sending copies", exc)
                self.close()
                self.shipped, first = 0, 0
                fresh = job.keyframes
        return ShippedJob(self.owner, first, fresh, count, replace(job, keyframes=[]))

    def _pack_shared(self, job: LoopClosureJob, first: int, count: int, arena: KeyframeArena) -> ShippedJob:
        surfaces = []
        for position, kf in list(self._no_surface.items()):
            if position >= first or position >= count:
                del self._no_surface[position]
            elif kf.has_surface:
                surfaces.append((position, arena.share(kf)))
                del self._no_surface[position]
        fresh = []
        for position in range(first, count):
            kf = job.keyframes[position]
            fresh.append(arena.share(kf))
            if not kf.has_surface:
                self._no_surface[position] = kf
        return ShippedJob(self.owner, first, fresh, count, replace(job, keyframes=[]), tuple(surfaces))

    def reset(self) -> None:
        self.shipped = 0
        self._no_surface.clear()

    def close(self) -> None:
        """Unlink the shared keyframes (idempotent); later jobs send copies."""
        if self.arena is not None:
            self.arena.close()
            self.arena = None


class LoopClosureExecutor(Executor):
    """Runs loop-closure jobs in a worker process (``"process"``) or a thread (``"thread"``).

    It is a :class:`concurrent.futures.Executor`: a :class:`LoopClosureJob` submitted
    alone goes to the worker; any other callable (the search for a lost robot, which
    reads the live SLAM object) runs in this process, in one thread of its own.

    One job at a time (SLAM never has two in flight). A worker missing keyframes gets all
    of them and the job is retried once. A worker that dies (killed, out of memory) fails
    the job in progress, if any (a SLAM fault: the wheels stop until SLAM runs again); the
    next job starts a new worker.

    The worker is forked from multiprocessing's fork server, which imports the main
    module of the program as ``__mp_main__``: a script that starts the daemon needs the
    usual ``if __name__ == "__main__":`` guard (``mazebot`` and ``python -m mazebot`` have it).
    """

    def __init__(self, kind: str = "process", nice: int = 0) -> None:
        if kind not in EXECUTOR_KINDS:
            raise ValueError(f"loop-closure executor must be one of {', '.join(EXECUTOR_KINDS)}, got {kind!r}")
        self.kind = kind
        self.nice = nice  # the worker process's (``[slam] loop_closure_nice``); a thread keeps the daemon's
        #: the worker processes stopped by :meth:`pause` (their pids), until :meth:`resume`
        self._paused: list[int] = []
        self._shipper = JobShipper(share=kind == "process")
        self._pool: ProcessPoolExecutor | ThreadPoolExecutor | None = None
        self._local = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mazebot-slam-local")
        self._broken = False
        self._start()

    def _start(self) -> None:
        if self.kind == "thread":
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mazebot-slam")
            return
        # forkserver: workers fork from a clean process that imported SLAM once, never from
        # this one (whose threads a fork could catch holding a lock)
        context = multiprocessing.get_context("forkserver")
        context.set_forkserver_preload(list(FORKSERVER_PRELOAD))
        self._pool = ProcessPoolExecutor(
            max_workers=1, mp_context=context, initializer=_watch_daemon, initargs=(os.getpid(), self.nice)
        )
        # starting the worker waits for the fork server to import numpy and scipy (a second
        # or more on a Pi): a thread of its own does it, so the daemon's start never waits
        pool = self._pool
        threading.Thread(target=pool.submit, args=(_warm_up,), name="mazebot-slam-start", daemon=True).start()
        self._shipper.reset()

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future[Any]:
        """Start ``fn(*args, **kwargs)``; the future holds its result (or the exception it raised).

        A lone :class:`LoopClosureJob` runs where ``kind`` says; anything else runs in
        this process's local thread.
        """
        assert self._pool is not None, "submit after shutdown"
        if not isinstance(fn, LoopClosureJob) or args or kwargs:
            return self._local.submit(fn, *args, **kwargs)
        if self.kind == "thread":
            return self._pool.submit(fn.run)
        outer: Future[LoopClosureResult] = Future()
        self._send(fn, outer, retry=True)
        return outer

    def _send(self, job: LoopClosureJob, outer: Future[LoopClosureResult], retry: bool) -> None:
        if self._broken:
            self._replace_pool()
        try:
            inner = self._pool.submit(run_shipped, self._shipper.pack(job))  # type: ignore[union-attr]
        except BrokenProcessPool:  # the worker died between jobs: a new one gets every keyframe
            log.warning("loop-closure worker died; starting another")
            self._replace_pool()
            inner = self._pool.submit(run_shipped, self._shipper.pack(job))  # type: ignore[union-attr]

        def done(f: Future[LoopClosureResult]) -> None:
            if outer.cancelled():
                return
            if f.cancelled():
                outer.cancel()
                return
            exc = f.exception()
            if retry and isinstance(exc, MissingKeyframes):
                log.warning("loop-closure worker: %s; sending every keyframe again", exc)
                self._shipper.reset()
                self._send(job, outer, retry=False)
                return
            if isinstance(exc, BrokenProcessPool):
                self._broken = True  # replaced at the next job; this one is lost (and reported)
            if exc is not None:
                outer.set_exception(exc)
            else:
                outer.set_result(f.result())

        inner.add_done_callback(done)

    @property
    def paused(self) -> bool:
        """True between :meth:`pause` and :meth:`resume` while a worker process was stopped."""
        return bool(self._paused)

    def pause(self) -> bool:
        """Stop the worker process where it stands (SIGSTOP) until :meth:`resume`; True if one was stopped.

        Why: under a CPU quota the worker and the daemon draw on one budget, and a worker on
        another core of the machine draws on it at once, whatever its nice value (nice weighs
        tasks on one core's queue, a quota counts the CPU of every core). A 16x16 job of
        seconds then left SLAM's thread a fraction of what it needs, and revolutions were
        dropped. Paused, the job takes no CPU at all; it goes on, unchanged, where it stood.
        A thread executor has nothing to stop (False). The worker itself dies with its fork
        server (``PR_SET_PDEATHSIG``), so a daemon killed while it is paused leaves no
        stopped process behind.
        """
        if self.kind != "process" or self._paused or self._pool is None:
            return False
        workers = getattr(self._pool, "_processes", None) or {}  # the pool's worker processes by pid
        for pid, process in list(workers.items()):
            if process.exitcode is not None:  # ended: its pid may be another process's by now
                continue
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGSTOP)
                self._paused.append(pid)
        return bool(self._paused)

    def resume(self) -> None:
        """Let a paused worker go on (SIGCONT); idempotent."""
        paused, self._paused = self._paused, []
        for pid in paused:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)

    def _replace_pool(self) -> None:
        self.resume()
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
        self._broken = False
        self._start()

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = True) -> None:
        """Stop the worker after the job in progress, if any (its result goes unseen); idempotent.

        Waiting (tens of milliseconds) lets the pool close its pipes before the interpreter
        exits; without it Python's exit hook writes to a closed one.
        """
        self.resume()  # a stopped worker could not finish its job nor exit
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=cancel_futures)
            self._pool = None
        self._shipper.close()  # after the worker: it read the shared keyframes to the end
        self._local.shutdown(wait=wait, cancel_futures=cancel_futures)
