"""The motor control loop in a process of its own (``[daemon] control_process``, the real clock).

Why one module of ~660 lines: the shared memory's layout, its seqlock, the parent's side and
the child's side must agree byte for byte; with the layout and both of its readers and writers
in one file, an offset changed in one place is seen changed in all.

Why a process: under a CPU quota the daemon's main process is often frozen by the
throttle while it holds the interpreter lock, and C calls (numpy, scipy's k-d trees) hold
it for milliseconds more; a control *thread* waits for that lock however the kernel
schedules it. A process has its own lock, and one that sleeps most of the time is woken
ahead of the busy main process by the kernel's fair scheduler (CFS favours tasks with
little run time: Linux ``Documentation/scheduler/sched-design-CFS.rst``).

The two processes share one block of memory (:class:`ControlLink`), a fixed layout of
float64 with a sequence counter per block (a seqlock: the writer makes the counter odd,
writes, makes it even; a reader retries while it is odd or changed, and after a few tries
keeps its previous copy, so neither side ever waits for the other). No pickling on the
hot path.

- main -> child: the planner's motion command, the direct throttle command, the setup
  page's jog request, the run state's ``moving`` and ``jog_allowed``, ``stopping``,
  ``faults_raised``, the wheel ticks with their stamp and
  the odometry poses (now, and at the latest scan's end), the latest scan's robot-frame
  points (de-skewed) with its end time, the planner's remembered blind-zone returns.
  :class:`SharedState` mirrors each of these fields into the link as it is assigned
  (``SharedState.control_link``), so every writer is covered and a command reaches the
  child the moment the planner decides it.
- child -> main: the throttles written, wheel speeds and gains, the safety layer's stop
  reason and count, the tick count and time (the systemd watchdog's heartbeat), a ring of
  ticks (time, lateness, CPU, throttles) and a ring of notes and faults, which the
  coroutine :func:`run` turns into ``state`` updates on the main loop at the control rate.

The child makes the same decisions as the coroutine and the thread (``control_task.tick_once``
and :class:`~mazebot.tasks.control_task.MotorControl`) on a view of those inputs. It is
started from the multiprocessing fork server (a single-threaded process started afresh,
so a fork never catches a lock held by one of the daemon's threads, and the numpy and
scipy the loop-closure worker preloads there are shared with it page for page); it opens
its own motor driver with the picklable ``kit_opener`` of the hardware.

Safety: a main process that stops updating leaves the command unchanged, and the safety
layer stops the wheels after ``command_ttl_ticks`` ticks (a direct throttle command after
``STALE_PERIODS`` periods); a main process that is gone closes the stop pipe, and the child
brakes and exits. A child that dies is seen at once through its sentinel: the motors are
braked from the main process, and the supervisor raises a ``control`` fault and starts a
new child. The child's own driver has a :class:`~mazebot.io.motors.TtlGuard` thread too.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import math
import multiprocessing
import os
import signal
import time
from collections.abc import Callable, Iterator
from multiprocessing.connection import Connection
from multiprocessing.shared_memory import SharedMemory
from typing import Any

import numpy as np

from mazebot.config import Config
from mazebot.errors import MazebotError
from mazebot.planner.safety import deskewed_points_robot, reframe_points, with_remembered
from mazebot.planner.wheel_control import DriveMode
from mazebot.state import SharedState
from mazebot.tasks.priority import raise_priority

log = logging.getLogger(__name__)

#: Most robot-frame points of one revolution kept for the collision guard (an S2 gives ~3200).
MAX_SCAN_POINTS = 8192
#: Most remembered blind-zone returns kept for the collision guard (the planner's memory keeps
#: at most 2000, plus one revolution's near returns).
MAX_BLIND_POINTS = 4096
#: Entries of the tick ring and of the notes ring (51 s and 64 notes at 20 Hz: the main
#: process reads them every period, so only a main process stalled that long loses any).
TICK_RING = 1024
NOTE_RING = 64
NOTE_TEXT_BYTES = 256
SAFETY_TEXT_BYTES = 256
#: Tries of a seqlock read before the previous copy is kept.
READ_TRIES = 50
#: How long a stopping child may take to brake and exit before it is killed, seconds.
CHILD_STOP_S = 1.0

_MODES = list(DriveMode)
_NOTE_KINDS = ("note", "raise_fault", "clear_faults")


class ControlProcessDied(MazebotError):
    """The control process ended while the daemon was not stopping (the supervisor restarts it)."""


class _Layout:
    """Offsets (in float64 slots) of every block; the same numbers in both processes."""

    def __init__(self) -> None:
        at = 0

        def block(size: int) -> int:
            nonlocal at
            start = at
            at += size
            return start

        self.command = block(1 + 5)  # seq; present, v, w, mode, time
        self.throttle = block(1 + 4)  # seq; present, left, right, time
        self.run = block(1 + 4)  # seq; moving, stopping, faults_raised, jog allowed
        self.jog = block(1 + 4)  # seq; present, left, right, time
        self.odometry = block(1 + 13)  # seq; ticks present, stamp, left, right; pose present, x, y, th;
        #                                 history present, then-time, x, y, th
        self.scan = block(1 + 7 + 2 * MAX_SCAN_POINTS)  # seq; present, end time, n, then present, x, y, th; points
        self.blind = block(1 + 1 + 2 * MAX_BLIND_POINTS)  # seq; n; odometry-frame points
        self.output = block(1 + 8 + SAFETY_TEXT_BYTES // 8)  # seq; ticks, tick time, l, r, speeds,
        #                                                       stops, text length; text
        self.ticks = block(1 + 5 * TICK_RING)  # count; (time, late ms, cpu s, left, right) each
        self.notes = block(1 + NOTE_RING * (4 + NOTE_TEXT_BYTES // 8))  # count; (kind, time, src len, text len; text)
        self.size = at


LAYOUT = _Layout()


class _Seqlock:
    """One block of float64 slots with its sequence counter in the first slot; one writer."""

    def __init__(self, slots: np.ndarray, start: int, size: int) -> None:
        self._seq = slots[start:start + 1]
        self._data = slots[start + 1:start + size]
        self._last: np.ndarray | None = None

    def write(self, values: np.ndarray | list[float], count: int | None = None) -> None:
        n = len(values) if count is None else count
        self._seq[0] += 1.0  # odd: a write is under way
        self._data[:n] = values[:n]
        self._seq[0] += 1.0

    def read(self, count: int | None = None) -> np.ndarray | None:
        """A consistent copy of the first ``count`` slots (all), or the previous one (None: never read)."""
        n = len(self._data) if count is None else count
        for _ in range(READ_TRIES):
            before = float(self._seq[0])
            if before % 2.0:
                continue
            copy = self._data[:n].copy()
            if float(self._seq[0]) == before:
                self._last = copy
                return copy
        return self._last

    def data(self) -> np.ndarray:
        return self._data


class ControlLink:
    """The shared memory between the daemon's main process and its control process.

    Example::

        link = ControlLink.create(config)       # main process; link.name goes to the child
        state.control_link = link               # SharedState mirrors its fields into it
        child = ControlLink.attach(link.name)   # control process
        child.read_command()                    # (v, w, mode, time_s) or None
    """

    #: the SharedState fields mirrored into the link as they are assigned
    MIRRORED = frozenset(
        {"motion_command", "throttle_command", "jog_command", "run_state", "stopping", "faults_raised", "wheel_ticks",
         "latest_scan", "blind_zone_points"}
    )

    def __init__(self, shm: SharedMemory, owner: bool, config: Config | None = None) -> None:
        self._shm: SharedMemory | None = shm
        self._owner = owner
        self.name = shm.name
        slots = np.ndarray((LAYOUT.size,), dtype=np.float64, buffer=shm.buf)
        self._slots = slots
        self._bytes = np.ndarray((LAYOUT.size * 8,), dtype=np.uint8, buffer=shm.buf)
        self.command = _Seqlock(slots, LAYOUT.command, 6)
        self.throttle = _Seqlock(slots, LAYOUT.throttle, 5)
        self.run = _Seqlock(slots, LAYOUT.run, 5)
        self.jog = _Seqlock(slots, LAYOUT.jog, 5)
        self.odometry = _Seqlock(slots, LAYOUT.odometry, 14)
        self.scan = _Seqlock(slots, LAYOUT.scan, 8 + 2 * MAX_SCAN_POINTS)
        self.blind = _Seqlock(slots, LAYOUT.blind, 2 + 2 * MAX_BLIND_POINTS)
        self.output = _Seqlock(slots, LAYOUT.output, 9 + SAFETY_TEXT_BYTES // 8)
        self._ticks_read = 0
        self._notes_read = 0
        self.ticks_lost = 0  # ring entries overwritten before the main process read them
        self._scan_time_s = math.nan  # end time of the scan written last (main side)
        self._too_many_points_logged = False
        if config is not None:
            lidar = config.lidar
            self._lidar_range_m = (lidar.min_range_m, lidar.max_range_m)
            self._mount_xy_m = lidar.mount_xy_m

    @classmethod
    def create(cls, config: Config) -> ControlLink:
        shm = SharedMemory(create=True, size=LAYOUT.size * 8)
        buf = shm.buf
        assert buf is not None  # a block just created is mapped
        buf[:] = bytes(LAYOUT.size * 8)
        return cls(shm, owner=True, config=config)

    @classmethod
    def attach(cls, name: str) -> ControlLink:
        return cls(SharedMemory(name=name), owner=False)

    def close(self) -> None:
        """Let go of the memory (the creator also removes it); idempotent."""
        shm, self._shm = self._shm, None
        if shm is None:
            return
        del self._slots, self._bytes, self.command, self.throttle, self.jog, self.run, self.odometry, self.scan
        del self.blind
        del self.output
        shm.close()
        if self._owner:
            with contextlib.suppress(FileNotFoundError):
                shm.unlink()

    # --- main -> child (main process) ----------------------------------------------------

    def mirror(self, state: SharedState, name: str) -> None:
        """Write the block of ``state``'s field ``name`` (called by ``SharedState.__setattr__``)."""
        if name == "motion_command":
            c = state.motion_command
            self.command.write([0.0] * 5 if c is None
                               else [1.0, c.v_mps, c.w_radps, float(_MODES.index(DriveMode(c.mode))), c.time_s])
        elif name == "throttle_command":
            t = state.throttle_command
            self.throttle.write([0.0] * 4 if t is None else [1.0, t[0], t[1], t[2]])
        elif name == "jog_command":
            j = state.jog_command
            self.jog.write([0.0] * 4 if j is None else [1.0, j[0], j[1], j[2]])
        elif name in ("run_state", "stopping", "faults_raised"):
            self.run.write([float(state.run_state.moving), float(state.stopping), float(state.faults_raised),
                            float(state.run_state.jog_allowed)])
        elif name == "wheel_ticks":
            self._write_odometry(state)
        elif name == "latest_scan":
            self._write_scan(state)
        elif name == "blind_zone_points":
            points = state.blind_zone_points
            points = np.zeros((0, 2)) if points is None else points[-MAX_BLIND_POINTS:]  # the newest
            self.blind.write(np.concatenate(([float(len(points))], points.reshape(-1))))

    def publish_all(self, state: SharedState) -> None:
        """Every block from ``state`` as it is now (a new child starts from these)."""
        for name in ("motion_command", "throttle_command", "jog_command", "run_state", "latest_scan", "wheel_ticks",
                     "blind_zone_points"):
            self.mirror(state, name)

    def _poses(self, state: SharedState, scan_time_s: float) -> list[float]:
        """[pose present, x, y, th, history present, x, y, th at ``scan_time_s``]: what
        ``planner.pilot.moved_since_scan`` reads of the odometry."""
        history, odo = state.odometry_history, state.odometry
        if history is None or odo is None or len(history) == 0 or math.isnan(scan_time_s):
            return [0.0] * 8 if odo is None else [1.0, odo.x_m, odo.y_m, odo.theta_rad, 0.0, 0.0, 0.0, 0.0]
        then = history.pose_at(scan_time_s)
        return [1.0, odo.x_m, odo.y_m, odo.theta_rad, 1.0, float(then[0]), float(then[1]), float(then[2])]

    def _write_odometry(self, state: SharedState) -> None:
        ticks = state.wheel_ticks
        head = [0.0, 0.0, 0.0, 0.0] if ticks is None else [1.0, ticks[0], float(ticks[1]), float(ticks[2])]
        poses = self._poses(state, self._scan_time_s)
        # [ticks..., pose present, x, y, th, history present, then-time, x, y, th]
        self.odometry.write(head + poses[:4] + [poses[4], self._scan_time_s] + poses[5:])

    def _write_scan(self, state: SharedState) -> None:
        scan = state.latest_scan
        data = self.scan.data()
        if scan is None:
            self._scan_time_s = math.nan
            self.scan.write([0.0] * 7)
            return
        points = deskewed_points_robot(scan.angle_rad, scan.range_m, scan.valid, scan.time_s, state.odometry_history,
                                       *self._lidar_range_m, mount_xy_m=self._mount_xy_m)
        if len(points) > MAX_SCAN_POINTS:
            if not self._too_many_points_logged:
                log.warning("a revolution of %d returns: the control process guards with the first %d",
                            len(points), MAX_SCAN_POINTS)
                self._too_many_points_logged = True
            points = points[:MAX_SCAN_POINTS]
        self._scan_time_s = scan.end_time_s
        poses = self._poses(state, scan.end_time_s)
        n = len(points)
        # one seqlock write over header and points: the child never mixes two revolutions
        self.scan._seq[0] += 1.0
        data[:7] = [1.0, scan.end_time_s, float(n), poses[4], *poses[5:]]
        data[7:7 + 2 * n] = points.reshape(-1)
        self.scan._seq[0] += 1.0

    # --- main <- child (main process) ----------------------------------------------------

    def read_output(self) -> dict[str, Any] | None:
        raw = self.output.read()
        if raw is None:
            return None
        n = int(raw[7])
        text = raw[8:].view(np.uint8)[:n].tobytes().decode("utf-8", "replace")
        return {
            "ticks": int(raw[0]),
            "tick_time_s": float(raw[1]),
            "throttles": (float(raw[2]), float(raw[3])),
            "wheel_speeds_mps": (float(raw[4]), float(raw[5])),
            "safety_stops": int(raw[6]),
            "safety_stop": text,
        }

    def new_ticks(self) -> Iterator[tuple[float, float, float, float, float]]:
        """The child's ticks since the last call: (time s, lateness ms, CPU s, left, right)."""
        base = LAYOUT.ticks
        count = int(self._slots[base])
        if count - self._ticks_read > TICK_RING:
            self.ticks_lost += count - self._ticks_read - TICK_RING
            self._ticks_read = count - TICK_RING
        for i in range(self._ticks_read, count):
            at = base + 1 + 5 * (i % TICK_RING)
            yield tuple(float(v) for v in self._slots[at:at + 5])  # type: ignore[misc]
        self._ticks_read = count

    def new_notes(self) -> Iterator[tuple[str, float, str, str]]:
        """The child's notes and faults since the last call: (kind, time s, source, message)."""
        base, width = LAYOUT.notes, 4 + NOTE_TEXT_BYTES // 8
        count = int(self._slots[base])
        self._notes_read = max(self._notes_read, count - NOTE_RING)
        for i in range(self._notes_read, count):
            at = base + 1 + width * (i % NOTE_RING)
            kind, time_s, n_source, n_text = self._slots[at:at + 4]
            raw = self._bytes[(at + 4) * 8:(at + 4) * 8 + int(n_text)].tobytes().decode("utf-8", "replace")
            yield _NOTE_KINDS[int(kind)], float(time_s), raw[:int(n_source)], raw[int(n_source):]
        self._notes_read = count

    # --- child side ----------------------------------------------------------------------

    def write_output(self, ticks: int, tick_time_s: float, view: ChildView, control: Any) -> None:
        stop = view.safety_stop.encode("utf-8")[:SAFETY_TEXT_BYTES]
        data = self.output.data()
        self.output._seq[0] += 1.0
        data[:7] = [float(ticks), tick_time_s, *view.throttles, *view.wheel_speeds_mps, float(view.safety_stops)]
        data[7] = float(len(stop))
        data[8:].view(np.uint8)[:len(stop)] = np.frombuffer(stop, dtype=np.uint8)
        self.output._seq[0] += 1.0

    def push_tick(self, time_s: float, late_ms: float, cpu_s: float, left: float, right: float) -> None:
        base = LAYOUT.ticks
        count = int(self._slots[base])
        at = base + 1 + 5 * (count % TICK_RING)
        self._slots[at:at + 5] = (time_s, late_ms, cpu_s, left, right)
        self._slots[base] = count + 1  # the entry first, then the count that publishes it

    def push_note(self, kind: str, time_s: float, source: str, message: str) -> None:
        base, width = LAYOUT.notes, 4 + NOTE_TEXT_BYTES // 8
        count = int(self._slots[base])
        at = base + 1 + width * (count % NOTE_RING)
        src = source.encode("utf-8")[:32]
        text = (src + message.encode("utf-8"))[:NOTE_TEXT_BYTES]
        self._slots[at:at + 4] = (float(_NOTE_KINDS.index(kind)), time_s, float(len(src)), float(len(text)))
        self._bytes[(at + 4) * 8:(at + 4) * 8 + len(text)] = np.frombuffer(text, dtype=np.uint8)
        self._slots[base] = count + 1


