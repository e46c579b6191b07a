"""The daemon: build config, backends and shared state, run every task in one loop.

``mazebot run`` on the robot opens the real devices (motor HAT first, so the wheels can
always be stopped, then GPIO, then the lidar); ``mazebot run --sim`` puts the same task
code on a simulated robot whose devices speak the same protocols. Start-up order and
shutdown order are owned here: motors stop in ``finally`` blocks, never in ``__del__``.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import gc
import importlib
import logging
import signal
import time
from collections.abc import Awaitable, Callable, Iterator
from concurrent.futures import Executor
from contextlib import AsyncExitStack
from pathlib import Path
from typing import TYPE_CHECKING, Protocol, cast

from mazebot import sdnotify
from mazebot.clock import Clock, RealClock
from mazebot.config import Config
from mazebot.cpu_budget import garbage_collection_metered
from mazebot.errors import EXIT_OK, HardwareUnavailable
from mazebot.fork_server import FORKSERVER_PRELOAD, start_fork_server_here
from mazebot.hardware import Hardware, HardwareBuilder, LidarActivity, lgpio_pin_factory
from mazebot.malloc_tuning import fix_mmap_threshold
from mazebot.sdnotify import ControlHeartbeat
from mazebot.state import SharedState
from mazebot.tasks.supervisor import Supervisor

if TYPE_CHECKING:
    from aiohttp.web import AppRunner
    from gpiozero import Factory

    from mazebot.io.motor_hat import MotorKitLike
    from mazebot.io.serial_link import SerialLink
    from mazebot.record.foxglove_live import FoxgloveLive
    from mazebot.slam.slam import Slam, SlamParams

log = logging.getLogger("mazebot")


class Session(Protocol):
    """What the daemon asks of a run session (:class:`mazebot.run_session.RunSession`: record, save, resume).

    A protocol rather than the class: the session sits beside the daemon in the import layers,
    and either may change without the other importing it.
    """

    @property
    def resume(self) -> object | None:
        """The saved run this one continues, if any."""

    def open(self, config: Config, clock: Clock, state: SharedState, hardware: Hardware,
             stack: AsyncExitStack) -> Hardware:
        """The hardware with the session's recording taps in front of it."""

    def make_slam(self, params: SlamParams) -> Slam:
        """The daemon's SLAM: fresh, or the saved run's."""

    def start_tasks(self, config: Config, clock: Clock, state: SharedState, supervisor: Supervisor,
                    slam: Slam) -> None:
        """The session's own tasks (recording, saving)."""


#: ``run_daemon``'s hook on SLAM's compute: given the daemon's Slam and executor, the executor to use.
Instrument = Callable[["Slam", Executor], Executor]


