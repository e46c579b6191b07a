"""The two drive motors on the Adafruit DC & Stepper Motor HAT, and a fake with a log.

The hardware boundary is an object shaped like ``adafruit_motorkit.MotorKit``:
``kit.motor1`` … ``kit.motor4``, each with a ``throttle`` in [-1, 1] (0 = brake, ``None``
= coast). :func:`open_motorkit` (in :mod:`mazebot.io.motor_hat`) builds the real one, importing
``adafruit_motorkit`` (and with it Blinka's ``board``, which fails off a Pi) only when called;
:class:`FakeMotorKit` is the same shape for tests and the simulator.
:class:`DifferentialMotors` is what the rest of mazebot drives: left/right throttles,
per-side channel and polarity, and the safety rules.

Safety rules, each a test:

* A throttle that is not refreshed within ``command_ttl_s`` becomes a brake: each
  :meth:`DifferentialMotors.set` re-arms a ``loop.call_later`` handle (one timer, no
  polling task to die silently), and a control loop can also call
  :meth:`DifferentialMotors.expire_stale` with the clock's time.
* A failed write (I²C error) never leaves the other motor running: both motors are
  commanded to brake, the error is counted and :class:`MotorWriteError` is raised so the
  supervisor can fault.
* Non-finite throttles (NaN, ±inf: an upstream bug) are treated as 0 and logged; finite
  ones are clamped to [-1, 1].
* The HAT keeps its last PWM output across process restarts, so
  :class:`DifferentialMotors` brakes both motors when it is created, and again in
  :meth:`~DifferentialMotors.close` (idempotent; use it as a context manager). Never in
  ``__del__``.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import math
import random
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Final, Literal, Self

from mazebot.clock import Clock
from mazebot.errors import EXIT_UNAVAILABLE, MazebotError
from mazebot.io.motor_hat import CHANNELS, MotorKitLike, MotorLike
from mazebot.io.motor_hat import open_motorkit as open_motorkit  # re-exported: main.py opens the HAT from here
from mazebot.motors_config import MotorsConfig
from mazebot.taps import notify

logger = logging.getLogger(__name__)

#: Throttle writes the fake remembers (the newest ones).
COMMAND_LOG_LENGTH: Final = 10_000

#: Tries of each brake write after a failed write (transient I²C errors).
BRAKE_ATTEMPTS: Final = 3

#: Slack when comparing clock times, so a check exactly one TTL later (virtual time,
#: float sums of periods) counts as expired rather than one tick late.
_TIME_EPSILON_S: Final = 1e-9

#: Log a non-finite throttle the first time and then once every this many times.
_NONFINITE_LOG_EVERY: Final = 100


class MotorWriteError(MazebotError):
    """A throttle write to the motor HAT failed (I²C error); both motors were told to brake.

    ``channel`` is the HAT terminal whose write failed, ``side`` "left"/"right",
    ``stopped`` whether the brake commands that followed all succeeded (if not, a
    motor may still be turning: cut power).
    """

    exit_code = EXIT_UNAVAILABLE

    def __init__(self, message: str, *, channel: int, side: str, stopped: bool) -> None:
        super().__init__(message)
        self.channel = channel
        self.side = side
        self.stopped = stopped


# --- the fake -----------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ThrottleWrite:
    """One successful throttle write seen by :class:`FakeMotorKit`."""

    time_s: float
    channel: int
    throttle: float | None


class FakeMotor:
    """One fake DC motor; writes go through its kit so they are logged (or fail)."""

    def __init__(self, kit: FakeMotorKit, channel: int) -> None:
        self._kit = kit
        self.channel = channel
        self._throttle: float | None = None

    @property
    def throttle(self) -> float | None:
        return self._throttle

    @throttle.setter
    def throttle(self, value: float | None) -> None:
        self._kit._write(self.channel, value)
        self._throttle = value


class FakeMotorKit:
    """Same shape as ``MotorKit``; records every write, and can be told to fail writes.

    Like adafruit_motor's ``DCMotor``, a throttle outside [-1, 1] raises ``ValueError``
    (so clamping bugs show up in tests). Motors start coasting (``None``).

    Test controls: :attr:`command_log` (successful writes, in order),
    :meth:`fail_writes` / :meth:`heal` (make writes raise ``OSError`` like a broken I²C
    bus), :attr:`failed_writes`.

    Example::

        kit = FakeMotorKit()
        kit.motor1.throttle = 0.5
        kit.command_log[-1].throttle   # 0.5
        kit.fail_writes(channels=[2])
        kit.motor2.throttle = 0.1      # raises OSError (EIO)
    """

    def __init__(self, clock: Clock | None = None) -> None:
        self._clock = clock
        # bounded: the simulator runs this fake for hours at 40 writes a second
        self.command_log: deque[ThrottleWrite] = deque(maxlen=COMMAND_LOG_LENGTH)
        self.failed_writes = 0
        self._failing: frozenset[int] = frozenset()
        self._failures_left: int | None = None
        self._fail_probability = 1.0
        self._rng: random.Random | None = None
        self._motors = {channel: FakeMotor(self, channel) for channel in CHANNELS}
        #: taps (:mod:`mazebot.taps`). ``before_write`` is called before every write (the simulator
        #: brings its world up to the moment of the write); each of ``on_write`` is given every
        #: successful write, as it reached the HAT (the benchmark's "motors zero"). Neither can
        #: stop a write: what they raise is logged and the write goes ahead.
        self.before_write: Callable[[], None] | None = None
        self.on_write: tuple[Callable[[ThrottleWrite], None], ...] = ()

    @property
    def motor1(self) -> FakeMotor:
        return self._motors[1]

    @property
    def motor2(self) -> FakeMotor:
        return self._motors[2]

    @property
    def motor3(self) -> FakeMotor:
        return self._motors[3]

    @property
    def motor4(self) -> FakeMotor:
        return self._motors[4]

    def throttles(self) -> dict[int, float | None]:
        """The current throttle of every channel."""
        return {channel: motor.throttle for channel, motor in self._motors.items()}

    def fail_writes(
        self,
        channels: Iterable[int] = CHANNELS,
        times: int | None = None,
        *,
        probability: float = 1.0,
        rng: random.Random | None = None,
    ) -> None:
        """Make writes to ``channels`` raise ``OSError``: the next ``times`` writes, or all.

        With ``probability`` < 1 each write fails only with that chance (drawn from
        ``rng``): a noisy bus rather than a HAT gone for good.
        """
        if not 0.0 < probability <= 1.0:
            raise ValueError(f"probability must be in (0, 1], got {probability!r}")
        self._failing = frozenset(channels)
        self._failures_left = times
        self._fail_probability = probability
        self._rng = rng or random.Random(0)

    def heal(self) -> None:
        """Stop failing writes."""
        self._failing = frozenset()
        self._failures_left = None
        self._fail_probability = 1.0

    def _write(self, channel: int, throttle: float | None) -> None:
        if throttle is not None and not -1.0 <= throttle <= 1.0:
            raise ValueError(f"throttle must be None or between -1.0 and +1.0, got {throttle}")
        if self.before_write is not None:
            try:
                self.before_write()
            except Exception:  # a motor write, a brake above all, must happen whatever a tap does
                logger.exception("the motor kit's before_write tap failed; writing motor%d anyway", channel)
        failing = channel in self._failing and self._failures_left != 0
        if failing and self._fail_probability < 1.0:
            assert self._rng is not None
            failing = self._rng.random() < self._fail_probability
        if failing:
            if self._failures_left is not None:
                self._failures_left -= 1
            self.failed_writes += 1
            raise OSError(errno.EIO, f"injected I2C write failure on motor{channel}")
        time_s = self._clock.now_s() if self._clock is not None else 0.0
        write = ThrottleWrite(time_s, channel, throttle)
        self.command_log.append(write)
        if self.on_write:
            notify(self.on_write, write, "motor kit on_write")


# --- the differential drive ---------------------------------------------------------

CommandKind = Literal["set", "stop", "coast", "expired"]


@dataclass(frozen=True, slots=True)
class MotorCommand:
    """The last command given to both motors, before inversion (for telemetry).

    ``left``/``right`` are the throttles actually written (after clamping), ``None``
    when coasting. ``kind`` "expired" is a stop caused by the command time-to-live.
    """

    left: float | None
    right: float | None
    time_s: float
    kind: CommandKind


class DifferentialMotors:
    """Left and right drive motors on a MotorKit-shaped ``kit``, with the safety rules.

    Throttles are in [-1, 1], positive drives the robot forward (``left_invert`` /
    ``right_invert`` fix the wiring polarity; mirrored motors usually need one side
    inverted). Creating it brakes both motors (an I²C write).

    Writes are synchronous I²C transactions (a few short ones per call), cheap enough
    for the 20 Hz control loop to make on the event loop.

    Time-to-live: every :meth:`set` arms ``loop.call_later(command_ttl_s)`` on ``loop``
    (or, if none was given, the running loop of the caller), cancelling the previous
    handle; if it fires, both motors brake. Call :meth:`set` from the loop's thread.
    Without any loop (synchronous use), only :meth:`expire_stale` enforces the TTL.

    Example::

        with DifferentialMotors(FakeMotorKit(), command_ttl_s=0.3, clock=RealClock()) as m:
            m.set(0.4, 0.4)    # forward; brakes by itself 0.3 s later unless refreshed
    """

    def __init__(
        self,
        kit: MotorKitLike,
        *,
        left_channel: int = 1,
        right_channel: int = 2,
        left_invert: bool = False,
        right_invert: bool = False,
        command_ttl_s: float = 0.3,
        clock: Clock,
        loop: asyncio.AbstractEventLoop | None = None,
        ttl_guarded: bool = False,
    ) -> None:
        for name, channel in (("left_channel", left_channel), ("right_channel", right_channel)):
            if channel not in CHANNELS:
                raise ValueError(f"{name} must be a HAT motor terminal 1..4, got {channel!r}")
        if left_channel == right_channel:
            raise ValueError(f"left and right motors share channel {left_channel}")
        if not command_ttl_s > 0:
            raise ValueError(f"command_ttl_s must be > 0 s, got {command_ttl_s!r}")
        self._sides = (
            ("left", left_channel, _motor(kit, left_channel), -1.0 if left_invert else 1.0),
            ("right", right_channel, _motor(kit, right_channel), -1.0 if right_invert else 1.0),
        )
        self.command_ttl_s = command_ttl_s
        self._clock = clock
        self._loop = loop
        self._ttl_handle: asyncio.TimerHandle | None = None
        self._closed = False
        # ``ttl_guarded``: no event loop here, a TtlGuard thread enforces the TTL (the control process)
        self._warned_no_loop = ttl_guarded
        self.last_command: MotorCommand | None = None
        self.write_errors = 0
        self.last_error: MotorWriteError | None = None  # for a supervisor to poll
        self.nonfinite_commands = 0
        self.expirations = 0
        self._write_lock = threading.RLock()  # the loop's writes and a hang guard's brake (TtlGuard)
        # The HAT may still be running the PWM of a previous process: brake first.
        self._write_both(0.0, 0.0, "stop")

    @classmethod
    def from_config(
        cls,
        cfg: MotorsConfig,
        kit: MotorKitLike,
        clock: Clock,
        *,
        loop: asyncio.AbstractEventLoop | None = None,
        ttl_guarded: bool = False,
    ) -> DifferentialMotors:
        """Build from the ``[motors]`` section; ``kit`` comes from :func:`open_motorkit`
        or is a :class:`FakeMotorKit` (``backend = "fake"``)."""
        return cls(
            kit,
            left_channel=cfg.left_channel,
            right_channel=cfg.right_channel,
            left_invert=cfg.left_invert,
            right_invert=cfg.right_invert,
            command_ttl_s=cfg.command_ttl_s,
            clock=clock,
            loop=loop,
            ttl_guarded=ttl_guarded,
        )

    @property
    def closed(self) -> bool:
        return self._closed

    def set(self, left: float, right: float) -> None:
        """Drive: throttles in [-1, 1] (clamped; non-finite -> 0), valid for the TTL.

        Raises :class:`MotorWriteError` if the HAT write fails (both motors were then
        told to brake), ``RuntimeError`` after :meth:`close`.
        """
        if self._closed:
            raise RuntimeError("DifferentialMotors is closed; it cannot drive the motors")
        left_t = self._sanitize("left", left)
        right_t = self._sanitize("right", right)
        self._write_both(left_t, right_t, "set")
        if left_t == 0.0 and right_t == 0.0:
            self._cancel_ttl()  # a zero command is a brake already: nothing to expire
        else:
            self._arm_ttl()

    def stop(self) -> None:
        """Brake both motors (throttle 0). Allowed after :meth:`close`."""
        self._cancel_ttl()
        self._write_both(0.0, 0.0, "stop")

    def coast(self) -> None:
        """Let both motors spin freely (throttle ``None``)."""
        self._cancel_ttl()
        self._write_both(None, None, "coast")

    def expire_stale(self, now_s: float) -> bool:
        """Brake if the last :meth:`set` is older than the TTL at clock time ``now_s``.

        For a control loop that checks each tick (and for virtual-time runs, where the
        event loop's timer does not follow the clock). Returns whether it braked.
        """
        last = self.last_command
        if last is None or last.kind != "set" or (last.left == 0.0 and last.right == 0.0):
            return False
        if now_s - last.time_s < self.command_ttl_s - _TIME_EPSILON_S:
            return False
        self._expire()
        return True

    def close(self) -> None:
        """Brake both motors and refuse further :meth:`set`. Idempotent.

        Raises :class:`MotorWriteError` (on the first call only) if the brake could
        not be written.
        """
        if self._closed:
            return
        self._closed = True
        self.stop()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def __repr__(self) -> str:
        (_, left_ch, _, _), (_, right_ch, _, _) = self._sides
        return (
            f"<DifferentialMotors left=motor{left_ch} right=motor{right_ch} "
            f"ttl={self.command_ttl_s}s last={self.last_command}>"
        )

    # --- internals ------------------------------------------------------------------

    def _sanitize(self, side: str, throttle: float) -> float:
        value = float(throttle)
        if not math.isfinite(value):
            self.nonfinite_commands += 1
            if self.nonfinite_commands % _NONFINITE_LOG_EVERY == 1:
                logger.warning(
                    "non-finite %s throttle %r treated as 0 (%d so far): a bug upstream",
                    side,
                    throttle,
                    self.nonfinite_commands,
                )
            return 0.0
        return min(1.0, max(-1.0, value))

    def brake_if_stale(self, now_s: float) -> bool:
        """From any thread: brake when the last driving :meth:`set` is older than the TTL at ``now_s``.

        What :class:`TtlGuard` calls while the event loop cannot run its own TTL timer;
        it leaves that timer alone (it belongs to the loop; braking twice is harmless).
        """
        last = self.last_command
        if last is None or last.kind != "set" or (last.left == 0.0 and last.right == 0.0):
            return False
        if now_s - last.time_s < self.command_ttl_s - _TIME_EPSILON_S:
            return False
        self.expirations += 1
        self._write_unguarded_brake()
        return True

    def _write_unguarded_brake(self) -> None:
        with self._write_lock:
            for _, channel, motor, _ in self._sides:
                try:
                    motor.throttle = 0.0
                except Exception:
                    logger.exception("could not brake motor%d from the hang guard", channel)
            self.last_command = MotorCommand(0.0, 0.0, self._clock.now_s(), "expired")

    def _write_both(self, left: float | None, right: float | None, kind: CommandKind) -> None:
        """Write both throttles; on any failure, brake both and raise MotorWriteError."""
        with self._write_lock:
            self._write_both_locked(left, right, kind)

    def _write_both_locked(self, left: float | None, right: float | None, kind: CommandKind) -> None:
        for (side, channel, motor, sign), throttle in zip(self._sides, (left, right), strict=True):
            try:
                # "+ 0.0" turns an inverted brake (-0.0) into 0.0 for the log and the HAT.
                motor.throttle = None if throttle is None else sign * throttle + 0.0
            except Exception as error:
                # Safety first: whatever went wrong, do not leave either motor running.
                self.write_errors += 1
                self._cancel_ttl()
                stopped = self._brake_all_best_effort()
                reason = " ".join(f"{type(error).__name__}: {error}".split())
                outcome = "both motors braked" if stopped else "BRAKE FAILED, cut motor power"
                fault = MotorWriteError(
                    f"motor HAT write failed on motor{channel} ({side}) ({reason}); "
                    f"{outcome}; check the HAT's I2C wiring and power",
                    channel=channel,
                    side=side,
                    stopped=stopped,
                )
                self.last_error = fault
                raise fault from error
        self.last_command = MotorCommand(left, right, self._clock.now_s(), kind)

    def _brake_all_best_effort(self) -> bool:
        """Throttle 0 on both motors, each tried even if the other fails.

        Each brake write is tried up to ``BRAKE_ATTEMPTS`` times: I²C errors on a noisy bus
        (EIO, EREMOTEIO) are mostly transient, and a brake that is not written leaves the
        PCA9685 driving the wheel at its last duty cycle.
        """
        stopped = True
        for side, channel, motor, _ in self._sides:
            for attempt in range(1, BRAKE_ATTEMPTS + 1):
                try:
                    motor.throttle = 0.0
                    break
                except Exception:
                    self.write_errors += 1
                    if attempt == BRAKE_ATTEMPTS:
                        stopped = False
                        logger.exception("could not brake motor%d (%s)", channel, side)
        self.last_command = MotorCommand(0.0, 0.0, self._clock.now_s(), "stop")
        return stopped

    def _arm_ttl(self) -> None:
        loop = self._loop
        if loop is None:
            try:
                loop = asyncio.get_running_loop()
            except RuntimeError:
                loop = None
        self._cancel_ttl()
        if loop is None:
            if not self._warned_no_loop:
                self._warned_no_loop = True
                logger.warning(
                    "motor command TTL has no event loop: only expire_stale() will stop "
                    "a stale command"
                )
            return
        try:
            self._ttl_handle = loop.call_later(self.command_ttl_s, self._on_ttl_expired)
        except RuntimeError:  # the loop is closed: nothing would ever expire this command
            self._brake_all_best_effort()
            raise

    def _cancel_ttl(self) -> None:
        if self._ttl_handle is not None:
            self._ttl_handle.cancel()
            self._ttl_handle = None

    def _on_ttl_expired(self) -> None:
        """Timer callback: runs on the loop, where exceptions would only be logged."""
        self._ttl_handle = None
        try:
            self._expire()
        except MotorWriteError:
            logger.exception("motor command expired and the brake write failed")

    def _expire(self) -> None:
        self.expirations += 1
        logger.warning(
            "motor command not refreshed within %.3f s: braking", self.command_ttl_s
        )
        self._cancel_ttl()
        self._write_both(0.0, 0.0, "expired")


class TtlGuard:
    """Enforces the motors' time-to-live from a thread of its own, for when the event loop hangs.

    The TTL of :class:`DifferentialMotors` is a timer of the event loop, and the control
    task's deadline acts on the loop's next tick: a loop that is stuck for good (a
    blocking call, a deadlock) runs neither, and the wheels would turn on until systemd's
    watchdog (``WatchdogSec``) kills the process. This thread looks every ``period_s``
    (wall time) and brakes a throttle older than ``command_ttl_s``. Use it only where the
    loop's clock is the monotonic clock (the robot, ``run --sim``), never on virtual time.

    Example::

        guard = TtlGuard(motors)
        guard.start()
        ...
        guard.close()
    """

    def __init__(self, motors: DifferentialMotors, period_s: float | None = None) -> None:
        self._motors = motors
        self.period_s = float(period_s) if period_s is not None else motors.command_ttl_s / 3.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.brakes = 0

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="mazebot-motor-ttl", daemon=True)
            self._thread.start()

    def check(self, now_s: float) -> bool:
        """One look at monotonic time ``now_s``; True when it braked."""
        if not self._motors.brake_if_stale(now_s):
            return False
        self.brakes += 1
        logger.error(
            "the event loop has not refreshed the motors for over %.3f s: braked from the hang guard",
            self._motors.command_ttl_s,
        )
        return True

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self.check(time.monotonic())

    def close(self) -> None:
        """Stop the thread; idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None


def _motor(kit: MotorKitLike, channel: int) -> MotorLike:
    motor: MotorLike = getattr(kit, f"motor{channel}")
    return motor