class _RunState:
    """What ``MotorControl.tick`` reads of the run state."""

    def __init__(self) -> None:
        self.moving = False
        self.jog_allowed = False


class _Fault:
    def __init__(self, source: str) -> None:
        self.source = source


class _MotionCommand:
    __slots__ = ("mode", "time_s", "v_mps", "w_radps")

    def __init__(self, v_mps: float, w_radps: float, mode: str, time_s: float) -> None:
        self.v_mps, self.w_radps, self.mode, self.time_s = v_mps, w_radps, mode, time_s


class _ScanStamp:
    __slots__ = ("end_time_s",)

    def __init__(self, end_time_s: float) -> None:
        self.end_time_s = end_time_s


class _TickRing:
    """``control_lateness_ms`` of the child: the lateness waits for the tick's CPU and throttles."""

    def __init__(self) -> None:
        self.pending_ms = 0.0

    def append(self, late_ms: float) -> None:
        self.pending_ms = late_ms


class _TickMeter:
    """The ``control tick`` meter of the child: its thread CPU per tick, into the tick ring."""

    def __init__(self, link: ControlLink, view: ChildView) -> None:
        self._link, self._view = link, view

    @contextlib.contextmanager
    def measure(self) -> Iterator[None]:
        start_s = time.thread_time()
        try:
            yield
        finally:
            view = self._view
            self._link.push_tick(view.tick_time_s, view.control_lateness_ms.pending_ms,
                                 time.thread_time() - start_s, *view.throttles)