def robot_hardware_builder(
    open_kit: Callable[[int, float], MotorKitLike] | None = None,
    make_pin_factory: Callable[[], Factory] = lgpio_pin_factory,
) -> HardwareBuilder:
    """The real robot's devices, opened in the order that keeps the wheels stoppable.

    Motor HAT first, and zeroed at once (a PCA9685 keeps its last PWM after the process
    that set it died), then GPIO for the encoders, then the lidar, which must answer
    GET_HEALTH. Any missing device raises HardwareUnavailable naming it (exit 69); the
    devices already open are closed, the motors braked, before the error leaves.
    ``open_kit`` and ``make_pin_factory`` stand in for ``MotorKit`` and lgpio in tests.
    """

    async def build(config: Config, clock: Clock, stack: AsyncExitStack) -> Hardware:
        from mazebot.io.encoders import WheelEncoders
        from mazebot.io.motors import DifferentialMotors, open_motorkit
        from mazebot.io.rplidar import RPLidar
        from mazebot.io.serial_link import SerialLink

        kit: MotorKitLike
        if config.motors.backend == "gpio" and open_kit is None:
            from mazebot.io.motor_gpio import open_gpio_motorkit

            kit = open_gpio_motorkit(config.motors)  # braked as it opens
            stack.callback(kit.close)  # after the motors' own close (the stack runs last-in first-out)
        else:
            kit = (open_kit or open_motorkit)(config.motors.i2c_address, config.motors.pwm_frequency_hz)
        motors = DifferentialMotors.from_config(config.motors, kit, clock)
        stack.callback(motors.close)
        motors.stop()

        try:
            pin_factory = make_pin_factory()
        except Exception as exc:  # ImportError off a Pi, lgpio.error without /dev/gpiochip*, ...
            raise HardwareUnavailable(
                f"GPIO for the wheel encoders is not available ({type(exc).__name__}: {exc}); "
                "`mazebot run` needs a Raspberry Pi with lgpio, use `mazebot run --sim` elsewhere"
            ) from None
        stack.callback(pin_factory.close)
        enc = config.encoders
        try:
            encoders = WheelEncoders.from_config(enc, pin_factory)
        except Exception as exc:  # a pin in use by another program, or not on this board
            pins = "/".join(f"GPIO{p}" for p in (enc.left_a_pin, enc.left_b_pin, enc.right_a_pin, enc.right_b_pin))
            raise HardwareUnavailable(
                f"wheel encoder pins {pins} cannot be used ({type(exc).__name__}: {exc}); "
                "check [encoders] pins and that no other program holds them"
            ) from None
        stack.callback(encoders.close)

        # Open the port and ask for the health now, so a missing or silent lidar is
        # reported at start-up (exit 69), not as an endless reconnect loop.
        probe = await SerialLink.open(config.lidar.port, config.lidar.baudrate)
        lidar = RPLidar.from_config(config.lidar, clock, link_factory=_once(probe, config))
        await stack.enter_async_context(lidar)
        await lidar.stop()  # a lidar left scanning by a killed daemon answers nothing else
        await lidar.get_health()  # HardwareUnavailable, naming the port, when it stays silent
        opener = None
        if config.motors.backend == "motorkit" and open_kit is None:  # a second MotorKit on the same I2C HAT
            opener = functools.partial(open_motorkit, config.motors.i2c_address, config.motors.pwm_frequency_hz)
        return Hardware(
            lidar=lidar,
            encoders=encoders,
            motors=motors,
            motor_kit_opener=opener,
            description=f"robot: lidar on {config.lidar.port}, "
            + (f"motor H-bridge on GPIO {config.motors.gpio_motor1_pins} and {config.motors.gpio_motor2_pins}"
               if config.motors.backend == "gpio" else f"motor HAT at {config.motors.i2c_address:#04x}"),
        )

    return build


def _once(link: SerialLink, config: Config) -> Callable[[], Awaitable[SerialLink]]:
    """A link factory that hands out ``link`` first, then opens the port anew (reconnects)."""
    first = [link]

    async def factory() -> SerialLink:
        from mazebot.io.serial_link import SerialLink

        return first.pop() if first else await SerialLink.open(config.lidar.port, config.lidar.baudrate)

    return factory


async def open_robot_hardware(config: Config, clock: Clock, stack: AsyncExitStack) -> Hardware:
    """Open the real robot's devices (see :func:`robot_hardware_builder`)."""
    return await robot_hardware_builder()(config, clock, stack)


#: What ``run_daemon`` imports after the page is served: SLAM, planner and the tasks
#: (numpy, scipy; most of the start-up time).
_ROBOT_MODULES = (
    "mazebot.planner.pilot",
    "mazebot.slam.loop_worker",
    "mazebot.slam.odometry",
    "mazebot.slam.slam",
    "mazebot.tasks.command_task",
    "mazebot.tasks.control_task",
    "mazebot.tasks.health_task",
    "mazebot.tasks.lidar_task",
    "mazebot.tasks.odometry_task",
    "mazebot.tasks.planner_task",
    "mazebot.tasks.slam_task",
)


def _import_the_robot() -> None:
    for name in _ROBOT_MODULES:
        importlib.import_module(name)


@contextlib.contextmanager
def _start_up_objects_frozen() -> Iterator[None]:
    """Keep the ~100 000 objects of start-up (modules, config, tasks) out of every full collection.

    Python's cyclic garbage collector scans all tracked objects in a full (generation 2)
    collection, and it runs on the event loop's thread: with the web page churned by
    clients (hundreds of short connections a second), 11 full collections a minute of 57 ms
    each (max 77) were the longest stalls of the 20 Hz control tick (bench/web_bench.py
    --abuse, quiet machine). Objects alive at start-up live as long as the daemon, so
    scanning them again finds nothing: ``gc.freeze`` moves them to a generation that is
    never scanned. Unfrozen when the daemon ends, so a process that runs several daemons
    (the tests, the benchmarks) can still collect them.
    """
    gc.collect()  # garbage left from start-up is not frozen with the rest
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def _on_the_monotonic_clock(clock: Clock, loop: asyncio.AbstractEventLoop) -> bool:
    """Whether the daemon's clock is the wall's monotonic clock, which a thread can keep too
    (not the simulator's virtual time, where only the loop moves the clock)."""
    return isinstance(clock, RealClock) and abs(loop.time() - time.monotonic()) <= 0.5


