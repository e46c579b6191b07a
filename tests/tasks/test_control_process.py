"""The motor control loop in a process of its own (``[daemon] control_process``, the real clock).

Real processes and real shared memory: the child makes the decisions ``MotorControl.tick``
makes on the same inputs; a main process that hangs or dies leaves the wheels braked
within the command's time-to-live; a child that dies is a ``control`` fault, the motors
are braked from the main process and a new child starts.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import multiprocessing
import os
import signal
import time
from collections.abc import Iterator
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mazebot.clock import RealClock
from mazebot.config import Config
from mazebot.io.scan import Scan
from mazebot.sdnotify import ControlHeartbeat
from mazebot.sim.remote_devices import PipeKitOpener
from mazebot.sim.world_process import decode_throttle
from mazebot.slam.ekf import OdometryHistory
from mazebot.slam.odometry import OdometryPose
from mazebot.state import MotionRequest, RunState, SharedState
from mazebot.tasks import control_process
from mazebot.tasks.control_process import ChildView, ControlLink
from mazebot.tasks.control_task import MotorControl
from mazebot.tasks.supervisor import Supervisor
from tests.odometry_beats import tick_odometry_beats


def _wall_scan(distance_m: float, time_s: float) -> Scan:
    """A revolution with a straight wall ``distance_m`` ahead (and nothing elsewhere)."""
    angle = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    ahead = np.abs(angle) < 0.6
    rng = np.where(ahead, distance_m / np.cos(np.where(ahead, angle, 0.0)), 0.0)
    return Scan(angle, rng, np.full(360, 40, np.uint8), np.linspace(time_s - 0.18, time_s, 360), rng > 0)


class Recorder:
    """Main-process motors: remembers each brake."""

    def __init__(self) -> None:
        self.stops: list[float] = []

    def stop(self) -> None:
        self.stops.append(time.monotonic())

    def set(self, left: float, right: float) -> None:  # the main process never drives in this mode
        raise AssertionError("the main process drove the motors")


@contextlib.contextmanager
def _linked_controls(config: Config) -> Iterator[tuple[SharedState, ChildView, MotorControl, Any]]:
    """An exploring robot's state linked through real shared memory to a child's view of it:
    (state, view, the in-process MotorControl, the child's control), to be stepped on the same
    inputs; the shared memory closed afterwards."""
    link = ControlLink.create(config)
    child_link = ControlLink.attach(link.name)
    state = SharedState(run_state=RunState.EXPLORING, started_at_s=0.0, auto_resume=True)
    try:
        state.odometry_history = OdometryHistory(3.0)
        state.control_link = link
        link.publish_all(state)  # what was set before the link (the child's start does the same)
        view = ChildView(child_link)
        yield state, view, MotorControl.from_config(config), control_process._child_control(config, view)
    finally:
        state.control_link = None
        child_link.close()
        link.close()


def test_the_child_decides_as_motor_control_does_on_the_same_inputs() -> None:
    """Step by step through real shared memory: driving, a wall coming closer (the collision
    guard), odometry moving since the scan, a fault, a stale command, a stop."""
    config = Config()
    with _linked_controls(config) as (state, view, reference, child):
        period_s = config.daemon.control_period_s
        outputs, stops = [], set()
        x_m, left_ticks, right_ticks = 0.0, 0, 0
        for k in range(120):
            now_s = 100.0 + k * period_s
            if k % 2 == 0 and k < 80:  # the planner: 10 Hz, fresh commands (none after tick 80: they go stale)
                state.motion_command = MotionRequest(0.2, 0.1 * math.sin(k / 10), "drive", now_s)
            if k == 50:
                state.raise_fault("lidar", "a test fault", now_s)
            if k == 55:
                state.clear_faults("lidar")
            if k == 110:
                state.stopping = True
            x_m += 0.01
            left_ticks += 9 + k % 3
            right_ticks += 10
            state.odometry_history.append(now_s, x_m, 0.0, 0.0)
            state.odometry = OdometryPose(x_m, 0.0, 0.0)
            state.wheel_ticks = (now_s, left_ticks, right_ticks)
            # a revolution: a wall ahead coming closer, then gone; published once the odometry covers
            # it (each return is placed with the pose of its time: the two loops de-skew at different
            # moments, the same once the history holds the revolution's end)
            if k % 4 == 0:
                state.latest_scan = _wall_scan(0.5 - 0.008 * k if k < 60 else 2.0, now_s - 0.01)
            expected = reference.tick(state, now_s)
            state.throttles = expected
            view.refresh()
            got = child.tick(view, now_s)
            view.throttles = got
            assert got == expected, f"tick {k}"
            assert view.wheel_speeds_mps == state.wheel_speeds_mps
            assert view.safety_stop == state.safety_stop and view.safety_stops == state.safety_stops
            outputs.append(got)
            stops.add(state.safety_stop.split(":")[0])
        # every branch was taken: driving, the guard's emergency stop, the stale command
        assert any(abs(left) > 0.05 for left, _ in outputs)
        assert outputs[-1] == (0.0, 0.0)
        assert "stale command" in stops and stops - {"", "stale command"}, stops  # and the guard's


def test_the_child_jogs_as_motor_control_does_and_never_while_stopping_or_in_a_fault() -> None:
    """The setup page's hold-to-run jog through real shared memory: applied while idle and
    fresh, dropped when stale, in a fault, during a run, and once the daemon stops."""
    config = Config()
    link = ControlLink.create(config)
    child_link = ControlLink.attach(link.name)
    try:
        state = SharedState(run_state=RunState.IDLE, started_at_s=0.0)
        state.control_link = link
        link.publish_all(state)
        view = ChildView(child_link)
        reference, child = MotorControl.from_config(config), control_process._child_control(config, view)
        period_s = config.daemon.control_period_s
        outputs = []
        for k in range(100):
            now_s = 50.0 + k * period_s
            if k < 20 or 40 <= k < 90:  # held: a fresh request every tick
                state.jog_command = (0.3, -0.3, now_s)
            if k == 50:
                state.raise_fault("lidar", "a test fault", now_s)
            if k == 60:
                state.clear_faults("lidar")
                state.run_state = RunState.IDLE
            if k == 70:
                state.run_state = RunState.EXPLORING
            if k == 75:
                state.run_state = RunState.STOPPED
            if k == 85:
                state.stopping = True
            expected = reference.tick(state, now_s)
            state.throttles = expected
            view.refresh()
            got = child.tick(view, now_s)
            view.throttles = got
            assert got == expected, f"tick {k}"
            outputs.append(got)
        jogged = [k for k, (left, right) in enumerate(outputs) if (left, right) == (0.3, -0.3)]
        assert 0 in jogged and 45 in jogged and 80 in jogged  # held while idle, and again after the stop
        ttl_ticks = math.ceil(config.motors.command_ttl_s / period_s)
        assert all(outputs[k] == (0.0, 0.0) for k in range(20 + ttl_ticks + 1, 40))  # released: stale
        assert all(outputs[k] == (0.0, 0.0) for k in range(50, 60))  # a fault
        assert all(outputs[k] == (0.0, 0.0) for k in range(70, 75))  # a run
        assert all(outputs[k] == (0.0, 0.0) for k in range(86, 100))  # the daemon stopping
    finally:
        state.control_link = None
        child_link.close()
        link.close()


def _read_throttles(motor_rx: Connection, until_s: float) -> list[tuple[float, int, float | None]]:
    out = []
    while time.monotonic() < until_s:
        if not motor_rx.poll(0.05):
            continue
        try:
            channel, throttle = decode_throttle(motor_rx.recv_bytes())
        except EOFError:
            break
        out.append((time.monotonic(), channel, throttle))
    return out


def test_the_real_child_writes_what_motor_control_decides() -> None:
    """A child process on its own clock: its ticks (time, throttles) replayed through
    ``MotorControl.tick`` on the same inputs give the same throttles, and they reach the motors."""
    config = Config()
    link = ControlLink.create(config)
    motor_rx, motor_tx = multiprocessing.Pipe(duplex=False)
    state = SharedState(run_state=RunState.EXPLORING, started_at_s=0.0)
    state.control_link = link
    command = MotionRequest(0.0, 0.8, "turn", time.monotonic())  # turning in place: the guard allows it
    state.motion_command = command
    link.publish_all(state)
    child, stop_tx = control_process.start_child(link, config, PipeKitOpener(motor_tx), "warning")
    try:
        writes, ticks = [], []
        deadline = time.monotonic() + 30.0  # the fork server's first start imports numpy: slow on a busy machine
        while len(ticks) < 20 and time.monotonic() < deadline:
            writes += _read_throttles(motor_rx, time.monotonic() + 0.1)
            ticks += link.new_ticks()
    finally:
        stop_tx.send_bytes(b"stop")
        child.join(5.0)
        state.control_link = None
        link.close()
    assert child.exitcode == 0
    assert len(ticks) >= 12
    reference = SharedState(run_state=RunState.EXPLORING, started_at_s=0.0)
    reference.motion_command = command
    control = MotorControl.from_config(config)
    for time_s, _late_ms, _cpu_s, left, right in ticks:
        expected = control.tick(reference, time_s)
        reference.throttles = expected
        assert (left, right) == expected
    assert any(left != 0.0 for _, _, _, left, _ in ticks)  # it turned, then the command went stale
    assert ticks[-1][3:] == (0.0, 0.0)
    driven = [t for _, _, t in writes if t]
    assert driven and writes[-1][2] == 0.0  # the motors got them; the last write is a brake


def _main_side(motor_tx: Connection, report_tx: Connection) -> None:
    """A daemon's main process in small: the link, a planner that keeps the robot turning, the child."""

    async def main() -> None:
        from mazebot.io.motors import DifferentialMotors
        from mazebot.sim.remote_devices import PipeMotorKit

        config = Config()
        link = ControlLink.create(config)
        state = SharedState(run_state=RunState.EXPLORING, started_at_s=0.0)
        state.control_link = link
        motors = DifferentialMotors.from_config(config.motors, PipeMotorKit(motor_tx), RealClock())
        task = asyncio.create_task(control_process.run(link, motors, state, ControlHeartbeat(RealClock()), config,
                                                       PipeKitOpener(motor_tx)))
        sent = False
        while True:
            state.motion_command = MotionRequest(0.0, 0.8, "turn", time.monotonic())
            children = [p for p in multiprocessing.active_children() if p.name == "mazebot-control"]
            if children and not sent:
                report_tx.send(children[0].pid)
                sent = True
            await asyncio.sleep(0.02)
            assert not task.done()

    asyncio.run(main())


@pytest.mark.parametrize("how", ["killed", "hung"])
def test_a_main_process_gone_or_hung_leaves_the_wheels_braked_within_the_ttl(
        how: str, monkeypatch: pytest.MonkeyPatch) -> None:
    # a spawned child imports this module by name: with pytest's importlib mode the repository's
    # root is not on sys.path unless put there (spawn hands the parent's sys.path to the child)
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[2]))
    child_pid = None
    ctx = multiprocessing.get_context("spawn")
    motor_rx, motor_tx = ctx.Pipe(duplex=False)
    report_rx, report_tx = ctx.Pipe(duplex=False)
    main = ctx.Process(target=_main_side, args=(motor_tx, report_tx))  # not daemonic: it has a child
    main.start()
    motor_tx.close()
    report_tx.close()
    try:
        assert report_rx.poll(60.0), "the main side did not start its control process"
        child_pid = report_rx.recv()
        deadline = time.monotonic() + 30.0  # the child's start imports numpy: slow on a busy machine
        while time.monotonic() < deadline and not any(t for _, _, t in _read_throttles(motor_rx,
                                                                                       time.monotonic() + 0.2)):
            pass
        assert time.monotonic() < deadline, "the wheels were not driven"
        os.kill(main.pid, signal.SIGKILL if how == "killed" else signal.SIGSTOP)
        gone_s = time.monotonic()
        after = _read_throttles(motor_rx, gone_s + 2.0)
        ttl_s = Config().control.command_ttl_ticks * Config().daemon.control_period_s
        last = {channel: throttle for _, channel, throttle in after}
        assert set(last) == {1, 2} and all(throttle == 0.0 for throttle in last.values())
        # braked within the command's time-to-live (plus a period and the machine's slack): the
        # last write that drove came no later
        driving = [t_s for t_s, _, throttle in after if throttle]
        braked_s = (max(driving) if driving else gone_s) - gone_s
        assert braked_s <= ttl_s + 0.3, braked_s
        if how == "killed":  # its parent gone, the child brakes and exits
            deadline = time.monotonic() + 3.0
            while time.monotonic() < deadline and _alive(child_pid):
                time.sleep(0.05)
            assert not _alive(child_pid)
    finally:
        if main.exitcode is None:
            os.kill(main.pid, signal.SIGKILL)
            os.kill(main.pid, signal.SIGCONT)
        main.join(5.0)
        deadline = time.monotonic() + 3.0
        while child_pid is not None and time.monotonic() < deadline and _alive(child_pid):
            time.sleep(0.05)
        assert child_pid is None or not _alive(child_pid)  # a hung parent killed: the child follows


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rpartition(")")[2].split()[0] != "Z"
    except OSError:
        return False


