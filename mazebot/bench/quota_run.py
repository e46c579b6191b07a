"""``mazebot bench --cpu-quota``: the daemon on a Pi's share of this CPU, the world outside it.

Why one module of ~760 lines: the three processes of a quota run (the daemon under the quota,
the world outside it, this parent watching both) and the ``/proc`` readings that measure them
are one experiment; the metrics at the end read the record the watcher fills, so its fields and
their readers sit together.

Three processes, on the real clock:

- **the world** (:mod:`mazebot.sim.world_process`): physics, encoder edges, the lidar
  emulator on a pseudo-terminal; outside any quota, so a slow daemon never slows the
  world it lives in (a shared process would also share the GIL);
- **the daemon** (:func:`daemon_main`): ``main.run_daemon`` with the robot's own hardware
  builder (``main.robot_hardware_builder``): the serial driver opens the pty with
  pyserial-asyncio as it opens ``/dev/ttyUSB0`` on the robot; the motor HAT is a
  :class:`~mazebot.sim.remote_devices.PipeMotorKit` and lgpio's callback thread a
  :class:`~mazebot.sim.remote_devices.GpioEdgeThread` (the real encoder code counts the
  world's edges on it). The process joins the quota's cgroup before it imports the
  daemon, so its tasks, thread pools and loop-closure worker (forked later from a fork
  server the daemon itself starts) all run inside;
- **this process**: makes and removes the cgroup (:mod:`mazebot.bench.cgroup`), reads its
  CPU accounting and throttling counters when the daemon says the run started and ended,
  samples every process's resident memory, and turns the daemon's report and the
  world's ground truth into metrics.

Stopping: the daemon is stopped first (a message, then SIGKILL), then the world, then the
cgroup goes; Ctrl-C or SIGTERM to this process (or to the whole process group) does the same:
the daemon ignores both and the world waits for the daemon, so this process alone decides the
order.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import multiprocessing
import os
import signal
import time
from array import array
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any

from mazebot.cpu_budget import RecentValues
from mazebot.errors import MazebotError

log = logging.getLogger(__name__)

#: How long the world may take to build and serve its lidar, and the daemon to come up.
START_TIMEOUT_S = 60.0
#: How long a stopped daemon or world may take to end before it is terminated, then killed.
STOP_TIMEOUT_S = 15.0
#: A control tick this late (ms) is counted apart in the results: a whole control period (the
#: default 50 ms) missed, as a host's stop of the whole machine (its ~100 ms period) shows, where
#: a daemon on a machine of its own comes 1-2 ms late.
LATE_TICK_MS = 50.0
#: How often this process samples the resident memory of the others.
RSS_PERIOD_S = 0.5
#: How often the daemon samples SLAM's pose estimate (for the trajectory error).
RECORD_PERIOD_S = 0.1
#: Control ticks whose lateness is kept for the p99 (a 16x16 maze is ~12 000 ticks at 20 Hz).
LATENESS_KEPT = 200_000
#: The emulated Pi GPIO path's cost per edge (:mod:`mazebot.sim.edge_cost`), measured after each run:
#: quadrature cycles per timed run (4 edges each) and runs per stage (the median kept); ~0.6 s of CPU.
EDGE_COST_CYCLES = 5_000
EDGE_COST_REPEATS = 7
#: What the daemon process writes to the bench's stderr (the control process logs at ``[daemon] log_level``).
DAEMON_LOG_LEVEL = "warning"


class QuotaRunError(MazebotError):
    """The two-process run could not be carried out (the world failed to start): exit code 70."""


# --- the daemon process ----------------------------------------------------------------


def daemon_main(
    config: Any,
    max_run_s: float,
    pty_path: str,
    motor_tx: Connection,
    edge_rx: Connection,
    result_tx: Connection,
    control_rx: Connection,
    procs_files: list[str],
) -> None:
    """The daemon process's entry point: join the cgroup, run the daemon, send its report."""
    from mazebot.bench.cgroup import join
    from mazebot.logs import setup_logging

    if procs_files:  # first of all: everything this process does from here on is inside the quota
        join([Path(p) for p in procs_files])
    # A spawned process starts with no logging set up: only Python's last-resort handler wrote
    # its warnings, bare, and its info lines went nowhere. The daemon's warnings and errors (a
    # dropped revolution and why, a fault) reach the bench's output as ``mazebot run`` writes them;
    # its info lines (every closure and goal) would bury the progress line.
    setup_logging(DAEMON_LOG_LEVEL)
    # Ctrl-C (or a SIGTERM to the process group) reaches every process at once: the parent stops
    # us, then the world. Ignored here, both are ignored by the loop-closure fork server and its
    # worker too (a process started from here inherits ignored signals), which would otherwise die
    # under the daemon's feet.
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    try:
        result = asyncio.run(_run_daemon(config, max_run_s, pty_path, motor_tx, edge_rx, result_tx, control_rx))
        result_tx.send(("result", result))
    except BaseException as exc:
        with contextlib.suppress(OSError):
            result_tx.send(("error", f"{type(exc).__name__}: {exc}"))
        raise
    finally:
        for conn in (motor_tx, edge_rx, result_tx, control_rx):
            conn.close()