def _guard_motors_from_a_thread(
    motors: object, clock: Clock, loop: asyncio.AbstractEventLoop, stack: AsyncExitStack
) -> None:
    """Brake from a thread when the event loop hangs (:class:`mazebot.io.motors.TtlGuard`).

    Only where the loop runs on the monotonic clock: a virtual-time loop's clock is not
    the wall clock, and there a hung loop lets no time pass either.
    """
    from mazebot.io.motors import DifferentialMotors, TtlGuard

    if not isinstance(motors, DifferentialMotors) or not _on_the_monotonic_clock(clock, loop):
        return
    guard = TtlGuard(motors)
    guard.start()
    stack.callback(guard.close)


def _start_foxglove(config: Config, stack: AsyncExitStack) -> FoxgloveLive | None:
    """The Foxglove live server when ``[foxglove] enabled`` (its SDK imported only then), else None."""
    if not config.foxglove.enabled:
        return None
    from mazebot.record.foxglove_live import FoxgloveLive, LiveLogHandler

    host = config.foxglove.host or config.web.host
    live = FoxgloveLive.start(host, config.foxglove.port)
    stack.callback(live.stop)
    handler = LiveLogHandler(live)
    logging.getLogger("mazebot").addHandler(handler)
    stack.callback(logging.getLogger("mazebot").removeHandler, handler)
    log.info("Foxglove live on ws://%s:%d/ (Foxglove: Open connection)", host, live.port)
    return live