async def test_a_dead_child_is_a_control_fault_braked_and_restarted() -> None:
    config = Config()
    link = ControlLink.create(config)
    motor_rx, motor_tx = multiprocessing.Pipe(duplex=False)
    state = SharedState(run_state=RunState.IDLE)
    state.control_link = link
    motors = Recorder()
    supervisor = Supervisor(state, motors, RealClock(), exit_on_fault=False, restart_min_s=0.2)
    heartbeat = ControlHeartbeat(RealClock())
    supervisor.start("control", lambda: control_process.run(link, motors, state, heartbeat, config,
                                                            PipeKitOpener(motor_tx)), restart=True)

    def children() -> list[multiprocessing.process.BaseProcess]:
        return [p for p in multiprocessing.active_children() if p.name == "mazebot-control"]

    async def until(condition, timeout_s: float = 10.0) -> None:
        deadline = time.monotonic() + timeout_s
        while not condition():
            assert time.monotonic() < deadline, "condition not met in time"
            await asyncio.sleep(0.01)

    try:
        # the fork server's first start imports numpy: slow on a busy machine
        await until(lambda: len(children()) == 1 and len(state.control_lateness_ms) >= 3, 60.0)
        first = children()[0].pid
        assert heartbeat.last_tick_s > time.monotonic() - 1.0  # the systemd watchdog sees its ticks
        os.kill(first, signal.SIGKILL)
        killed_s = time.monotonic()
        await until(lambda: any(f.source == "control" for f in state.faults), 2.0)
        assert any(s >= killed_s for s in motors.stops)  # braked from the main process
        assert min(s for s in motors.stops if s >= killed_s) - killed_s < 0.5
        fault = next(f for f in state.faults if f.source == "control")
        assert "control process" in fault.message and "exit code -9" in fault.message
        await until(lambda: [p.pid for p in children()] not in ([], [first]), 30.0)  # a new child
        ticks = len(state.control_lateness_ms)
        await until(lambda: len(state.control_lateness_ms) > ticks + 3, 30.0)  # and it ticks
    finally:
        supervisor.request_stop("test over")
        await supervisor.wait()
        state.control_link = None
        link.close()
    assert children() == []  # stopped means stopped: the child braked and exited
    writes = []
    while motor_rx.poll(0):
        writes.append(decode_throttle(motor_rx.recv_bytes()))
    assert writes and writes[-1][1] == 0.0