class ChildView:
    """The fields of :class:`SharedState` that one control tick reads and writes, in the child.

    :meth:`refresh` reads the main process's blocks; what the tick writes stays here and
    goes back through :meth:`ControlLink.write_output`; notes and faults go into the link's
    ring (the same calls as on ``SharedState``).
    """

    def __init__(self, link: ControlLink) -> None:
        self._link = link
        self.run_state = _RunState()
        self.stopping = False
        self.faults_raised = 0
        self.motion_command: _MotionCommand | None = None
        self.throttle_command: tuple[float, float, float] | None = None
        self.jog_command: tuple[float, float, float] | None = None
        self.wheel_ticks: tuple[float, int, int] | None = None
        self.wheel_speeds_mps = (0.0, 0.0)
        self.throttles = (0.0, 0.0)
        self.safety_stop = ""
        self.safety_stops = 0
        self.faults: list[_Fault] = []  # the faults this process raised and has not cleared
        self.control_lateness_ms = _TickRing()
        self.tick_time_s = 0.0
        # the scan: robot-frame points at its end, its end time, the odometry pose then (or None)
        self.scan_points: np.ndarray | None = None
        self.scan_time_s: float | None = None
        self.pose_then: tuple[float, float, float] | None = None
        self.pose_now: tuple[float, float, float] | None = None
        #: the planner's remembered blind-zone returns, odometry frame (N, 2)
        self.blind_points = np.zeros((0, 2))

    def refresh(self) -> None:
        link = self._link
        run = link.run.read()
        if run is not None:
            self.run_state.moving, self.stopping, self.faults_raised = bool(run[0]), bool(run[1]), int(run[2])
            self.run_state.jog_allowed = bool(run[3])
        c = link.command.read()
        if c is not None:
            self.motion_command = (_MotionCommand(float(c[1]), float(c[2]), _MODES[int(c[3])].value, float(c[4]))
                                   if c[0] else None)
        t = link.throttle.read()
        if t is not None:
            self.throttle_command = (float(t[1]), float(t[2]), float(t[3])) if t[0] else None
        j = link.jog.read()
        if j is not None:
            self.jog_command = (float(j[1]), float(j[2]), float(j[3])) if j[0] else None
        o = link.odometry.read()
        odo_then: tuple[float, tuple[float, float, float]] | None = None
        if o is not None:
            self.wheel_ticks = (float(o[1]), int(o[2]), int(o[3])) if o[0] else None
            self.pose_now = (float(o[5]), float(o[6]), float(o[7])) if o[4] else None
            if o[8]:
                odo_then = (float(o[9]), (float(o[10]), float(o[11]), float(o[12])))
        head = link.scan.read(7)
        if head is None or not head[0]:
            self.scan_points, self.scan_time_s, self.pose_then = None, None, None
        elif head[1] != self.scan_time_s or self.scan_points is None:
            n = int(head[2])
            whole = link.scan.read(7 + 2 * n)
            if whole is not None and whole[1] == head[1]:
                self.scan_time_s = float(whole[1])
                self.scan_points = whole[7:7 + 2 * n].reshape(-1, 2)
                self.pose_then = (float(whole[4]), float(whole[5]), float(whole[6])) if whole[3] else None
        if odo_then is not None and odo_then[0] == self.scan_time_s:
            self.pose_then = odo_then[1]  # computed with the odometry history of now, as the thread does
        count = link.blind.read(1)
        if count is not None:
            n = int(count[0])
            whole = link.blind.read(1 + 2 * n)
            if whole is not None and int(whole[0]) == n:
                self.blind_points = whole[1:1 + 2 * n].reshape(-1, 2)

    @property
    def latest_scan(self) -> _ScanStamp | None:
        """What an idle tick reads of the latest scan: its end time (the lidar's age counts on)."""
        return None if self.scan_time_s is None else _ScanStamp(self.scan_time_s)

    # the SharedState calls tick_once and _write make (through ``post``)
    def note(self, source: str, message: str, time_s: float) -> None:
        self._link.push_note("note", time_s, source, message)

    def raise_fault(self, source: str, message: str, time_s: float) -> None:
        self.faults = [f for f in self.faults if f.source != source] + [_Fault(source)]
        self._link.push_note("raise_fault", time_s, source, message)

    def clear_faults(self, source: str) -> None:
        self.faults = [f for f in self.faults if f.source != source]
        self._link.push_note("clear_faults", 0.0, source, "")