async def run_daemon(
    config: Config,
    build_hardware: HardwareBuilder,
    *,
    clock: Clock | None = None,
    ready: asyncio.Event | None = None,
    install_signal_handlers: bool = True,
    serve_web: bool = True,
    state: SharedState | None = None,
    on_started: Callable[[Hardware, SharedState, Supervisor], None] | None = None,
    autonomous: bool = True,
    session: Session | None = None,
    instrument: Instrument | None = None,
    config_path: Path | None = None,
) -> int:
    """Run the whole robot until a signal (exit 0) or a fatal fault; return the exit code.

    ``on_started`` is called once every task runs (the benchmark adds its driver and
    recorder there); ``serve_web=False`` leaves the web server out (virtual-time runs);
    ``autonomous=False`` leaves the planner out (the benchmark's scripted tour drives).
    ``session`` (a :class:`mazebot.run_session.RunSession`) records, saves or resumes the run.
    ``instrument(slam, executor)`` is shown the daemon's :class:`Slam` before its first revolution
    and returns the executor SLAM is to use: the harness's one way to reach the compute (the fault
    injector sets the Slam's fault seam ``before_update`` there and slows its executor:
    :mod:`mazebot.sim.faults`; the benchmark listens on its taps). ``config_path`` is the file
    ``config`` came from: a calibration confirmed on the setup page replaces it.
    """
    clock = clock or RealClock()
    loop = asyncio.get_running_loop()
    state = state if state is not None else SharedState()
    fix_mmap_threshold()  # before the fork server starts: its children inherit the setting
    if config.slam.loop_closure_executor == "process":
        # forked from here while this process is one thread with no device open, so the modules
        # imported so far (numpy, pydantic, the config's models) are in memory once, not twice
        start_fork_server_here(FORKSERVER_PRELOAD)
    async with AsyncExitStack() as stack:
        live = _start_foxglove(config, stack)  # first: a missing package stops us before any device opens
        hardware = await build_hardware(config, clock, stack)
        _guard_motors_from_a_thread(hardware.motors, clock, loop, stack)
        if session is not None:  # the recording taps go in front of the devices
            hardware = session.open(config, clock, state, hardware, stack)
        motors = hardware.motors
        stack.callback(motors.stop)  # runs on every exit path, after the tasks are gone
        supervisor = Supervisor(state, motors, clock, exit_on_fault=config.daemon.exit_on_fault)
        if install_signal_handlers:
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(sig, supervisor.request_stop, f"signal {sig.name}")
                stack.callback(loop.remove_signal_handler, sig)
        for name, factory in hardware.extra_tasks:
            supervisor.start(name, factory)
        state.cpu.started_s = clock.now_s()
        state.scans = asyncio.Queue(maxsize=config.slam.scan_queue_size)
        web_started = False
        web_runner: AppRunner | None = None

        async def serve() -> None:
            nonlocal web_runner
            from mazebot.web.server import start_web_server  # aiohttp: ~0.3-1 s to import, unused by benchmarks

            web = await start_web_server(state, config, hardware, config_path)
            stack.push_async_callback(web.cleanup)
            web_runner = web
            log.info("%s; web page on http://%s:%d/", hardware.description, config.web.host, config.web.port)

        if serve_web and (session is None or session.resume is None):
            # The page first, the SLAM and planner imports (most of start-up) after: the motors
            # are open and zeroed already, and a start pressed meanwhile waits in the command
            # queue until the tasks that act on it run. (A resumed run serves its saved map from
            # the first answer on, so it starts the page once SLAM holds that map, below.)
            await serve()
            web_started = True
            # the imports run in a thread, so the loop serves the page meanwhile (a module being
            # imported there is locked for the others: https://docs.python.org/3/library/importlib.html)
            await asyncio.to_thread(_import_the_robot)
        from mazebot.planner.pilot import Pilot, PilotParams
        from mazebot.slam.loop_worker import LoopClosureExecutor
        from mazebot.slam.odometry import DiffDriveOdometry
        from mazebot.slam.slam import Slam, SlamParams
        from mazebot.tasks import (
            command_task,
            control_task,
            health_task,
            lidar_task,
            odometry_task,
            planner_task,
            slam_task,
        )
        from mazebot.tasks.health_task import HealthMonitor

        # loop closures (verification, pose-graph optimization, map rebuilds) run here, off the event loop
        slam_executor: Executor = LoopClosureExecutor(config.slam.loop_closure_executor, config.slam.loop_closure_nice)
        stack.callback(slam_executor.shutdown)
        state.auto_resume = config.daemon.auto_resume
        # what must survive a task's restart is built here, outside the tasks: the odometry
        # (the pose must not jump back to the origin), SLAM (the map), planner and control
        odometry = DiffDriveOdometry(
            config.encoders.ticks_per_rev, config.drive.wheel_diameter_m, config.drive.track_width_m,
            config.drive.wheel_diameter_ratio,
        )
        slam_params = SlamParams.from_config(config.slam, config.lidar, config.planner)
        if session is not None:  # recorded, saved or resumed
            slam = session.make_slam(slam_params)
        else:
            slam = Slam(slam_params, background=True, record_trajectory=False)
        if instrument is not None:
            slam_executor = instrument(slam, slam_executor)
        supervisor.start("lidar", lambda: lidar_task.run(hardware.lidar, state), restart=True)
        supervisor.start(
            "odometry",
            lambda: odometry_task.run(
                hardware.encoders, state, clock, config.encoders, config.drive, config.slam.odometry_history_s,
                odometry,
            ),
            restart=True,
        )
        supervisor.start("slam", lambda: slam_task.run(state, clock, slam_params, slam_executor, slam,
                                                        pause_behind=config.slam.loop_closure_pause_behind),
                         restart=True)
        # hasattr, not isinstance on the Protocol: the recording tap forwards the driver's names through
        # __getattr__, which Python 3.12's runtime protocol checks no longer look at
        has_bytes = hasattr(hardware.lidar, "bytes_waiting")  # the tests' fakes count no bytes
        lidar_activity = cast(LidarActivity, hardware.lidar) if has_bytes else None
        monitor = HealthMonitor(config.daemon.lidar_silence_s, config.daemon.startup_grace_s, lidar=lidar_activity,
                                wheel_gains=health_task.wheel_gains_from_config(config))
        # on the real clock the checks run in the odometry's wake-ups (health_task.run)
        beat_s = 1.0 / config.encoders.odometry_rate_hz if _on_the_monotonic_clock(clock, loop) else None
        supervisor.start("health", lambda: health_task.run(state, clock, monitor, beat_s), restart=True)
        heartbeat = ControlHeartbeat(clock)  # the control loop's ticks feed the systemd watchdog
        pilot = Pilot(PilotParams.from_config(config))
        if autonomous:
            supervisor.start("planner", lambda: planner_task.run(state, clock, pilot, state.planner_ms), restart=True)
        control = control_task.MotorControl.from_config(config)
        real_time = _on_the_monotonic_clock(clock, loop)
        if config.daemon.control_process and real_time and hardware.motor_kit_opener is not None:
            from mazebot.tasks import control_process

            link = control_process.ControlLink.create(config)
            stack.callback(link.close)  # after the tasks are gone (the stack runs last-in first-out)
            stack.callback(setattr, state, "control_link", None)
            state.control_link = link
            opener = hardware.motor_kit_opener
            supervisor.start(
                "control", lambda: control_process.run(link, motors, state, heartbeat, config, opener), restart=True
            )
        else:
            if config.daemon.control_process and real_time:
                log.info("the control loop runs on a thread: these motors can only be driven from this process")
            control_thread = config.daemon.control_thread and real_time
            supervisor.start(
                "control", lambda: control_task.run(motors, state, heartbeat, control, thread=control_thread),
                restart=True,
            )
        watchdog_s = sdnotify.watchdog_period_s()  # systemd's WatchdogSec, when it set one
        if watchdog_s is not None:
            silence_s = max(watchdog_s / 2, 10 * config.daemon.control_period_s)
            supervisor.start("watchdog", lambda: sdnotify.feed_watchdog(heartbeat, watchdog_s / 4, silence_s))
        supervisor.start("commands", lambda: command_task.run(state, motors, clock), restart=True)
        if session is not None:
            session.start_tasks(config, clock, state, supervisor, slam)
        if live is not None:
            from mazebot.tasks import foxglove_task

            fc, mount_xy_m = config.foxglove, config.lidar.mount_xy_m
            supervisor.start(
                "foxglove",
                lambda: foxglove_task.run(state, live, clock, fc.pose_hz, fc.map_period_s, mount_xy_m),
                restart=True,
            )
        if serve_web and not web_started:
            await serve()
        elif not serve_web:
            log.info("%s; no web page", hardware.description)
        if config.zenoh.enabled:
            _join_the_fleet(config, state, supervisor, web_runner, loop, stack)
        if on_started is not None:
            on_started(hardware, state, supervisor)
        if ready is not None:
            ready.set()
        # lidar, motors and web are up: tell systemd (Type=notify)
        sdnotify.notify(f"READY=1\nSTATUS={hardware.description}")
        try:
            with _start_up_objects_frozen(), garbage_collection_metered(state.cpu.part("garbage collection")):
                return await supervisor.wait()
        finally:
            sdnotify.notify("STOPPING=1")
    return EXIT_OK  # pragma: no cover - unreachable, keeps type checkers calm