async def _run_daemon(
    config: Any,
    max_run_s: float,
    pty_path: str,
    motor_tx: Connection,
    edge_rx: Connection,
    result_tx: Connection,
    control_rx: Connection,
) -> dict[str, Any]:
    from mazebot.clock import RealClock
    from mazebot.main import Hardware, robot_hardware_builder, run_daemon
    from mazebot.sim.remote_devices import GpioEdgeThread, PipeKitOpener, PipeMotorKit
    from mazebot.sim.world_process import encoder_pins
    from mazebot.state import RunState, SharedState
    from mazebot.tasks.supervisor import Supervisor

    loop = asyncio.get_running_loop()
    clock = RealClock()
    config = config.model_copy(deep=True)
    config.lidar.port = pty_path  # the emulated A1 on its pty, where the robot has /dev/ttyUSB0
    kit = PipeMotorKit(motor_tx, clock)
    factory = GpioEdgeThread.pin_factory()
    gpio = GpioEdgeThread(edge_rx, factory, encoder_pins(config))
    opener = PipeKitOpener(motor_tx)
    robot_builder = robot_hardware_builder(open_kit=lambda address, frequency: kit, make_pin_factory=lambda: factory)

    async def build(config: Any, clock: Any, stack: contextlib.AsyncExitStack) -> Hardware:
        hardware = await robot_builder(config, clock, stack)
        hardware.motor_kit_opener = opener  # the control process writes the world's motors too
        gpio.start()  # the encoders listen now: the edges start arriving
        stack.callback(gpio.stop)
        return hardware

    state = SharedState()
    state.control_lateness_ms = RecentValues(LATENESS_KEPT)
    state.odometry_edge_age_ms = RecentValues(LATENESS_KEPT)
    # the logs in flat float arrays (t, x, y, θ per row): the daemon's memory is measured with them in it
    run: dict[str, Any] = {"done": False, "start_s": None, "end_s": None, "est": array("d"), "odometry": array("d"),
                           "scans": [], "encoders": None, "gpio_at_start": (None, 0), "gpio_at_end": (None, 0),
                           "loop_at_start": (None, None), "loop_at_end": (None, None)}

    def on_started(hardware: Hardware, state: SharedState, supervisor: Supervisor) -> None:
        run["start_s"] = clock.now_s()
        run["gpio_at_start"] = (gpio.cpu_s(), gpio.edges)  # the simulator's stand-in, read with the cgroup's CPU
        run["loop_at_start"] = (time.thread_time(), time.process_time())  # the event loop's thread, this process
        result_tx.send(("started", run["start_s"]))

        def on_control() -> None:
            try:
                message = control_rx.recv()
            except (EOFError, OSError):  # the parent is gone
                message = "stop"
            if message == "stop":
                loop.remove_reader(control_rx.fileno())
                supervisor.request_stop("benchmark stopped")

        loop.add_reader(control_rx.fileno(), on_control)

        # the recorder and the driver run in the odometry's wake-ups (:class:`mazebot.clock.Beat`):
        # the harness's own timers would wake the daemon's loop 15 times a second, charged to its CPU
        record_beats = max(1, round(RECORD_PERIOD_S * config.encoders.odometry_rate_hz))

        async def recorder() -> None:
            logged_s = -math.inf
            while True:
                p = state.pose
                if state.pose_time_s is not None:
                    run["est"].extend((state.pose_time_s, p.x_m, p.y_m, p.theta_rad))
                scan, scans = state.latest_scan, run["scans"]
                if scan is not None and len(scan.time_s) and (not scans or scans[-1][0] != scan.revolution):
                    scans.append((scan.revolution, float(scan.time_s[0])))  # the stamp of its first sample
                history = state.odometry_history
                if history is not None:  # every odometry pose with its date, as SLAM reads them
                    rows = history.since(logged_s)
                    if len(rows):
                        run["odometry"].extend(rows.ravel().tolist())
                        logged_s = float(rows[-1, 0])
                await state.odometry_beat.wait(record_beats, timeout_s=2 * RECORD_PERIOD_S)

        async def explore() -> None:
            """Press start as the user would, then wait for the planner to say done."""
            await clock.sleep(1.0)  # the lidar spins up and SLAM publishes its first map
            state.commands.put_nowait("start")
            while state.run_state not in (RunState.DONE, RunState.FAULT):
                await state.odometry_beat.wait(2 * record_beats, timeout_s=4 * RECORD_PERIOD_S)
            run["done"] = state.run_state is RunState.DONE

        async def drive_then_stop() -> None:
            with contextlib.suppress(TimeoutError):  # out of time: done stays False
                await asyncio.wait_for(explore(), max_run_s)
            run["end_s"] = clock.now_s()
            reading = hardware.encoders.read()
            run["encoders"] = (reading.left_ticks, reading.right_ticks)
            run["gpio_at_end"] = (gpio.cpu_s(), gpio.edges)
            run["loop_at_end"] = (time.thread_time(), time.process_time())
            result_tx.send(("finished", run["end_s"]))
            supervisor.request_stop("benchmark run finished")

        supervisor.start("bench-recorder", recorder)
        supervisor.start("bench-driver", drive_then_stop)

    exit_code = await run_daemon(
        config, build, clock=clock, serve_web=False, install_signal_handlers=False, state=state,
        on_started=on_started, autonomous=True,
    )
    fault = state.active_fault
    slam = state.slam
    return {
        "exit_code": exit_code,
        "done": run["done"] and exit_code == 0,
        "start_s": run["start_s"],
        "end_s": run["end_s"],
        "run_state": str(state.run_state),
        "fault": None if fault is None else f"{fault.source}: {fault.message}",
        "fault_time_s": None if fault is None else fault.time_s,
        "events": [(e.time_s, e.source, e.message) for e in list(state.events)[-40:]],
        "faults_raised": state.faults_raised,
        "lateness_ms": list(state.control_lateness_ms),
        "edge_age_ms": list(state.odometry_edge_age_ms),
        # thread CPU per part of the daemon (mazebot.cpu_budget), over the run
        "cpu_budget": state.cpu.table(run["end_s"] - run["start_s"]
                                      if run["end_s"] is not None and run["start_s"] is not None else None),
        "scan_ms": list(state.scan_ms),
        "slam_scans": slam.scans,
        "slam_scans_dropped": slam.scans_dropped,
        "slam_drop_notes": list(slam.drop_notes),
        "slam_worker_pauses": slam.worker_pauses,
        "slam_queue_peak": slam.queue_peak,
        "slam_queue_behind": slam.queue_behind,
        "slam_worker_paused_s": slam.worker_paused_s,
        "slam_scans_uncovered": slam.uncovered,
        "slam_scans_held_back": slam.held_back,
        "keyframes": slam.keyframes,
        "loop_closures": slam.loop_closures,
        "lidar_revolutions": state.sensors.lidar_revolutions,
        "lidar_bytes_dropped": state.sensors.lidar_bytes_dropped,
        "encoder_invalid_transitions": state.sensors.encoder_invalid_transitions,
        "encoder_ticks": run["encoders"],
        "gpio_edges": gpio.edges,
        # the GPIO edge thread over the run (started .. finished): its CPU seconds and the edges it drove
        "gpio_thread_cpu_s": _difference(run["gpio_at_end"][0], run["gpio_at_start"][0]),
        "gpio_window_edges": run["gpio_at_end"][1] - run["gpio_at_start"][1],
        # the event loop's thread and the daemon's whole process (all its threads) over the run, CPU seconds
        "loop_thread_cpu_s": _difference(run["loop_at_end"][0], run["loop_at_start"][0]),
        "daemon_process_cpu_s": _difference(run["loop_at_end"][1], run["loop_at_start"][1]),
        "motor_writes": kit.writes_sent + opener.writes_sent,  # this process's and the control process's
        "est": run["est"],
        "odometry": run["odometry"],
        "scans": run["scans"],
        "planner_events": list(state.planner_events),
        "map": state.map,
    }