def _child_control(config: Config, view: ChildView) -> Any:
    """A :class:`MotorControl` whose scan comes from the view (prepared by the main process)."""
    from mazebot.tasks.control_task import MotorControl

    class ProcessMotorControl(MotorControl):
        def scan_points(self, state: Any) -> tuple[np.ndarray | None, float | None]:
            if view.scan_points is None:
                return None, None
            if view.pose_then is None or view.pose_now is None:  # as moved_since_scan without odometry
                return view.scan_points, view.scan_time_s
            points = reframe_points(view.scan_points, view.pose_then, view.pose_now)
            return with_remembered(points, view.blind_points, view.pose_now), view.scan_time_s

    return ProcessMotorControl.from_config(config)


def child_main(link_name: str, config: Config, kit_opener: Callable[[], Any], stop_rx: Connection,
               log_level: str) -> None:
    """The control process: tick until told to stop, or until the main process is gone; brake on every way out."""
    # The objects this process inherited from the fork server (numpy, scipy, the SLAM modules
    # the loop-closure worker needs) stay out of its garbage collector: a collection writes to
    # every object it examines, and each page it writes to is copied out of the fork server's
    # and counts whole in this process's memory (gc.freeze: Python's gc module documentation)
    gc.freeze()
    stopping = []
    # first of all, before the imports below take their time: a Ctrl-C to the whole process group
    # (a terminal's) while this process starts must stop it quietly, not as a KeyboardInterrupt
    for sig in (signal.SIGINT, signal.SIGTERM):  # brake and leave, unless whoever started us ignores them
        if signal.getsignal(sig) is not signal.SIG_IGN:
            signal.signal(sig, lambda *_: stopping.append(True))
    from mazebot.clock import RealClock
    from mazebot.io.motors import DifferentialMotors, TtlGuard
    from mazebot.logs import setup_logging
    from mazebot.tasks.control_task import call_now, tick_once

    setup_logging(log_level)
    # before the driver's threads start, so they inherit it
    got = raise_priority(config.daemon.control_rt_priority, config.daemon.control_nice)
    log.info("control process %d scheduled with %s", os.getpid(), got)
    try:
        link = ControlLink.attach(link_name)
    except FileNotFoundError:  # the daemon stopped (and removed the link) before we got here: no motor was touched
        log.info("control process %d: the daemon stopped before it started", os.getpid())
        stop_rx.close()
        return
    motors = DifferentialMotors.from_config(config.motors, kit_opener(), RealClock(), ttl_guarded=True)
    guard = TtlGuard(motors)  # this process's own loop hangs: its driver still brakes
    guard.start()
    view = ChildView(link)
    control = _child_control(config, view)
    meter = _TickMeter(link, view)
    ticks = 0
    try:
        next_tick_s = time.monotonic()
        while not stopping:
            view.refresh()
            now_s = time.monotonic()
            view.tick_time_s = now_s
            next_tick_s = tick_once(motors, view, control, meter, now_s, next_tick_s, call_now)  # type: ignore[arg-type]
            ticks += 1
            link.write_output(ticks, now_s, view, control)
            # sleeping on the stop pipe: a message or its end (the main process is gone) wakes us at once
            if stop_rx.poll(max(0.0, next_tick_s - time.monotonic())):
                break
    except BaseException as exc:
        with contextlib.suppress(Exception):
            view.note("control", f"the control process crashed ({type(exc).__name__}: {exc})", time.monotonic())
        raise
    finally:
        try:
            motors.close()  # brakes
        finally:
            guard.close()
            stop_rx.close()
            link.close()