def _join_the_fleet(config: Config, state: SharedState, supervisor: Supervisor, web_runner: AppRunner | None,
                    loop: asyncio.AbstractEventLoop, stack: AsyncExitStack) -> None:
    """Publish on Zenoh (``[zenoh]``, :mod:`mazebot.fleet.robot_link`): the page's packets from its own
    broadcaster and start/stop checked by its own PIN lockout; without a page, a broadcaster of its own."""
    from mazebot.fleet.robot_link import start_robot_link
    from mazebot.web.app import AUTH_KEY, BROADCASTER_KEY
    from mazebot.web.auth import ControlAuth
    from mazebot.web.broadcaster import Broadcaster
    from mazebot.web.server import control_token

    if web_runner is not None:
        broadcaster, auth = web_runner.app[BROADCASTER_KEY], web_runner.app[AUTH_KEY]
    else:
        web = config.web
        broadcaster = Broadcaster(state, rate_hz=web.broadcast_hz, resync_every=web.resync_every,
                                  heartbeat_s=web.heartbeat_s, trail_points=web.trail_points)
        auth = ControlAuth(control_token(config))
        supervisor.start("zenoh broadcast", broadcaster.run, restart=True)
    link = start_robot_link(config.zenoh, state, broadcaster, auth, loop)
    stack.callback(link.close)
    supervisor.start("zenoh", link.run, restart=True)
