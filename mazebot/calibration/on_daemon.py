"""The calibration run inside the daemon, for the setup page: the same routine on the daemon's own devices.

``mazebot calibrate`` opens the drivers itself; the running daemon already owns them (the
lidar task reads the lidar, the odometry task the encoders, the control task is the only
writer of the motors). So here the :class:`~mazebot.calibration.routine.Calibrator` gets
:class:`DaemonDevices`, shaped like the drivers but going through the shared state:

- its throttles are the hold-to-run request of the setup page, ``SharedState.jog_command``,
  time-stamped: the control task applies it only while no run is going and no fault is
  active, and only while it is younger than ``[motors] command_ttl_s``. A routine that
  stops refreshing it (stopped, crashed, or its event loop stalled) stops the wheels within
  that time-to-live, as a released jog button does. While a calibration runs it is the one
  writer of that request: the jog endpoint refuses (``mazebot.web.setup``).
- its encoder counts are the odometry task's latest reading (``SharedState.wheel_ticks``);
- its revolutions are the lidar task's (``SharedState.latest_scan``), each one once.

A :class:`PageCalibration` runs one calibration at a time and stops it, motors first, when
the page asks, when the page has not been heard from for :data:`PAGE_SILENCE_S` (a lost
connection), when the robot's run state changes (start, stop or a fault from anywhere), or
when the daemon stops. Nothing is written until the user confirms the result
(:meth:`PageCalibration.write`), and a calibration that did not finish has nothing to write.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import secrets
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final, Literal

from mazebot.calibration.geometry import CalibrationError
from mazebot.calibration.progress import Progress
from mazebot.clock import Clock, RealClock
from mazebot.config import Config
from mazebot.io.scan import Scan
from mazebot.state import RunState, SharedState

log = logging.getLogger(__name__)

#: The page polls the calibration's state every 0.5 s; silent for this long, it is gone
#: (a phone that lost the Wi-Fi, a closed tab) and the calibration stops. The silence is
#: counted in the watch's periods that ran, each at most :data:`WATCH_STEP_MAX_S`, as the
#: control task counts a command's age in the ticks that ran: when the daemon itself could
#: not run (a starved core), the page's polls wait unread in the socket, and that is no
#: silence of the page's. (A stalled daemon stops the wheels anyway: its jog request goes
#: stale in the control task after ``[motors] command_ttl_s``.)
PAGE_SILENCE_S: Final = 3.0
#: How often the watch over a running calibration looks at its reasons to stop, and how
#: often the lidar facade looks for a new revolution (a revolution takes ~0.1 s or more).
WATCH_PERIOD_S: Final = 0.05
WATCH_STEP_MAX_S: Final = 2 * WATCH_PERIOD_S
LIDAR_POLL_S: Final = 0.02

RunStatus = Literal["running", "done", "failed", "stopped", "written"]


class CalibrationStopped(CalibrationError):
    """The calibration was stopped from outside the routine: the message says by what."""


@dataclass(frozen=True)
class _Reading:
    left_ticks: int
    right_ticks: int


class DaemonDevices:
    """Motors, encoders and lidar for the :class:`~mazebot.calibration.routine.Calibrator`,
    through the daemon's shared state (module docstring).

    ``why_stop()`` returns a reason to stop (or None); every throttle asked for checks it
    first, so no motion is commanded after a reason appeared.
    """

    def __init__(self, state: SharedState, clock: Clock, why_stop: Any) -> None:
        self.motors = _Motors(state, clock, why_stop)
        self.encoders = _Encoders(state)
        self.lidar = _Lidar(state, clock)


class _Motors:
    def __init__(self, state: SharedState, clock: Clock, why_stop: Any) -> None:
        self._state, self._clock, self._why_stop = state, clock, why_stop

    def set(self, left: float, right: float) -> None:
        if (reason := self._why_stop()) is not None:
            self._state.jog_command = None
            raise CalibrationStopped(reason)
        self._state.jog_command = (float(left), float(right), self._clock.now_s())

    def stop(self) -> None:
        self._state.jog_command = None


class _Encoders:
    def __init__(self, state: SharedState) -> None:
        self._state = state

    def read(self) -> _Reading:
        ticks = self._state.wheel_ticks
        if ticks is None:
            raise CalibrationError("no encoder reading yet: the odometry task has not run")
        return _Reading(ticks[1], ticks[2])


class _Lidar:
    def __init__(self, state: SharedState, clock: Clock) -> None:
        self._state, self._clock = state, clock

    async def scans(self) -> AsyncIterator[Scan]:
        """Every revolution the lidar task publishes from now on, once each."""
        last = self._state.latest_scan
        while True:
            scan = self._state.latest_scan
            if scan is not None and scan is not last:
                last = scan
                yield scan
            await self._clock.sleep(LIDAR_POLL_S)


@dataclass
class CalibrationRun:
    """One calibration started from the page: its steps, and once done, the result and the diff."""

    id: str
    progress: Progress
    run_state: RunState  # the robot's run state when it started: any change stops it
    status: RunStatus = "running"
    silent_s: float = 0.0  # since the page's last poll, in watch periods that ran (PAGE_SILENCE_S)
    reason: str = ""  # why it failed or stopped; where it was written
    stop_request: str | None = None
    diff: list[tuple[str, Any, Any]] = field(default_factory=list)
    new_config: Config | None = None
    result: Any = None
    report_png: bytes | None = None
    written_to: str | None = None
    backup: str | None = None

    def as_json(self) -> dict[str, Any]:
        failed = next((s.name for s in self.progress.steps if s.state == "failed"), None)
        running = next((s.name for s in self.progress.steps if s.state == "running"), None)
        return {
            "id": self.id,
            "status": self.status,
            "reason": self.reason,
            "current_step": running,
            "failed_step": failed,
            "steps": self.progress.as_json(),
            "diff": [{"key": k, "old": old, "new": new} for k, old, new in self.diff],
            "written_to": self.written_to,
            "backup": self.backup,
        }


class PageCalibration:
    """At most one calibration at a time on the daemon's devices, for the setup page (module docstring).

    ``config_path`` is the file a confirmed result replaces (``./config.toml`` when the
    daemon runs on the defaults, as ``mazebot calibrate --write`` does); ``sim`` says the
    robot is the simulator's (its ``[sim]`` keys then keep describing the same true robot);
    ``report_dir`` receives the report (JSON + PNG) with a confirmed result.
    """

    def __init__(self, state: SharedState, config: Config, config_path: Path | None, *, sim: bool,
                 report_dir: Path | None = None, clock: Clock | None = None) -> None:
        self.state = state
        self.config = config
        self.config_path = config_path
        self.sim = sim
        self.report_dir = report_dir
        self.clock = clock or RealClock()
        self.run: CalibrationRun | None = None
        self._task: asyncio.Task[None] | None = None

    @property
    def running(self) -> bool:
        return self.run is not None and self.run.status == "running"

    def refusal(self) -> str | None:
        """Why a calibration cannot start now; None when it can."""
        state = self.state
        if self.running:
            return "a calibration is already running"
        if state.stopping:
            return "the daemon is stopping"
        if state.run_state.moving:
            return f"the robot is {state.run_state.value}: stop the run before calibrating"
        if state.run_state is RunState.FAULT:
            fault = state.active_fault
            return f"a fault is active ({fault.message if fault else 'unknown'}): clear it before calibrating"
        jog = state.jog_command
        if jog is not None and 0.0 <= self.clock.now_s() - jog[2] <= self.config.motors.command_ttl_s:
            return "a jog button is held: release it before calibrating"
        return None

    def start(self) -> CalibrationRun:
        """Begin a calibration (the caller checked :meth:`refusal`); returns it at once, running."""
        from mazebot.calibration.routine import STEPS

        assert self.refusal() is None
        run = CalibrationRun(secrets.token_urlsafe(12), Progress(STEPS), self.state.run_state)
        self.run = run
        self.state.calibrating = True
        self._task = asyncio.create_task(self._calibrate(run), name="calibration")
        log.info("calibration started from the page")
        return run

    def seen(self, run_id: str | None) -> CalibrationRun | None:
        """The page that started ``run_id`` is still there (its poll); returns the run it names."""
        run = self.run
        if run is None or run_id != run.id:
            return None
        run.silent_s = 0.0
        return run

    def stop(self, reason: str) -> bool:
        """Ask a running calibration to stop (motors at once); False if none runs."""
        if not self.running:
            return False
        assert self.run is not None
        self.state.jog_command = None
        self.run.stop_request = reason
        return True

    def why_stop(self, run: CalibrationRun) -> str | None:
        """A reason for ``run`` to stop now, or None."""
        state = self.state
        if run.stop_request is not None:
            return run.stop_request
        if state.stopping:
            return "the daemon is stopping"
        if state.run_state is not run.run_state:
            if state.run_state is RunState.FAULT and state.active_fault is not None:
                return f"a fault: {state.active_fault.message}"
            return f"the robot went from {run.run_state.value} to {state.run_state.value} (start or stop pressed)"
        if run.silent_s > PAGE_SILENCE_S:
            return f"the page was not heard from for {run.silent_s:.1f} s (lost connection?)"
        return None

    async def _calibrate(self, run: CalibrationRun) -> None:
        from mazebot.calibration.result import calibrated_config, config_diff, report_png
        from mazebot.calibration.routine import Calibrator

        devices = DaemonDevices(self.state, self.clock, lambda: self.why_stop(run))
        routine = asyncio.create_task(Calibrator(devices, self.config, self.clock, run.progress).run(),
                                      name="calibration-routine")
        try:
            watched_s = self.clock.now_s()
            while not routine.done():
                now_s = self.clock.now_s()
                run.silent_s += min(max(0.0, now_s - watched_s), WATCH_STEP_MAX_S)
                watched_s = now_s
                reason = self.why_stop(run)
                if reason is not None:
                    self.state.jog_command = None
                    routine.cancel()
                    with contextlib.suppress(asyncio.CancelledError, Exception):
                        await routine
                    self._finish(run, "stopped", reason)
                    return
                await asyncio.wait({routine}, timeout=WATCH_PERIOD_S)
            try:
                result = routine.result()
            except CalibrationError as error:  # a step could not measure, or was stopped (CalibrationStopped)
                reason = self.why_stop(run)
                if reason is not None:
                    self._finish(run, "stopped", reason)
                else:
                    self._finish(run, "failed", str(error))
                return
            except Exception as error:  # a bug: the robot must still stop, and the page hear of it
                log.exception("calibration crashed")
                self._finish(run, "failed", f"calibration crashed: {type(error).__name__}: {error}")
                return
            run.result = result
            run.new_config = calibrated_config(self.config, result)
            run.diff = config_diff(self.config, run.new_config)
            run.report_png = report_png(result)
            self._finish(run, "done", "" if run.diff else "no changes: the config matches the robot")
        finally:
            self.state.jog_command = None
            self.state.calibrating = False
            if not routine.done():  # this task itself was cancelled (the daemon stops)
                routine.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await routine
                self._finish(run, "stopped", "the daemon is stopping")

    def _finish(self, run: CalibrationRun, status: RunStatus, reason: str) -> None:
        self.state.jog_command = None
        self.state.calibrating = False
        if run.status != "running":
            return
        run.status, run.reason = status, reason
        if status == "stopped":  # the step it stopped in says why (the routine only knows it was interrupted)
            for step in run.progress.steps:
                if step.state in ("running", "failed"):
                    step.state, step.detail = "failed", f"stopped: {reason}"
        log.info("calibration %s%s", status, f": {reason}" if reason else "")

    def write(self, run_id: str | None) -> CalibrationRun:
        """Write the confirmed result (``run_id`` must be the finished run's): the report and a copy of
        the new config in ``report_dir/calibration``, then the config file atomically with a backup.
        CalibrationError when there is nothing to write, or when the config file cannot be written
        (under the systemd unit ``/etc/mazebot`` is read-only to the daemon): the message names the
        copy and the command that installs it."""
        from mazebot.calibration.result import config_to_write, report_json, write_calibrated_config
        from mazebot.config import render_toml
        from mazebot.files import write_atomic

        run = self.run
        if run is None or run.id != run_id:
            raise CalibrationError("no such calibration: start one first")
        if run.status == "written":
            raise CalibrationError(f"already written to {run.written_to}")
        if run.status != "done" or run.new_config is None:
            raise CalibrationError(f"the calibration {run.status}: there is nothing to write")
        target = (self.config_path or Path("config.toml")).absolute()
        copy = None
        if self.report_dir is not None:
            report = self.report_dir / "calibration"
            write_atomic(report / "calibration.json", report_json(run.result, run.diff, run.progress.as_json()))
            write_atomic(report / "calibration.png", run.report_png or b"")
            copy = write_atomic(report / "config.toml",
                                render_toml(config_to_write(self.config, run.new_config, sim=self.sim)).encode())
        try:
            backup = write_calibrated_config(target, self.config, run.new_config, sim=self.sim)
        except OSError as error:
            where = "" if copy is None else (
                f"; the calibrated config is in {copy}: install it with "
                f"`sudo cp -b --suffix=.bak {copy} {target}` and restart mazebot")
            raise CalibrationError(f"cannot write {target} ({error.strerror or error}){where}") from None
        run.status, run.written_to = "written", str(target)
        run.backup = None if backup is None else str(backup)
        run.reason = f"written to {target}: restart mazebot to drive with it"
        log.info("calibrated config written to %s (the old one: %s)", target, backup)
        return run

    async def close(self) -> None:
        """Stop a running calibration and wait for it (the daemon is stopping)."""
        self.stop("the daemon is stopping")
        if self._task is not None:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._task
        self.state.jog_command = None