# --- the main process ------------------------------------------------------------------------


def _take_output(link: ControlLink, state: SharedState, heartbeat: Any, meter: Any) -> None:
    """What the child wrote since the last call, into ``state`` (on the main loop: one writer each)."""
    out = link.read_output()
    if out is not None and out["ticks"] > 0:
        state.throttles = out["throttles"]
        state.wheel_speeds_mps = out["wheel_speeds_mps"]
        state.safety_stop = out["safety_stop"]
        state.safety_stops = out["safety_stops"]
        if hasattr(heartbeat, "last_tick_s"):
            heartbeat.last_tick_s = max(heartbeat.last_tick_s, out["tick_time_s"])
    for time_s, late_ms, cpu_s, left, right in link.new_ticks():
        state.throttle_history.append((time_s, left, right))  # the child's clock is this process's monotonic one
        state.control_lateness_ms.append(late_ms)
        meter.add(cpu_s)
    for kind, time_s, source, message in link.new_notes():
        if kind == "note":
            state.note(source, message, time_s)
        elif kind == "raise_fault":
            state.raise_fault(source, message, time_s)
        else:
            state.clear_faults(source)


def start_child(link: ControlLink, config: Config, kit_opener: Callable[[], Any],
                log_level: str) -> tuple[multiprocessing.process.BaseProcess, Connection]:
    """Start the control process from the fork server; returns it and the stop pipe's sending end."""
    from mazebot.slam.loop_worker import FORKSERVER_PRELOAD

    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(list(FORKSERVER_PRELOAD))  # in case this child starts the server
    stop_rx, stop_tx = ctx.Pipe(duplex=False)
    child = ctx.Process(target=child_main, name="mazebot-control", daemon=True,
                        args=(link.name, config, kit_opener, stop_rx, log_level))
    child.start()
    stop_rx.close()  # only the child holds the receiving end: our end closing is its signal
    return child, stop_tx