def test_a_child_that_starts_after_the_daemon_stopped_leaves_quietly_without_touching_a_motor() -> None:
    """A Ctrl-C right after start: the main process removed the link before the child attached to it."""
    link = ControlLink.create(Config())
    name = link.name
    link.close()  # the owner unlinks it
    opened: list[bool] = []

    def opener() -> None:
        opened.append(True)
        raise AssertionError("no motor driver may be opened")

    stop_rx, stop_tx = multiprocessing.Pipe(duplex=False)
    saved = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        # in this process: no real-time priority or nice, which everything the tests start later would inherit
        fair = Config.model_validate({"daemon": {"control_rt_priority": 0, "control_nice": 0}})
        control_process.child_main(name, fair, opener, stop_rx, "warning")  # returns, raises nothing
    finally:
        for sig, handler in saved.items():
            signal.signal(sig, handler)
        stop_tx.close()
    assert opened == []
    assert stop_rx.closed


def test_the_control_modules_do_not_import_the_planner_or_scipy() -> None:
    """What the child imports of its own: the control loop's modules, not the planner's (scipy, the grid)."""
    import subprocess
    import sys

    heavy = "('scipy', 'mazebot.planner.dwa', 'mazebot.planner.pilot', 'mazebot.slam.grid')"
    code = ("import sys, mazebot.tasks.control_process, mazebot.tasks.control_task\n"
            f"print(sorted(m for m in sys.modules if m.startswith({heavy})))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@pytest.mark.slow
def test_the_child_starts_from_a_fork_server_that_holds_its_modules_and_stays_small() -> None:
    """The child forks from a server that imported its modules, and keeps what it inherited shared.

    A forked child's memory is its own only where it writes: its own imports (~7 MB before the
    server preloaded them) and the pages a garbage collection touches (~13 MB of the server's
    objects, before the child froze them out of the collector). Measured in
    ``/proc/PID/smaps_rollup`` after the child's first 40 ticks: ~4 MB when this test starts
    the server, 12.5 MB once in a whole test session whose earlier tests had started it (a
    server is started once per process); the bound is what an unfrozen collection alone
    would exceed.
    """
    from mazebot.slam.loop_worker import FORKSERVER_PRELOAD

    assert "mazebot.tasks.control_process" in FORKSERVER_PRELOAD
    config = Config()
    link = ControlLink.create(config)
    motor_rx, motor_tx = multiprocessing.Pipe(duplex=False)
    state = SharedState(run_state=RunState.IDLE, started_at_s=0.0)
    state.control_link = link
    link.publish_all(state)
    child, stop_tx = control_process.start_child(link, config, PipeKitOpener(motor_tx), "warning")
    try:
        ticks: list[tuple[float, ...]] = []
        deadline = time.monotonic() + 30.0  # the fork server's first start imports numpy and scipy
        while len(ticks) < 40 and time.monotonic() < deadline:
            _read_throttles(motor_rx, time.monotonic() + 0.1)
            ticks += link.new_ticks()
        assert len(ticks) >= 40
        rollup = Path(f"/proc/{child.pid}/smaps_rollup").read_text().splitlines()
        kb = {line.split()[0]: int(line.split()[1]) for line in rollup if line.endswith("kB")}
        private_mb = (kb["Private_Clean:"] + kb["Private_Dirty:"]) / 1024
    finally:
        stop_tx.send_bytes(b"stop")
        child.join(5.0)
        state.control_link = None
        link.close()
    assert child.exitcode == 0
    assert private_mb < 16.0, f"the control process holds {private_mb:.1f} MB of its own"


def test_the_child_and_motor_control_stop_for_a_return_only_the_planner_remembers() -> None:
    """A leg 0.12 m ahead, inside the lidar's 0.15 m minimum range: the revolution shows
    nothing near, the planner's blind-zone memory (``state.blind_zone_points``, odometry
    frame) has it. Both control loops stop a drive towards it, and neither stops one beside it."""
    config = Config()
    with _linked_controls(config) as (state, view, reference, child):
        period_s = config.daemon.control_period_s
        # the robot stands at (1, 1) facing +y (odometry frame); the leg is 0.12 m ahead of it
        pose = (1.0, 1.0, math.pi / 2)
        for k in range(4):
            state.odometry_history.append(100.0 + k * period_s, *pose)
        state.odometry = OdometryPose(*pose)
        state.latest_scan = _wall_scan(2.0, 100.0 + 3 * period_s)  # only a far wall in the scan
        verdicts = {}
        for k, (points, w) in enumerate(((None, 0.0), (np.array([[1.0, 1.12]]), 0.0), (np.array([[1.12, 1.0]]), 0.0))):
            now_s = 100.0 + (4 + k) * period_s
            state.blind_zone_points = points
            state.motion_command = MotionRequest(0.2, w, "drive", now_s)
            state.wheel_ticks = (now_s, 0, 0)
            expected = reference.tick(state, now_s)
            view.refresh()
            assert child.tick(view, now_s) == expected
            assert view.safety_stop == state.safety_stop
            verdicts[k] = state.safety_stop.startswith("emergency stop") and expected == (0.0, 0.0)
            state.safety_stop = ""
            view.safety_stop = ""
        assert verdicts == {0: False, 1: True, 2: False}  # nothing; the leg ahead; the leg beside (to the right)


class _IdleChild:
    """A control process that stays alive: its sentinel (a pipe nobody writes) never becomes readable."""

    def __init__(self) -> None:
        self._rx, self._tx = os.pipe()
        self.sentinel = self._rx
        self.pid = 0
        self.exitcode: int | None = None

    def join(self, timeout: float | None = None) -> None:
        return None

    def kill(self) -> None:
        self.exitcode = -9

    def close(self) -> None:
        for fd in (self._rx, self._tx):
            with contextlib.suppress(OSError):  # closed already (the task closes a child that exited)
                os.close(fd)


def _outputs_taken(beat_period_s: float | None, monkeypatch: pytest.MonkeyPatch) -> tuple[list[float], list[float]]:
    """The loop times at which the main side took the child's outputs over 1 s of virtual time,
    and the times of the odometry's beats (every ``beat_period_s``; None: no odometry)."""
    from mazebot.sim.virtual_time import run_virtual

    taken: list[float] = []
    beats: list[float] = []
    child = _IdleChild()
    monkeypatch.setattr(control_process, "start_child", lambda *args: (child, _NullPipe()))
    monkeypatch.setattr(control_process, "_take_output",
                        lambda *args: taken.append(asyncio.get_running_loop().time()))

    async def main() -> None:
        config = Config()
        link = ControlLink.create(config)
        state = SharedState()
        task = asyncio.create_task(control_process.run(link, Recorder(), state, ControlHeartbeat(RealClock()),
                                                       config, lambda: None))
        await tick_odometry_beats(state, beats, asyncio.get_running_loop().time() + 1.0, beat_period_s)
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await task
        link.close()

    run_virtual(main(), start_s=100.0)
    child.close()
    return taken, beats


class _NullPipe:
    def send_bytes(self, data: bytes) -> None:
        pass

    def close(self) -> None:
        pass


def test_the_child_s_outputs_are_taken_in_the_odometry_s_wake_ups_and_without_it_each_period(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # with the odometry beating at 40 Hz, each take follows a beat in the same wake-up (no timer of
    # its own: the loop's clock has not moved), and no control period goes without one
    period_s = Config().daemon.control_period_s
    taken, beats = _outputs_taken(0.025, monkeypatch)
    after_beats = [t for t in taken if beats[0] < t <= beats[-1] + 1e-3]  # the task's last take (cancelled) aside
    assert len(after_beats) >= len(beats) - 1
    for t in after_beats:
        since_beat_s = t - max(b for b in beats if b <= t)
        assert since_beat_s < 1e-4  # a pass or two of the loop (1 µs each on virtual time)
    # no odometry (a test's state, a stalled task): the outputs are still taken every control period
    taken, _ = _outputs_taken(None, monkeypatch)
    taken = [t for t in taken if t <= 101.0]
    gaps = np.diff(taken)
    assert len(taken) >= 18
    assert gaps.max() <= period_s + 1e-3
