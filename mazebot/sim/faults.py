"""Faults a real robot meets, injected into the simulated world at a chosen time.

Every fault acts where the world meets the robot's software, never on the daemon's
state: the lidar emulator's serial line (unplugged, silent, noisy, a sick device), the
gpiozero mock pins of the encoders, the fake motor HAT's I²C writes, the physics (a
slipping tyre, a weak motor, someone picking the robot up), and, for the compute
faults, the SLAM object, its executor and the event loop themselves. The real drivers
and tasks then see what they would see on the robot, and have to cope.

``mazebot bench --faults lidar-unplug@20 kidnap@45`` and the tests use the same
catalogue (:data:`FAULTS`): ``NAME`` alone is injected at :data:`DEFAULT_AT_S` simulated
seconds after the daemon started, ``NAME@T`` at ``T``.

Example::

    injector = FaultInjector([parse_fault("lidar-unplug@20")], robot, clock, seed=1)
    supervisor.start("faults", injector.run)     # injector.injections says what happened when
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import math
import random
import time
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass, field, replace
from typing import Any

from mazebot.clock import Clock
from mazebot.errors import UsageError

log = logging.getLogger(__name__)

#: When a fault named without ``@T`` is injected (simulated seconds after the start).
DEFAULT_AT_S = 20.0
#: How far and how much the robot is turned when it is kidnapped.
KIDNAP_M = 0.2
KIDNAP_RAD = math.radians(20.0)
#: The fault suite's targets (docs/design.md): a fault that needs the wheels stopped is noticed
#: within this long of its start, and the motors are at zero within this long of that.
DETECTED_MAX_MS = 500.0
MOTORS_ZERO_MAX_MS = 200.0


@dataclass(frozen=True)
class FaultKind:
    """One kind of fault: what it does, for how long, and what the daemon must do about it.

    ``must_stop``: afterwards the robot no longer knows where it is or what is in front of
    it, so its motors must be at zero within 200 ms of the detection. ``sources``: the
    ``/api/status`` fault or event sources that report it. ``duration_s`` 0 is a one-shot.
    """

    name: str
    what: str
    duration_s: float
    must_stop: bool
    sources: tuple[str, ...]
    begin: Callable[[FaultContext], None]
    end: Callable[[FaultContext], None] | None = None


@dataclass(frozen=True)
class FaultSpec:
    """A fault to inject and when (simulated seconds after the daemon started)."""

    name: str
    at_s: float = DEFAULT_AT_S

    def __str__(self) -> str:
        return f"{self.name}@{self.at_s:g}"


@dataclass
class Injection:
    """What was injected, and the true clock times it began and ended (None: not yet)."""

    spec: FaultSpec
    kind: FaultKind
    begin_s: float | None = None
    end_s: float | None = None
    detail: str = ""


@dataclass
class FaultContext:
    """What a fault can reach: the simulated robot, the clock, a random source, compute."""

    robot: Any  # mazebot.sim.robot.SimulatedRobot
    clock: Clock
    rng: random.Random
    slam: Any = None  # the daemon's Slam (compute faults)
    #: how many of SLAM's next updates fail (``slam-raise``; :meth:`FaultInjector.before_slam_update`)
    slam_updates_to_fail: int = 0
    executor: SlowableExecutor | None = None
    injection: Injection | None = None  # the one being applied (a fault may fill in ``detail``)
    saved: dict[str, Any] = field(default_factory=dict)  # what ``end`` must put back


# --- the lidar ------------------------------------------------------------------------


def _emulator(ctx: FaultContext) -> Any:
    return ctx.robot.lidar_line.emulator


def _unplug(ctx: FaultContext) -> None:
    ctx.robot.lidar_line.unplug()


def _replug(ctx: FaultContext) -> None:
    ctx.robot.lidar_line.replug()


def _freeze(ctx: FaultContext) -> None:
    _emulator(ctx).frozen = True


def _thaw(ctx: FaultContext) -> None:
    _emulator(ctx).frozen = False


def _noise_bursts(ctx: FaultContext) -> None:
    rng = ctx.rng

    def burst(data: bytes) -> bytes:
        if rng.random() >= 0.3:  # a burst in about one 20 ms batch of three
            return data
        junk = bytes(rng.getrandbits(8) for _ in range(rng.randint(8, 96)))
        at = rng.randint(0, len(data))
        return data[:at] + junk + data[at:]

    _emulator(ctx).line_filter = burst


def _bit_flips(ctx: FaultContext) -> None:
    rng = ctx.rng

    def flip(data: bytes) -> bytes:
        out = bytearray(data)
        for k in range(len(out)):
            if rng.random() < 1 / 200:  # one byte in 200 gets one bit flipped
                out[k] ^= 1 << rng.randrange(8)
        return bytes(out)

    _emulator(ctx).line_filter = flip


def _clean_line(ctx: FaultContext) -> None:
    _emulator(ctx).line_filter = None


def _truncated_descriptor(ctx: FaultContext) -> None:
    # The device core restarts by itself (a brown-out): it stops streaming, and the first
    # descriptor it sends afterwards is cut short after 4 of its 7 bytes.
    emulator = _emulator(ctx)
    emulator.mode = None
    emulator.truncate_next_descriptor = 4


def _health_error(ctx: FaultContext) -> None:
    _emulator(ctx).protection_stop()


def _jam_motor(ctx: FaultContext) -> None:
    _emulator(ctx).motor_jammed = True


def _free_motor(ctx: FaultContext) -> None:
    _emulator(ctx).motor_jammed = False


# --- encoders, motors, wheels ---------------------------------------------------------


def _bounce(ctx: FaultContext) -> None:
    for signal in (ctx.robot.left_signal, ctx.robot.right_signal):
        signal.rng = ctx.rng
        signal.bounce_probability = 0.05
        signal.lost_edge_probability = 0.01


def _no_bounce(ctx: FaultContext) -> None:
    for signal in (ctx.robot.left_signal, ctx.robot.right_signal):
        signal.bounce_probability = signal.lost_edge_probability = 0.0


def _cut_left_encoder(ctx: FaultContext) -> None:
    ctx.robot.left_signal.dead = True


def _mend_left_encoder(ctx: FaultContext) -> None:
    ctx.robot.left_signal.dead = False


def _slip_left(ctx: FaultContext) -> None:
    ctx.robot.physics.grip = (0.4, 1.0)


def _grip(ctx: FaultContext) -> None:
    ctx.robot.physics.grip = (1.0, 1.0)


def _i2c_errors(ctx: FaultContext) -> None:
    motors = ctx.robot.config.motors
    ctx.robot.kit.fail_writes([motors.left_channel, motors.right_channel], probability=0.5, rng=ctx.rng)


def _i2c_heal(ctx: FaultContext) -> None:
    ctx.robot.kit.heal()


def _weak_left_motor(ctx: FaultContext) -> None:
    physics = ctx.robot.physics
    ctx.saved["params"] = physics.params
    physics.params = replace(physics.params, gain_left=physics.params.gain_left * 0.4)


def _restore_params(ctx: FaultContext) -> None:
    ctx.robot.physics.params = ctx.saved.pop("params")


def _kidnap(ctx: FaultContext) -> None:
    """Pick the robot up and put it down 0.2 m away, turned by 20°, where its footprint fits.

    Its wheels turn on meanwhile, so it rolls on from where it is put down until the daemon
    notices and stops it. A place is taken only if that roll, at the robot's speed for the
    time the daemon is given (:data:`DETECTED_MAX_MS` + :data:`MOTORS_ZERO_MAX_MS`), stays clear:
    put down facing a wall 1 cm away it touched the wall 60 ms later, a contact no daemon can
    avoid. Where no place has that room, the first where the footprint fits.
    """
    physics = ctx.robot.physics
    x, y, theta = physics.pose
    need_m = physics.params.footprint_radius_m + 0.01
    turn = 0.0
    fits: list[tuple[float, float, float]] = []  # (direction, x, y) where the footprint fits
    for k in range(32):  # along the heading first, then every direction in turn
        step = (k + 1) // 2 * (1 if k % 2 else -1)
        direction = theta + step * (math.tau / 32)
        nx, ny = x + KIDNAP_M * math.cos(direction), y + KIDNAP_M * math.sin(direction)
        if physics.clearance_m(nx, ny) >= need_m and _line_clear(physics, (x, y), (nx, ny), need_m - 0.01):
            if not fits:
                turn = KIDNAP_RAD if ctx.rng.random() < 0.5 else -KIDNAP_RAD
            fits.append((direction, nx, ny))
            if _room_to_roll(physics, nx, ny, theta + turn, need_m):
                break
    else:  # no place with room to roll: the first where the footprint fits
        fits = fits[:1]
    if not fits:
        raise RuntimeError(f"nowhere to put the robot {KIDNAP_M} m from ({x:.2f}, {y:.2f})")
    direction, nx, ny = fits[-1]
    physics.teleport(nx, ny, theta + turn)
    if ctx.injection is not None:
        ctx.injection.detail = (
            f"moved {KIDNAP_M} m towards {math.degrees(direction):.0f}°, turned {math.degrees(turn):+.0f}°"
        )


def _room_to_roll(physics: Any, x_m: float, y_m: float, heading_rad: float, need_m: float) -> bool:
    """The robot put down at (x, y) facing ``heading_rad`` rolls on at its speed, clear of every wall,
    for as long as the daemon is given to notice and stop it."""
    speed_mps, _ = physics.body_velocity
    roll_m = speed_mps * (DETECTED_MAX_MS + MOTORS_ZERO_MAX_MS) / 1000.0
    end = (x_m + roll_m * math.cos(heading_rad), y_m + roll_m * math.sin(heading_rad))
    return physics.clearance_m(*end) >= need_m and _line_clear(physics, (x_m, y_m), end, need_m - 0.01)


def _line_clear(physics: Any, a: tuple[float, float], b: tuple[float, float], radius_m: float) -> bool:
    """The robot could have been carried along the floor from a to b (no wall in between)."""
    return all(
        physics.clearance_m(a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1])) >= radius_m
        for f in (0.25, 0.5, 0.75)
    )


# --- compute --------------------------------------------------------------------------


class InjectedFault(RuntimeError):
    """The failure a compute fault makes happen."""


def _slam_raises(ctx: FaultContext) -> None:
    slam = ctx.slam
    if slam is None or slam.before_update is None:
        raise RuntimeError(
            "slam-raise needs the daemon's Slam with the injector's seam "
            "(run_daemon(instrument=FaultInjector.instrument))"
        )
    ctx.slam_updates_to_fail = 1  # the next update fails, the one after is processed normally


def _slow_job(ctx: FaultContext) -> None:
    if ctx.executor is None:
        raise RuntimeError("executor-slow needs the daemon's executor (FaultInjector.instrument)")
    ctx.executor.slow_next(2.0, ctx.injection)


def _loop_stall(ctx: FaultContext) -> None:
    loop = asyncio.get_running_loop()

    def stall() -> None:
        advance = getattr(loop, "advance", None)
        if advance is not None:  # virtual time: half a second passes with nothing running
            advance(0.5)
        else:  # a real loop: something blocks it
            time.sleep(0.5)

    loop.call_soon(stall)


class SlowableExecutor(Executor):
    """The daemon's executor, with a way to make its next job take ``delay_s`` longer.

    The delay is counted on the event loop's clock (virtual or real), from the job's
    submission, so on a virtual-time run the job also "takes" two simulated seconds.
    """

    def __init__(self, inner: Executor, loop: asyncio.AbstractEventLoop) -> None:
        self._inner = inner
        self._loop = loop
        self._slow: tuple[float, Injection | None] | None = None

    def slow_next(self, delay_s: float, injection: Injection | None = None) -> None:
        self._slow = (delay_s, injection)

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> concurrent.futures.Future[Any]:
        inner = self._inner.submit(fn, *args, **kwargs)
        if self._slow is None:
            return inner
        delay_s, injection = self._slow
        self._slow = None
        submitted_s = self._loop.time()
        if injection is not None:  # the fault happens now, to this job
            injection.begin_s = submitted_s
            injection.detail = f"a {getattr(fn, '__qualname__', 'job')} held back {delay_s:g} s"
        outer: concurrent.futures.Future[Any] = concurrent.futures.Future()

        def settle() -> None:
            if injection is not None:
                injection.end_s = self._loop.time()
            if inner.cancelled():
                outer.cancel()
            elif inner.exception() is not None:
                outer.set_exception(inner.exception())
            else:
                outer.set_result(inner.result())

        def finished(_: concurrent.futures.Future[Any]) -> None:
            def later() -> None:
                remaining_s = submitted_s + delay_s - self._loop.time()
                self._loop.call_later(max(0.0, remaining_s), settle)

            self._loop.call_soon_threadsafe(later)

        inner.add_done_callback(finished)
        return outer

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self._inner.shutdown(wait=wait, cancel_futures=cancel_futures)


# --- the catalogue --------------------------------------------------------------------

FAULTS: dict[str, FaultKind] = {
    k.name: k
    for k in (
        FaultKind("lidar-unplug", "the lidar's USB cable is pulled out and put back 2 s later", 2.0, True,
                  ("lidar",), _unplug, _replug),
        FaultKind("lidar-stall", "the lidar sends no byte and answers nothing for 1.5 s", 1.5, True,
                  ("lidar",), _freeze, _thaw),
        FaultKind("lidar-noise", "bursts of random bytes on the lidar's line for 2 s", 2.0, False,
                  ("lidar",), _noise_bursts, _clean_line),
        FaultKind("lidar-bitflip", "one byte in 200 from the lidar has a bit flipped, for 2 s", 2.0, False,
                  ("lidar",), _bit_flips, _clean_line),
        FaultKind("lidar-truncated-descriptor", "the lidar's core restarts; its next descriptor is cut short",
                  0.0, True, ("lidar",), _truncated_descriptor),
        FaultKind("lidar-health-error", "the lidar reports health status \"error\" and stops scanning",
                  0.0, True, ("lidar",), _health_error),
        FaultKind("lidar-motor-stop", "the lidar's motor stops for 2 s", 2.0, True, ("lidar",),
                  _jam_motor, _free_motor),
        FaultKind("encoder-bounce", "both encoders bounce and lose edges (impossible transitions) for 3 s",
                  3.0, False, ("encoders",), _bounce, _no_bounce),
        FaultKind("encoder-dead", "the left encoder's cable is cut for 3 s", 3.0, True, ("encoders",),
                  _cut_left_encoder, _mend_left_encoder),
        FaultKind("wheel-slip", "the left tyre keeps only 40 % of its grip for 3 s", 3.0, False,
                  ("odometry", "localization"), _slip_left, _grip),
        FaultKind("motor-i2c", "half the throttle writes to the motor HAT fail with OSError for 1.5 s",
                  1.5, True, ("motors",), _i2c_errors, _i2c_heal),
        FaultKind("motor-weak", "the left motor gives 40 % of its speed for 10 s", 10.0, False,
                  ("motors",), _weak_left_motor, _restore_params),
        FaultKind("slam-raise", "one SLAM update raises", 0.0, True, ("slam",), _slam_raises),
        FaultKind("executor-slow", "the next executor job (a loop closure) takes 2 s more", 0.0, False,
                  ("slam",), _slow_job),
        FaultKind("loop-stall", "the event loop is blocked for 500 ms", 0.0, True, ("control",), _loop_stall),
        FaultKind("kidnap", "the robot is picked up and put down 0.2 m away, turned by 20°", 0.0, True,
                  ("localization",), _kidnap),
    )
}


def parse_fault(text: str) -> FaultSpec:
    """``NAME`` or ``NAME@T`` (T simulated seconds after the start) -> FaultSpec; UsageError if bad."""
    name, _, at = text.partition("@")
    if name not in FAULTS:
        raise UsageError(f"unknown fault {name!r}; known faults: {', '.join(FAULTS)}")
    if not at:
        return FaultSpec(name)
    try:
        at_s = float(at)
    except ValueError:
        raise UsageError(f"fault {text!r}: the time after @ must be seconds, got {at!r}") from None
    if not (math.isfinite(at_s) and at_s >= 0):
        raise UsageError(f"fault {text!r}: the time after @ must be >= 0 s")
    return FaultSpec(name, at_s)


class FaultInjector:
    """Applies faults to a simulated robot at their times; ``injections`` is the ground truth.

    ``instrument(slam, executor)`` (the ``run_daemon`` hook) lets the compute faults reach
    SLAM and its executor: it puts :meth:`before_slam_update` in the Slam's fault seam
    (``before_update``) and returns the executor the daemon must use.
    """

    def __init__(self, specs: list[FaultSpec], robot: Any, clock: Clock, *, seed: int = 0) -> None:
        self.injections = [Injection(spec, FAULTS[spec.name]) for spec in sorted(specs, key=lambda s: s.at_s)]
        self.ctx = FaultContext(robot, clock, random.Random(seed))
        self.start_s: float | None = None
        #: called just before each fault begins (the benchmark keeps the map as it was)
        self.on_begin: Callable[[Injection], None] | None = None

    def instrument(self, slam: Any, executor: Executor) -> Executor:
        slam.before_update = self.before_slam_update
        self.ctx.slam = slam
        self.ctx.executor = SlowableExecutor(executor, asyncio.get_running_loop())
        return self.ctx.executor

    def before_slam_update(self, scan: Any) -> None:
        """SLAM's fault seam (:class:`mazebot.slam.slam.Slam`'s ``before_update``): ``slam-raise``'s failure.

        Raises :class:`InjectedFault` in the update after the fault began, as a bug in one of
        SLAM's stages would; the SLAM task must skip that revolution and go on.
        """
        if self.ctx.slam_updates_to_fail > 0:
            self.ctx.slam_updates_to_fail -= 1
            raise InjectedFault("injected: a SLAM update failed")

    async def run(self) -> None:
        """The injector task: each fault at its time, and its end ``duration_s`` later."""
        clock = self.ctx.clock
        self.start_s = clock.now_s() if self.start_s is None else self.start_s
        pending: list[tuple[float, int, Injection, bool]] = [
            (self.start_s + inj.spec.at_s, k, inj, True) for k, inj in enumerate(self.injections)
        ]
        while pending:
            pending.sort(key=lambda p: (p[0], p[1]))
            due_s, k, inj, beginning = pending.pop(0)
            await clock.sleep(due_s - clock.now_s())
            # the robot must be where the clock says before the world changes under it
            self.ctx.robot.step(clock.now_s())
            self.ctx.injection = inj
            if beginning:
                if self.on_begin is not None:
                    self.on_begin(inj)
                deferred = inj.kind.name == "executor-slow"  # begins when the next job is submitted
                if not deferred:
                    inj.begin_s = clock.now_s()
                inj.kind.begin(self.ctx)
                log.warning("fault injected: %s (%s)", inj.kind.name, inj.kind.what)
                if inj.kind.end is not None:
                    pending.append((clock.now_s() + inj.kind.duration_s, k, inj, False))
                elif not deferred:
                    inj.end_s = inj.begin_s
            else:
                assert inj.kind.end is not None
                inj.kind.end(self.ctx)
                inj.end_s = clock.now_s()
                log.warning("fault ended: %s", inj.kind.name)