def _difference(end: float | None, start: float | None) -> float | None:
    return None if end is None or start is None else end - start


# --- this process ------------------------------------------------------------------------


def _children(pid: int) -> list[int]:
    out: list[int] = []
    with contextlib.suppress(OSError):
        for task in os.listdir(f"/proc/{pid}/task"):
            with contextlib.suppress(OSError), open(f"/proc/{pid}/task/{task}/children") as f:
                out += [int(c) for c in f.read().split()]
    return out


def process_tree(pid: int) -> list[int]:
    """``pid`` and all its descendants now (from ``/proc/PID/task/TID/children``)."""
    seen, todo = [], [pid]
    while todo:
        p = todo.pop()
        if p in seen:
            continue
        seen.append(p)
        todo += _children(p)
    return seen


def _proc_kb(path: str, key: str) -> int:
    with contextlib.suppress(OSError, ValueError, IndexError), open(path) as f:
        for line in f:
            if line.startswith(key):
                return int(line.split()[1])
    return 0


def _start_time(pid: int) -> str | None:
    """The start time of process ``pid`` (field 22 of ``/proc/PID/stat``): a pid with its start time
    names one process, even once the pid has been reused."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rpartition(")")[2].split()[19]
    except (OSError, IndexError):
        return None


def process_cpu_s(pid: int | None) -> float | None:
    """User + system CPU seconds of process ``pid`` so far (fields 14 and 15 of ``/proc/PID/stat``)."""
    if pid is None:
        return None
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rpartition(")")[2].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def end_processes(seen: dict[int, str | None], timeout_s: float = STOP_TIMEOUT_S / 3) -> list[int]:
    """Wait for these processes (pid: start time) to end; SIGTERM, then SIGKILL, the ones that do not.

    The daemon's fork server and resource tracker end by themselves shortly after the daemon;
    one that outlives it (a stuck worker) would otherwise be an orphan. Returns the pids that
    had to be signalled.
    """
    def alive() -> list[int]:
        return [pid for pid, start in seen.items() if start is not None and _start_time(pid) == start]

    signalled: list[int] = []
    for sig in (None, signal.SIGTERM, signal.SIGKILL):
        if sig is not None:
            for pid in alive():
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.kill(pid, sig)
                    signalled.append(pid)
        deadline = time.monotonic() + timeout_s
        while alive() and time.monotonic() < deadline:
            time.sleep(0.05)
        if not alive():
            break
    return sorted(set(signalled))


def rss_mb(pids: list[int]) -> float:
    """The resident memory of these processes added up (``VmRSS`` of ``/proc/PID/status``), MB.

    Pages the processes share (the fork server's numpy and scipy, forked into the
    loop-closure worker) count once per process here: an upper bound.
    """
    return sum(_proc_kb(f"/proc/{pid}/status", "VmRSS:") for pid in pids) / 1024.0


def pss_mb(pids: list[int]) -> float:
    """Their proportional set size added up (``Pss`` of ``/proc/PID/smaps_rollup``), MB: each shared
    page split between the processes that map it, so the sum is the memory they take together
    (kernel documentation, ``Documentation/filesystems/proc.rst``)."""
    return sum(_proc_kb(f"/proc/{pid}/smaps_rollup", "Pss:") for pid in pids) / 1024.0


@dataclass
class QuotaRecord:
    """What this process saw of one two-process run."""

    percent: float | None
    cgroup_version: int | None = None
    cpu_at_start: Any = None  # mazebot.bench.cgroup.CpuStat when the daemon said "started"
    cpu_at_end: Any = None  # ... and "finished"
    cpu_at_exit: Any = None  # ... and when the daemon process had ended
    world_cpu_at_start: float | None = None  # the world process's CPU seconds at "started" and "finished"
    world_cpu_at_end: float | None = None
    steal_at_start_s: float | None = None  # the host's steal time of this machine at those moments
    steal_at_end_s: float | None = None
    started_s: float | None = None  # this process's monotonic clock at those moments
    finished_s: float | None = None
    daemon_pid: int | None = None
    world_pid: int | None = None
    daemon_rss_mb_peak: float = 0.0  # the daemon and its children (fork server, worker), VmRSS added up
    daemon_pss_mb_peak: float = 0.0  # ... proportional set size added up (shared pages once)
    world_rss_mb_peak: float = 0.0
    #: every process seen in the daemon's tree (pid: start time), ended with it
    daemon_tree: dict[int, str | None] = field(default_factory=dict)
    truth: deque[tuple[float, float, float, float, int]] = field(default_factory=lambda: deque(maxlen=4))
    collision_times_s: list[float] = field(default_factory=list)  # the world's truth reports that counted one more
    daemon: dict[str, Any] | None = None  # the daemon's report (``_run_daemon``)
    world: dict[str, Any] | None = None  # the world's summary
    errors: list[str] = field(default_factory=list)
    loadavg_before: str | None = None  # /proc/loadavg when the run began and when it ended
    loadavg_after: str | None = None
    #: seconds of CPU per encoder edge of each stage of :mod:`mazebot.sim.edge_cost`, measured in this
    #: process once the run's processes had ended (None: not measured)
    edge_costs: dict[str, float] | None = None


def _stop_process(
    process: multiprocessing.process.BaseProcess,
    control_tx: Connection | None,
    output: Connection | None = None,
    on_message: Callable[[Any], None] | None = None,
) -> None:
    """Ask ``process`` to stop, then terminate it, then kill it; returns once it has ended.

    While it stops, what it still sends on ``output`` is read (to ``on_message``): a process
    blocked writing its last report into a full pipe could not end.
    """
    if process.exitcode is not None or process.pid is None:
        return
    if control_tx is not None:
        with contextlib.suppress(OSError, ValueError):
            control_tx.send("stop")
    deadline = time.monotonic() + STOP_TIMEOUT_S
    while process.exitcode is None and time.monotonic() < deadline:
        watched = [process.sentinel] + ([output] if output is not None else [])
        if output is not None and output in wait(watched, timeout=0.5):
            try:
                message = output.recv()
            except (EOFError, OSError):
                output = None
                continue
            if on_message is not None:
                on_message(message)
    if process.exitcode is None:
        process.terminate()
        process.join(STOP_TIMEOUT_S / 3)
    if process.exitcode is None:
        process.kill()
        process.join()


def run_two_process(
    config: Any,
    maze_path: str | None,
    seed: int | None,
    size: tuple[int, int] | None,
    max_run_s: float,
    quota: Any = None,
) -> QuotaRecord:
    """One run: the world in its process, the daemon in another (inside ``quota``, a
    :class:`mazebot.bench.cgroup.CpuQuota`, when given); everything stopped on return."""
    from mazebot.sim.world_process import world_main

    ctx = multiprocessing.get_context("spawn")  # fresh interpreters: nothing of this process's state
    record = QuotaRecord(percent=quota.percent if quota is not None else None,
                         cgroup_version=quota.version if quota is not None else None)
    motor_rx, motor_tx = ctx.Pipe(duplex=False)
    edge_rx, edge_tx = ctx.Pipe(duplex=False)
    report_rx, report_tx = ctx.Pipe(duplex=False)
    world_ctl_rx, world_ctl_tx = ctx.Pipe(duplex=False)
    result_rx, result_tx = ctx.Pipe(duplex=False)
    daemon_ctl_rx, daemon_ctl_tx = ctx.Pipe(duplex=False)
    world = ctx.Process(target=world_main, name="mazebot-world",
                        args=(config, maze_path, seed, size, motor_rx, edge_tx, report_tx, world_ctl_rx))
    daemon: multiprocessing.process.BaseProcess | None = None
    record.loadavg_before = _loadavg()
    try:
        world.start()
        record.world_pid = world.pid
        for conn in (motor_rx, edge_tx, report_tx, world_ctl_rx):
            conn.close()  # the world's ends live in the world
        pty_path = _await_ready(report_rx, world, record)
        procs = [str(p) for p in quota.procs_files] if quota is not None else []
        daemon = ctx.Process(target=daemon_main, name="mazebot-daemon",
                             args=(config, max_run_s, pty_path, motor_tx, edge_rx, result_tx, daemon_ctl_rx, procs))
        daemon.start()
        record.daemon_pid = daemon.pid
        for conn in (motor_tx, edge_rx, result_tx, daemon_ctl_rx):
            conn.close()
        _watch(daemon, world, result_rx, report_rx, daemon_ctl_tx, quota, record, max_run_s)
        if quota is not None:
            record.cpu_at_exit = quota.stat()
        record.loadavg_after = _loadavg()
    finally:
        if daemon is not None:
            _stop_process(daemon, daemon_ctl_tx, result_rx, lambda message: _on_result(message, record, quota))
            left = end_processes(record.daemon_tree)
            if left:
                record.errors.append(f"daemon: processes {left} outlived the daemon and were ended")
        with contextlib.suppress(OSError, ValueError):
            world_ctl_tx.send("stop")
        _drain_world(report_rx, world, record)
        _stop_process(world, None)
        for conn in (report_rx, world_ctl_tx, result_rx, daemon_ctl_tx):
            conn.close()
    record.edge_costs = _edge_costs()
    return record


def _edge_costs() -> dict[str, float] | None:
    """The Pi's GPIO path per edge and its parts, on this process's thread CPU (the run's processes ended)."""
    from mazebot.sim.edge_cost import measure_stages

    try:
        return measure_stages(EDGE_COST_CYCLES, EDGE_COST_REPEATS)
    except Exception as exc:  # a measurement gone wrong costs the one figure, not the run
        log.warning("the GPIO path's cost per edge could not be measured: %s", exc)
        return None


def _await_ready(report_rx: Connection, world: multiprocessing.process.BaseProcess, record: QuotaRecord) -> str:
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        ready = wait([report_rx, world.sentinel], timeout=1.0)
        if report_rx in ready:
            try:
                message = report_rx.recv()
            except EOFError:
                break
            if message[0] == "ready":
                return message[1]
            if message[0] == "error":
                raise QuotaRunError(f"the simulated world failed to start: {message[1]}")
        elif world.sentinel in ready:
            break
    raise QuotaRunError(f"the simulated world did not serve its lidar within {START_TIMEOUT_S:g} s "
                        f"(exit code {world.exitcode})")


def _take_truth(report_rx: Connection, record: QuotaRecord) -> None:
    while report_rx.poll():
        message = report_rx.recv()
        if message[0] == "truth":
            if record.truth and message[5] > record.truth[-1][4]:  # the world counted a collision since
                record.collision_times_s.append(message[1])
            record.truth.append(message[1:])
        elif message[0] == "summary":
            record.world = message[1]
        elif message[0] == "error":
            record.errors.append(f"world: {message[1]}")


def _watch(
    daemon: multiprocessing.process.BaseProcess,
    world: multiprocessing.process.BaseProcess,
    result_rx: Connection,
    report_rx: Connection,
    daemon_ctl_tx: Connection,
    quota: Any,
    record: QuotaRecord,
    max_run_s: float,
) -> None:
    """Until the daemon process ends: its messages, the world's truth, memory samples, the time limit."""
    hard_deadline = time.monotonic() + START_TIMEOUT_S + max_run_s + STOP_TIMEOUT_S
    next_rss = 0.0
    stop_sent = False
    result_open = True
    while daemon.exitcode is None or result_open:
        watched: list[Any] = [daemon.sentinel, report_rx] + ([result_rx] if result_open else [])
        ready = wait(watched, timeout=RSS_PERIOD_S)
        if result_rx in ready and result_open:
            try:
                _on_result(result_rx.recv(), record, quota)
            except EOFError:
                result_open = False
        if report_rx in ready:
            with contextlib.suppress(EOFError, OSError):
                _take_truth(report_rx, record)
        now = time.monotonic()
        if now >= next_rss:
            next_rss = now + RSS_PERIOD_S
            if daemon.pid is not None and daemon.exitcode is None:
                tree = process_tree(daemon.pid)
                for pid in tree:
                    if pid not in record.daemon_tree:
                        record.daemon_tree[pid] = _start_time(pid)
                record.daemon_rss_mb_peak = max(record.daemon_rss_mb_peak, rss_mb(tree))
                record.daemon_pss_mb_peak = max(record.daemon_pss_mb_peak, pss_mb(tree))
            if world.pid is not None and world.exitcode is None:
                record.world_rss_mb_peak = max(record.world_rss_mb_peak, rss_mb([world.pid]))
        if daemon.exitcode is not None and not result_rx.poll():
            result_open = False
        if now > hard_deadline and not stop_sent:
            record.errors.append("daemon: did not end in time, stopped")
            with contextlib.suppress(OSError, ValueError):
                daemon_ctl_tx.send("stop")
            stop_sent = True
        elif stop_sent and now > hard_deadline + STOP_TIMEOUT_S:
            return  # it does not listen: the caller kills it


def _on_result(message: Any, record: QuotaRecord, quota: Any) -> None:
    """One message of the daemon: the CPU counters are read the moment it says started or finished."""
    kind = message[0]
    if kind == "started":
        record.started_s = time.monotonic()
        record.cpu_at_start = quota.stat() if quota is not None else None
        record.world_cpu_at_start = process_cpu_s(record.world_pid)
        record.steal_at_start_s = host_steal_s()
    elif kind == "finished":
        record.finished_s = time.monotonic()
        record.cpu_at_end = quota.stat() if quota is not None else None
        record.world_cpu_at_end = process_cpu_s(record.world_pid)
        record.steal_at_end_s = host_steal_s()
    elif kind == "result":
        record.daemon = message[1]
    elif kind == "error":
        record.errors.append(f"daemon: {message[1]}")


def _drain_world(report_rx: Connection, world: multiprocessing.process.BaseProcess, record: QuotaRecord) -> None:
    """Wait (a little) for the world's summary after it was told to stop."""
    deadline = time.monotonic() + STOP_TIMEOUT_S
    while record.world is None and time.monotonic() < deadline:
        ready = wait([report_rx, world.sentinel], timeout=0.5)
        if report_rx in ready:
            try:
                _take_truth(report_rx, record)
            except (EOFError, OSError):
                return
        elif world.sentinel in ready and not report_rx.poll():
            return


# --- metrics -----------------------------------------------------------------------------


def _round(value: float | None, digits: int) -> float | None:
    return None if value is None else round(value, digits)


def quota_metrics(config: Any, spec: Any, record: QuotaRecord) -> dict[str, Any]:
    """The per-run keys of results.json for a two-process run; a metric whose part is missing is None."""
    import numpy as np

    from mazebot.bench.metrics import count_revisits, map_metrics, relative_poses
    from mazebot.sim.world_source import make_world

    d, w = record.daemon or {}, record.world or {}
    world = make_world(config, spec.maze_path, spec.seed if not spec.maze_path else None,
                       spec.size if not spec.maze_path else None)
    layout = world.maze
    traj = np.asarray(w.get("trajectory") or [], dtype=float).reshape(-1, 4)
    start = tuple(traj[0, 1:]) if len(traj) else world.start_pose
    maps: dict[str, Any] = {"coverage": None, "map_f1": None}
    if d.get("map") is not None:
        maps = map_metrics(d["map"], world, start, config.robot.footprint_radius_m)
    # SLAM's estimate against the true pose at the instant it describes (one monotonic clock for all)
    est = np.asarray(d.get("est") or [], dtype=float).reshape(-1, 4)
    ate_rms = ate_max = None
    if len(est) and len(traj) > 1:
        th = np.unwrap(traj[:, 3])
        truth = np.column_stack([np.interp(est[:, 0], traj[:, 0], traj[:, k]) for k in (1, 2)]
                                + [np.interp(est[:, 0], traj[:, 0], th)])
        rel = relative_poses(start, truth)
        err = np.hypot(est[:, 1] - rel[:, 0], est[:, 2] - rel[:, 1])
        ate_rms, ate_max = float(np.sqrt(np.mean(err**2))), float(err.max())
    odometry_errors = odometry_increment_errors(np.asarray(d.get("odometry") or [], dtype=float).reshape(-1, 4), traj)
    lidar_errors = lidar_stamp_errors_ms([t for _, t in d.get("scans") or []], w.get("lidar_revolution_starts_s") or [])
    lateness = np.asarray(d.get("lateness_ms") or [], dtype=float)
    edge_age = np.asarray(d.get("edge_age_ms") or [], dtype=float)
    time_s = d["end_s"] - d["start_s"] if d.get("end_s") is not None and d.get("start_s") is not None else None
    # the daemon's CPU from the cgroup's own accounting, over the run (started .. finished)
    a, b = record.cpu_at_start, record.cpu_at_end
    cpu_s = b.usage_s - a.usage_s if a is not None and b is not None and None not in (a.usage_s, b.usage_s) else None
    window_s = (record.finished_s - record.started_s
                if record.finished_s is not None and record.started_s is not None else None)
    cpu_pct = 100.0 * cpu_s / window_s if cpu_s is not None and window_s else None

    def delta(name: str) -> Any:
        if a is None or b is None or getattr(a, name) is None or getattr(b, name) is None:
            return None
        return getattr(b, name) - getattr(a, name)

    throttled_s = delta("throttled_s")
    exit_stat = record.cpu_at_exit
    gpio = gpio_share(cpu_s, window_s, d.get("gpio_thread_cpu_s"), d.get("gpio_window_edges"), record.edge_costs)
    where = cpu_by_thread(cpu_s, time_s, d.get("loop_thread_cpu_s"), d.get("daemon_process_cpu_s"),
                          d.get("gpio_thread_cpu_s"), d.get("cpu_budget"))
    return {
        "maze": spec.name,
        "seed": spec.seed,
        "drive": spec.drive,
        "clock": "real",
        "cpu_quota_percent": record.percent,  # None: no limit (the same processes, accounting only)
        "cgroup_version": record.cgroup_version,
        "cells": int(layout.width * layout.height) if layout is not None else None,
        "done": bool(d.get("done")) and not record.errors,
        "exit_code": d.get("exit_code"),
        "fault": d.get("fault"),
        "faults_raised": d.get("faults_raised"),
        "errors": record.errors,
        "time_s": _round(time_s, 2),
        "coverage": maps["coverage"],
        "map_f1": maps["map_f1"],
        "collisions": w.get("collisions"),
        # seconds since the daemon started: when the world saw each collision, when the fault came
        "collision_times_s": [_round(t - (d.get("start_s") or 0.0), 2) for t in record.collision_times_s],
        "fault_time_s": _round(d["fault_time_s"] - (d.get("start_s") or 0.0), 2)
        if d.get("fault_time_s") is not None else None,
        "events": [(_round(t - (d.get("start_s") or 0.0), 2), source, text)
                   for t, source, text in d.get("events") or []],
        "path_m": _round(w.get("odometer_m"), 3),
        "revisits": count_revisits(layout, traj[:, 1:3]) if layout is not None and len(traj) else None,
        "ate_rms_m": _round(ate_rms, 4),
        "ate_max_m": _round(ate_max, 4),
        "control_jitter_ms_p99": _round(float(np.percentile(lateness, 99)), 3) if len(lateness) else None,
        "control_jitter_ms_max": _round(float(lateness.max()), 3) if len(lateness) else None,
        "control_ticks": len(lateness),
        "control_ticks_late_over_50ms": int(np.count_nonzero(lateness > LATE_TICK_MS)) if len(lateness) else None,
        # CPU time the hypervisor gave this machine's virtual CPUs to others during the run: while
        # the host runs something else no process here runs, however urgent (host_steal_s)
        "host_steal_s": _round(record.steal_at_end_s - record.steal_at_start_s, 2)
        if record.steal_at_end_s is not None and record.steal_at_start_s is not None else None,
        # how old the newest encoder edge was when odometry read the counts (the error of dating
        # the pose by the reading time); the odometry dates it by the edge's own stamp
        # the odometry's motion over 0.2 s between two of its dates against the true motion between
        # the same instants: a pose dated late shows as a turn or a drive that comes late
        "odometry_window_heading_error_deg_p50": _round(odometry_errors[0], 3),
        "odometry_window_heading_error_deg_p99": _round(odometry_errors[1], 3),
        "odometry_window_position_error_mm_p50": _round(odometry_errors[2], 3),
        "odometry_window_position_error_mm_p99": _round(odometry_errors[3], 3),
        # the daemon's stamp of each revolution's first sample against when the emulator measured it
        "lidar_stamp_error_ms_p50": _round(lidar_errors[0], 3),
        "lidar_stamp_error_ms_p99": _round(lidar_errors[1], 3),
        "lidar_stamp_error_ms_max": _round(lidar_errors[2], 3),
        "encoder_edge_age_ms_p50": _round(float(np.percentile(edge_age, 50)), 3) if len(edge_age) else None,
        "encoder_edge_age_ms_p99": _round(float(np.percentile(edge_age, 99)), 3) if len(edge_age) else None,
        "encoder_edge_age_ms_max": _round(float(edge_age.max()), 3) if len(edge_age) else None,
        "scan_ms_p50": _round(float(np.percentile(d["scan_ms"], 50)), 3) if d.get("scan_ms") else None,
        "lidar_revolutions": d.get("lidar_revolutions"),
        "slam_scans": d.get("slam_scans"),
        "slam_scans_dropped": d.get("slam_scans_dropped"),  # revolutions SLAM had to drop
        "slam_drop_notes": d.get("slam_drop_notes") or [],  # what held SLAM up at each (the latest 50)
        # SLAM paused the loop-closure worker to catch up ([slam] loop_closure_pause_behind): times, seconds
        "slam_worker_pauses": d.get("slam_worker_pauses"),
        # the most revolutions that waited for SLAM at once; revolutions queued with 4 or more waiting
        "slam_queue_peak": d.get("slam_queue_peak"),
        "slam_queue_behind": d.get("slam_queue_behind"),
        "slam_worker_paused_s": _round(d.get("slam_worker_paused_s"), 2),
        "slam_scans_uncovered": d.get("slam_scans_uncovered"),  # left out: the odometry never reached their end
        "slam_scans_held_back": d.get("slam_scans_held_back"),  # localized only, not painted: the odometry distrusted
        "lidar_bytes_dropped": d.get("lidar_bytes_dropped"),
        "loop_closures": d.get("loop_closures"),
        "encoder_invalid_transitions": d.get("encoder_invalid_transitions"),
        "encoder_ticks": d.get("encoder_ticks"),
        "gpio_edges": d.get("gpio_edges"),
        "world_edges_sent": w.get("edges_sent"),
        "motor_writes": d.get("motor_writes"),
        "world_motor_writes": w.get("motor_writes"),
        "lidar_bytes_sent": w.get("lidar_bytes_sent"),
        "daemon_cpu_s": _round(cpu_s, 3),
        "cpu_budget": d.get("cpu_budget"),
        "daemon_cpu_percent": _round(cpu_pct, 1),  # of one core, over the run
        "daemon_cpu_percent_of_quota": _round(100.0 * cpu_pct / record.percent, 1)
        if cpu_pct is not None and record.percent else None,
        # the same with the simulator's share taken out: what its GPIO stand-in does per edge beyond
        # the Pi's path, times the edges (gpio_share); and the edge thread's own figures
        "daemon_cpu_percent_sim_out": _round(gpio["daemon_cpu_percent_sim_out"], 2),
        "gpio_sim_share_percent": _round(gpio["gpio_sim_share_percent"], 3),
        "gpio_thread_cpu_percent": _round(gpio["gpio_thread_cpu_percent"], 2),
        "gpio_thread_us_per_edge": _round(gpio["gpio_thread_us_per_edge"], 3),
        "gpio_sim_path_us_per_edge": _round(gpio["gpio_sim_path_us_per_edge"], 3),
        "gpio_pi_path_us_per_edge": _round(gpio["gpio_pi_path_us_per_edge"], 3),
        "gpio_edges_per_s": _round(gpio["gpio_edges_per_s"], 1),
        "gpio_edge_costs_us": {k: round(v * 1e6, 3) for k, v in record.edge_costs.items()}
        if record.edge_costs else None,
        # where the cgroup's CPU went, ms per robot-second (cpu_by_thread)
        **{key: _round(value, 2) for key, value in where.items()},
        "daemon_cpu_s_total": _round(exit_stat.usage_s if exit_stat is not None else None, 3),  # start-up included
        "cfs_periods": delta("nr_periods"),
        "cfs_throttled": delta("nr_throttled"),
        "cfs_throttled_s": _round(throttled_s, 3),
        "world_cpu_percent": _round(100.0 * (record.world_cpu_at_end - record.world_cpu_at_start) / window_s, 1)
        if record.world_cpu_at_end is not None and record.world_cpu_at_start is not None and window_s else None,
        "daemon_rss_mb_peak": _round(record.daemon_rss_mb_peak or None, 1),  # daemon + its workers
        "daemon_pss_mb_peak": _round(record.daemon_pss_mb_peak or None, 1),
        "world_rss_mb_peak": _round(record.world_rss_mb_peak or None, 1),
        "wall_s": _round(window_s, 2),
        # written beside results.json, not into it; seconds since the daemon started
        "planner_events": [(t_s - (d.get("start_s") or 0.0), text) for t_s, text in d.get("planner_events") or []],
        "loadavg_before": record.loadavg_before,
        "loadavg_after": record.loadavg_after,
    }


#: The parts of the CPU budget whose calls run on the daemon's event-loop thread (mazebot.cpu_budget);
#: the DWA is inside the planner tick, the loop-closure worker and the control tick are other processes.
LOOP_THREAD_PARTS = ("lidar decoding", "odometry", "slam per revolution", "planner tick", "health check")


def cpu_by_thread(cpu_s: float | None, robot_s: float | None, loop_cpu_s: float | None, process_cpu_s: float | None,
                  gpio_cpu_s: float | None, budget: dict[str, Any] | None) -> dict[str, float | None]:
    """Where the cgroup's CPU (``cpu_s`` over ``robot_s``) went, ms per robot-second: the event loop's
    thread, of it what no part's meter holds (the loop's own work: wake-ups, timers, reads, the
    glue between the parts), the daemon process's other threads (the GPIO edge thread, executors,
    the motors' time-to-live guard), and the other processes of the cgroup (the control process,
    the loop-closure worker, the fork server). Each None where a reading is missing.

    The per-part table holds each part's own calls; this says how much of the total lies
    outside them and in which thread or process, so a cut can be aimed there.
    """
    out: dict[str, float | None] = dict.fromkeys(
        ("loop_thread_ms_per_s", "loop_thread_outside_parts_ms_per_s", "process_other_threads_ms_per_s",
         "other_processes_ms_per_s"))
    if not robot_s:
        return out

    def per_s(seconds: float) -> float:
        return 1000.0 * seconds / robot_s

    if loop_cpu_s is not None:
        out["loop_thread_ms_per_s"] = per_s(loop_cpu_s)
        parts = [((budget or {}).get(name) or {}).get("cpu_ms_per_s") for name in LOOP_THREAD_PARTS]
        if budget and None not in parts:
            out["loop_thread_outside_parts_ms_per_s"] = per_s(loop_cpu_s) - sum(p for p in parts if p is not None)
    if process_cpu_s is not None and loop_cpu_s is not None:
        out["process_other_threads_ms_per_s"] = per_s(process_cpu_s - loop_cpu_s - (gpio_cpu_s or 0.0))
    if process_cpu_s is not None and cpu_s is not None:
        out["other_processes_ms_per_s"] = per_s(cpu_s - process_cpu_s)
    return out


def gpio_share(cpu_s: float | None, window_s: float | None, gpio_cpu_s: float | None, edges: int | None,
               edge_costs: dict[str, float] | None) -> dict[str, float | None]:
    """The GPIO edge thread's figures, and the daemon's CPU with the simulator's share of it taken out.

    The thread (:class:`mazebot.sim.remote_devices.GpioEdgeThread`) stands in for lgpio's
    callback thread but drives gpiozero mock pins. What it does per edge beyond the Pi's path
    (:func:`mazebot.sim.edge_cost.simulator_excess_s_per_edge` of ``edge_costs``: the stand-in's
    loop against our decoder behind gpiozero's dispatch and lgpio's notification loop, both
    timed in a loop) is the simulator's: its ``edges`` times that come out of the cgroup's
    ``cpu_s``. The rest of the thread's own CPU (``gpio_cpu_s``, its thread clock: several
    times the loop's cost per edge, for being woken in a busy process that shares one
    interpreter lock) stays: lgpio's callback thread is a Python thread of the daemon too.
    Every figure None where a part is missing: the raw figure then stands alone.
    """
    from mazebot.sim.edge_cost import pi_path_s_per_edge, simulator_excess_s_per_edge

    out: dict[str, float | None] = dict.fromkeys(
        ("daemon_cpu_percent_sim_out", "gpio_sim_share_percent", "gpio_thread_cpu_percent",
         "gpio_thread_us_per_edge", "gpio_sim_path_us_per_edge", "gpio_pi_path_us_per_edge", "gpio_edges_per_s"))
    if edge_costs:
        out["gpio_pi_path_us_per_edge"] = 1e6 * pi_path_s_per_edge(edge_costs)
        out["gpio_sim_path_us_per_edge"] = 1e6 * edge_costs["sim_path"]
    if gpio_cpu_s is None or not window_s or edges is None:
        return out
    out["gpio_thread_cpu_percent"] = 100.0 * gpio_cpu_s / window_s
    out["gpio_edges_per_s"] = edges / window_s
    if edges:
        out["gpio_thread_us_per_edge"] = 1e6 * gpio_cpu_s / edges
    if cpu_s is not None and edge_costs:
        share_s = min(edges * simulator_excess_s_per_edge(edge_costs), gpio_cpu_s)
        out["gpio_sim_share_percent"] = 100.0 * share_s / window_s
        out["daemon_cpu_percent_sim_out"] = 100.0 * (cpu_s - share_s) / window_s
    return out


#: The window over which the odometry's motion is compared with the true motion.
ODOMETRY_WINDOW_S = 0.2


def odometry_increment_errors(odometry: Any, traj: Any,
                              window_s: float = ODOMETRY_WINDOW_S) -> tuple[float | None, ...]:
    """Heading (degrees) and position (mm) error of the odometry's motion over ``window_s``: p50, p99.

    ``odometry`` rows (t, x, y, θ) as the history holds them, ``traj`` the world's true (t, x, y,
    θ) on the same clock. Every 0.1 s of the run, the odometry's motion from ``t`` to
    ``t + window_s`` (in the frame of its pose at ``t``) against the true motion between the
    same two instants: what SLAM is given to de-skew a revolution and to predict the next
    one. The wheels' own errors over 0.2 s are small; a date that is wrong by ``d`` adds about
    the turn rate times ``d``.
    """
    import numpy as np

    if len(odometry) < 2 or len(traj) < 2:
        return (None, None, None, None)
    t0, t1 = max(odometry[0, 0], traj[0, 0]), min(odometry[-1, 0], traj[-1, 0]) - window_s
    if t1 <= t0:
        return (None, None, None, None)
    times = np.arange(t0, t1, 0.1)

    def motion(rows: Any) -> tuple[Any, Any]:
        th = np.unwrap(rows[:, 3])
        a = [np.interp(times, rows[:, 0], v) for v in (rows[:, 1], rows[:, 2], th)]
        b = [np.interp(times + window_s, rows[:, 0], v) for v in (rows[:, 1], rows[:, 2], th)]
        dx, dy = b[0] - a[0], b[1] - a[1]
        c, s = np.cos(a[2]), np.sin(a[2])
        return np.column_stack([c * dx + s * dy, -s * dx + c * dy]), b[2] - a[2]

    odo_xy, odo_th = motion(odometry)
    true_xy, true_th = motion(traj)
    heading = np.degrees(np.abs(odo_th - true_th))
    position = 1000.0 * np.hypot(*(odo_xy - true_xy).T)
    return (float(np.percentile(heading, 50)), float(np.percentile(heading, 99)),
            float(np.percentile(position, 50)), float(np.percentile(position, 99)))


def lidar_stamp_errors_ms(stamps_s: list[float], starts_s: list[float]) -> tuple[float | None, ...]:
    """How late the daemon dated its revolutions, ms: p50, p99 and the largest in size (signed).

    ``stamps_s`` the daemon's stamps of revolutions' first samples, ``starts_s`` the times the
    emulator measured first samples (one clock); each stamp is held against the nearest start
    (revolutions are ~150 ms apart, the errors a few ms).
    """
    import numpy as np

    if not stamps_s or len(starts_s) < 2:
        return (None, None, None)
    starts = np.sort(np.asarray(starts_s, dtype=float))
    stamps = np.asarray(stamps_s, dtype=float)
    i = np.clip(np.searchsorted(starts, stamps), 1, len(starts) - 1)
    nearest = np.where(stamps - starts[i - 1] < starts[i] - stamps, starts[i - 1], starts[i])
    err = 1000.0 * (stamps - nearest)
    return float(np.percentile(err, 50)), float(np.percentile(err, 99)), float(err[np.argmax(np.abs(err))])


def host_steal_s(stat_text: str | None = None) -> float | None:
    """Seconds of "steal" of all this machine's CPUs so far: time a hypervisor ran something else
    while this virtual machine had work to run (the 8th value of ``/proc/stat``'s ``cpu`` line, in
    USER_HZ ticks; ``proc(5)``). None where there is no such line (not Linux) or it cannot be read.

    A virtual machine capped on its host stops whole, all its processes together, when it has
    used its share of a host period: a control tick then comes late by the host's period however
    the daemon is written, so a quota run says how much of its window the host took.
    """
    try:
        text = Path("/proc/stat").read_text() if stat_text is None else stat_text
        fields = text.split("\n", 1)[0].split()
        if fields[0] != "cpu" or len(fields) < 9:
            return None
        return int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def _loadavg() -> str | None:
    """``/proc/loadavg`` now: the machine is shared, and a busy one makes any figure slower."""
    try:
        return Path("/proc/loadavg").read_text().strip()
    except OSError:
        return None