async def run(link: ControlLink, motors: Any, state: SharedState, heartbeat: Any, config: Config,
              kit_opener: Callable[[], Any]) -> None:
    """Run the control loop in a child process for as long as this task lives.

    Each period it brings the child's outputs, ticks, notes and faults into ``state``. The
    child's end is seen at once (its sentinel on the event loop): the motors are braked
    from here, then (within a period) :class:`ControlProcessDied` goes to the supervisor, which raises the
    ``control`` fault and starts this task again (a new child). Cancelled (the daemon
    stops), it tells the child to stop and waits up to ``CHILD_STOP_S`` for it to brake
    and exit, then kills it and brakes from here.
    """
    loop = asyncio.get_running_loop()
    meter = state.cpu.part("control tick")
    link.publish_all(state)
    child, stop_tx = await asyncio.to_thread(start_child, link, config, kit_opener, config.daemon.log_level)
    ended: asyncio.Future[None] = loop.create_future()

    def on_end() -> None:
        loop.remove_reader(child.sentinel)
        with contextlib.suppress(Exception):
            motors.stop()  # before anything else: the child may have died mid-drive
        if not ended.done():
            ended.set_result(None)

    loop.add_reader(child.sentinel, on_end)
    log.info("control loop in process %d", child.pid)
    period_s = config.daemon.control_period_s
    try:
        while not ended.done():
            _take_output(link, state, heartbeat, meter)
            # in the odometry's wake-ups (each reading, 40 a second by default), not on a timer of
            # this task's own: 20 wake-ups of the loop a second fewer, and the odometry reads the
            # throttles as fresh as before (taken one reading earlier, at most a control period).
            # No wait on ``ended``: the end brakes the motors in ``on_end`` at once, and this loop
            # sees it within a period
            await state.odometry_beat.wait(1, timeout_s=period_s)
        _take_output(link, state, heartbeat, meter)
        child.join(CHILD_STOP_S)
        raise ControlProcessDied(f"the control process {child.pid} ended (exit code {child.exitcode}); "
                                 "motors braked")
    finally:
        if not ended.done():
            with contextlib.suppress(OSError, ValueError):
                stop_tx.send_bytes(b"stop")
            with contextlib.suppress(TimeoutError, asyncio.CancelledError):
                await asyncio.wait_for(asyncio.shield(ended), CHILD_STOP_S)
            loop.remove_reader(child.sentinel)
            if child.exitcode is None:
                log.error("the control process did not stop within %.1f s; killing it", CHILD_STOP_S)
                child.kill()
            with contextlib.suppress(Exception):
                motors.stop()
        await asyncio.to_thread(child.join, CHILD_STOP_S)
        with contextlib.suppress(Exception):
            _take_output(link, state, heartbeat, meter)
        stop_tx.close()
        if child.exitcode is not None:
            child.close()

