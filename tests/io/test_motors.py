"""The differential drive on a FakeMotorKit: mapping, limits, and every way to stop."""

from __future__ import annotations

import asyncio
import logging
import math
import subprocess
import sys
import types
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from mazebot.clock import RealClock
from mazebot.config import MotorsConfig
from mazebot.errors import EXIT_UNAVAILABLE, HardwareUnavailable
from mazebot.io.motors import (
    BRAKE_ATTEMPTS,
    DifferentialMotors,
    FakeMotorKit,
    MotorCommand,
    MotorWriteError,
    ThrottleWrite,
    TtlGuard,
    open_motorkit,
)
from tests.fake_clock import FakeClock


class FakeHandle:
    def __init__(self, delay_s: float, callback: Callable[[], None]) -> None:
        self.delay_s = delay_s
        self.callback = callback
        self.cancelled = False

    def cancel(self) -> None:
        self.cancelled = True


class FakeLoop:
    """Just enough of an event loop to see the TTL timer being armed and fired by hand."""

    def __init__(self) -> None:
        self.handles: list[FakeHandle] = []

    def call_later(self, delay_s: float, callback: Callable[[], None]) -> FakeHandle:
        handle = FakeHandle(delay_s, callback)
        self.handles.append(handle)
        return handle

    def live(self) -> list[FakeHandle]:
        return [h for h in self.handles if not h.cancelled]


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock(100.0)


@pytest.fixture
def kit(clock: FakeClock) -> FakeMotorKit:
    return FakeMotorKit(clock)


@pytest.fixture
def loop() -> FakeLoop:
    return FakeLoop()


def make(kit: FakeMotorKit, clock: FakeClock, loop: FakeLoop, **kwargs: Any) -> DifferentialMotors:
    return DifferentialMotors(kit, clock=clock, loop=loop, **kwargs)  # type: ignore[arg-type]


# --- FakeMotorKit ---------------------------------------------------------------------


def test_fake_kit_logs_writes_and_rejects_out_of_range(kit: FakeMotorKit, clock: FakeClock) -> None:
    assert kit.throttles() == {1: None, 2: None, 3: None, 4: None}
    kit.motor3.throttle = -0.25
    clock.t = 101.0
    kit.motor3.throttle = None
    assert list(kit.command_log) == [ThrottleWrite(100.0, 3, -0.25), ThrottleWrite(101.0, 3, None)]
    with pytest.raises(ValueError, match=r"between -1\.0 and"):
        kit.motor1.throttle = 1.01


def test_fake_kit_injected_failures(kit: FakeMotorKit) -> None:
    kit.fail_writes(channels=[2], times=1)
    kit.motor1.throttle = 0.5  # other channels unaffected
    with pytest.raises(OSError, match="motor2"):
        kit.motor2.throttle = 0.5
    kit.motor2.throttle = 0.5  # only once
    assert (kit.failed_writes, kit.motor2.throttle) == (1, 0.5)
    kit.fail_writes()
    with pytest.raises(OSError):
        kit.motor4.throttle = 0.0
    kit.heal()
    kit.motor4.throttle = 0.0


# --- driving --------------------------------------------------------------------------


def test_creation_brakes_both_motors(kit: FakeMotorKit, clock: FakeClock, loop: FakeLoop) -> None:
    motors = make(kit, clock, loop)
    assert list(kit.command_log) == [ThrottleWrite(100.0, 1, 0.0), ThrottleWrite(100.0, 2, 0.0)]
    assert motors.last_command == MotorCommand(0.0, 0.0, 100.0, "stop")
    assert loop.live() == []


def test_channels_and_inversion(kit: FakeMotorKit, clock: FakeClock, loop: FakeLoop) -> None:
    motors = make(kit, clock, loop, left_channel=3, right_channel=1, right_invert=True)
    motors.set(0.5, 0.25)
    assert kit.throttles() == {1: -0.25, 2: None, 3: 0.5, 4: None}
    assert motors.last_command == MotorCommand(0.5, 0.25, 100.0, "set")
    motors = make(kit, clock, loop, left_channel=2, right_channel=4, left_invert=True)
    motors.set(-1.0, 0.75)
    assert kit.throttles()[2] == 1.0
    assert kit.throttles()[4] == 0.75


def test_throttles_are_clamped(kit: FakeMotorKit, clock: FakeClock, loop: FakeLoop) -> None:
    motors = make(kit, clock, loop)
    motors.set(1.7, -3.0)
    assert (kit.motor1.throttle, kit.motor2.throttle) == (1.0, -1.0)
    assert motors.last_command == MotorCommand(1.0, -1.0, 100.0, "set")


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_throttle_is_zero_and_logged(
    kit: FakeMotorKit,
    clock: FakeClock,
    loop: FakeLoop,
    caplog: pytest.LogCaptureFixture,
    bad: float,
) -> None:
    motors = make(kit, clock, loop)
    with caplog.at_level(logging.WARNING, logger="mazebot.io.motors"):
        motors.set(bad, 0.5)
    assert (kit.motor1.throttle, kit.motor2.throttle) == (0.0, 0.5)
    assert motors.nonfinite_commands == 1
    assert "non-finite left throttle" in caplog.text


def test_inverted_brake_is_plus_zero(kit: FakeMotorKit, clock: FakeClock, loop: FakeLoop) -> None:
    make(kit, clock, loop, left_invert=True, right_invert=True)
    assert all(math.copysign(1.0, w.throttle) == 1.0 for w in kit.command_log if w.throttle == 0)


def test_stop_brakes_and_coast_releases(
    kit: FakeMotorKit, clock: FakeClock, loop: FakeLoop
) -> None:
    motors = make(kit, clock, loop)
    motors.set(0.4, 0.4)
    motors.stop()
    assert (kit.motor1.throttle, kit.motor2.throttle) == (0.0, 0.0)
    assert motors.last_command is not None and motors.last_command.kind == "stop"
    motors.set(0.4, 0.4)
    motors.coast()
    assert (kit.motor1.throttle, kit.motor2.throttle) == (None, None)
    assert motors.last_command == MotorCommand(None, None, 100.0, "coast")
    assert loop.live() == []  # neither leaves a timer behind


def test_from_config_maps_channels_inversion_and_ttl(kit: FakeMotorKit, clock: FakeClock) -> None:
    cfg = MotorsConfig(backend="fake", left_channel=4, right_channel=3, command_ttl_s=0.5)
    motors = DifferentialMotors.from_config(cfg, kit, clock)
    motors.set(0.5, 0.5)  # default config mirrors the right motor
    assert (kit.motor4.throttle, kit.motor3.throttle) == (0.5, -0.5)
    assert motors.command_ttl_s == 0.5
    motors.close()


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"left_channel": 0}, "left_channel"),
        ({"right_channel": 5}, "right_channel"),
        ({"left_channel": 2, "right_channel": 2}, "share channel 2"),
        ({"command_ttl_s": 0.0}, "command_ttl_s"),
    ],
)
def test_bad_arguments_are_rejected_before_any_write(
    kit: FakeMotorKit, clock: FakeClock, loop: FakeLoop, kwargs: dict[str, Any], match: str
) -> None:
    with pytest.raises(ValueError, match=match):
        make(kit, clock, loop, **kwargs)
    assert not kit.command_log


# --- time-to-live ---------------------------------------------------------------------


def test_each_set_rearms_one_timer(kit: FakeMotorKit, clock: FakeClock, loop: FakeLoop) -> None:
    motors = make(kit, clock, loop, command_ttl_s=0.3)
    motors.set(0.5, 0.5)
    motors.set(0.6, 0.6)
    assert [h.delay_s for h in loop.live()] == [0.3]
    assert loop.handles[0].cancelled
    motors.set(0.0, 0.0)  # a zero command is already a brake
    assert loop.live() == []


def test_timer_firing_brakes(kit: FakeMotorKit, clock: FakeClock, loop: FakeLoop) -> None:
    motors = make(kit, clock, loop)
    motors.set(0.5, -0.5)
    clock.t += 0.3
    loop.live()[0].callback()
    assert (kit.motor1.throttle, kit.motor2.throttle) == (0.0, 0.0)
    assert motors.last_command == MotorCommand(0.0, 0.0, 100.3, "expired")
    assert motors.expirations == 1


def test_timer_firing_with_a_dead_bus_does_not_raise_into_the_loop(
    kit: FakeMotorKit, clock: FakeClock, loop: FakeLoop, caplog: pytest.LogCaptureFixture
) -> None:
    motors = make(kit, clock, loop)
    motors.set(0.5, 0.5)
    kit.fail_writes()
    with caplog.at_level(logging.ERROR, logger="mazebot.io.motors"):
        loop.live()[0].callback()  # must not raise: it runs inside the event loop
    assert isinstance(motors.last_error, MotorWriteError)
    assert not motors.last_error.stopped
    assert "brake write failed" in caplog.text


def test_expire_stale_uses_the_clock(kit: FakeMotorKit, clock: FakeClock, loop: FakeLoop) -> None:
    motors = make(kit, clock, loop, command_ttl_s=0.3)
    motors.set(0.5, 0.5)
    assert not motors.expire_stale(100.29)
    assert kit.motor1.throttle == 0.5
    clock.t = 100.3
    assert motors.expire_stale(100.3)
    assert (kit.motor1.throttle, kit.motor2.throttle) == (0.0, 0.0)
    assert motors.last_command is not None and motors.last_command.kind == "expired"
    assert loop.live() == []
    assert not motors.expire_stale(200.0)  # nothing left to expire


async def test_ttl_expires_on_a_running_loop() -> None:
    braked = asyncio.Event()

    class WatchedKit(FakeMotorKit):
        watching = False

        def _write(self, channel: int, throttle: float | None) -> None:
            super()._write(channel, throttle)
            if self.watching and throttle == 0.0:
                braked.set()

    kit = WatchedKit()
    motors = DifferentialMotors(kit, command_ttl_s=0.05, clock=RealClock())
    motors.set(0.5, 0.5)
    kit.watching = True
    assert kit.motor1.throttle == 0.5  # nothing can expire before we yield to the loop
    await asyncio.wait_for(braked.wait(), timeout=5.0)
    assert (kit.motor1.throttle, kit.motor2.throttle) == (0.0, 0.0)
    assert motors.last_command is not None and motors.last_command.kind == "expired"
    assert motors.expirations == 1
    motors.close()


def test_set_without_a_loop_warns_once(
    kit: FakeMotorKit, clock: FakeClock, caplog: pytest.LogCaptureFixture
) -> None:
    motors = DifferentialMotors(kit, clock=clock)
    with caplog.at_level(logging.WARNING, logger="mazebot.io.motors"):
        motors.set(0.2, 0.2)
        motors.set(0.2, 0.2)
    assert caplog.text.count("only expire_stale()") == 1
    clock.t += 1.0
    assert motors.expire_stale(clock.now_s())


# --- write failures -------------------------------------------------------------------


def test_failed_right_write_brakes_both_and_raises(
    kit: FakeMotorKit, clock: FakeClock, loop: FakeLoop
) -> None:
    motors = make(kit, clock, loop)
    kit.fail_writes(channels=[2], times=1)
    with pytest.raises(MotorWriteError) as caught:
        motors.set(0.5, 0.5)
    assert (kit.motor1.throttle, kit.motor2.throttle) == (0.0, 0.0)
    error = caught.value
    assert (error.channel, error.side, error.stopped) == (2, "right", True)
    assert isinstance(error.__cause__, OSError)
    assert "\n" not in str(error)
    assert "motor2 (right)" in str(error) and "both motors braked" in str(error)
    assert error.exit_code == EXIT_UNAVAILABLE
    assert motors.write_errors == 1
    assert motors.last_error is error
    assert loop.live() == []
    assert motors.last_command is not None and motors.last_command.kind == "stop"


def test_dead_left_channel_still_brakes_the_right(
    kit: FakeMotorKit, clock: FakeClock, loop: FakeLoop
) -> None:
    motors = make(kit, clock, loop)
    motors.set(0.3, 0.3)
    kit.fail_writes(channels=[1])
    with pytest.raises(MotorWriteError) as caught:
        motors.set(0.8, 0.8)
    assert kit.motor2.throttle == 0.0  # the motor we can still reach is stopped
    assert not caught.value.stopped
    assert "BRAKE FAILED" in str(caught.value)
    assert motors.write_errors == 1 + BRAKE_ATTEMPTS  # the set and every brake try of motor1


def test_a_brake_write_that_fails_once_is_tried_again(
    kit: FakeMotorKit, clock: FakeClock, loop: FakeLoop
) -> None:
    motors = make(kit, clock, loop)
    motors.set(0.6, 0.6)
    kit.fail_writes(channels=[1], times=2)  # the set's write, then the first brake try
    with pytest.raises(MotorWriteError) as caught:
        motors.set(0.8, 0.8)
    assert caught.value.stopped and "both motors braked" in str(caught.value)
    assert kit.motor1.throttle == 0.0 and kit.motor2.throttle == 0.0


def test_unexpected_write_exception_is_handled_the_same(
    kit: FakeMotorKit, clock: FakeClock, loop: FakeLoop
) -> None:
    class Boom(RuntimeError):
        pass

    motors = make(kit, clock, loop)
    motors.set(0.3, 0.3)

    def broken_write(channel: int, throttle: float | None) -> None:
        if throttle:
            raise Boom("bus lock timeout")
        kit.command_log.append(ThrottleWrite(0.0, channel, throttle))

    kit._write = broken_write  # type: ignore[method-assign]
    with pytest.raises(MotorWriteError, match="Boom: bus lock timeout"):
        motors.set(0.9, 0.9)
    assert (kit.motor1.throttle, kit.motor2.throttle) == (0.0, 0.0)


# --- close ----------------------------------------------------------------------------


def test_close_brakes_once_and_refuses_set(
    kit: FakeMotorKit, clock: FakeClock, loop: FakeLoop
) -> None:
    motors = make(kit, clock, loop)
    motors.set(0.5, 0.5)
    motors.close()
    assert (kit.motor1.throttle, kit.motor2.throttle) == (0.0, 0.0)
    assert loop.live() == []
    writes = len(kit.command_log)
    motors.close()
    assert len(kit.command_log) == writes
    assert motors.closed
    with pytest.raises(RuntimeError, match="closed"):
        motors.set(0.1, 0.1)
    assert kit.motor1.throttle == 0.0


def test_context_manager_brakes_on_error(
    kit: FakeMotorKit, clock: FakeClock, loop: FakeLoop
) -> None:
    with pytest.raises(KeyError), make(kit, clock, loop) as motors:
        motors.set(0.7, 0.7)
        raise KeyError("a task crashed")
    assert (kit.motor1.throttle, kit.motor2.throttle) == (0.0, 0.0)


def test_close_reports_a_failed_brake(kit: FakeMotorKit, clock: FakeClock, loop: FakeLoop) -> None:
    motors = make(kit, clock, loop)
    kit.fail_writes()
    with pytest.raises(MotorWriteError):
        motors.close()
    motors.close()  # idempotent even after a failure


# --- the real HAT ---------------------------------------------------------------------


def test_importing_motors_does_not_import_board() -> None:
    code = (
        "import sys, mazebot.io.motors, mazebot.io.encoders\n"
        "bad = {'board', 'adafruit_motorkit', 'busio'} & set(sys.modules)\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


def _stub_motorkit(monkeypatch: pytest.MonkeyPatch, motorkit: Callable[..., Any]) -> None:
    module = types.ModuleType("adafruit_motorkit")
    module.MotorKit = motorkit  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "adafruit_motorkit", module)


def test_open_motorkit_without_a_hat_is_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    def no_hat(address: int, pwm_frequency: float) -> None:
        raise ValueError(f"No I2C device at address: 0x{address:x}\n(probe failed)")

    _stub_motorkit(monkeypatch, no_hat)
    with pytest.raises(HardwareUnavailable) as caught:
        open_motorkit(0x60, 1600.0)
    message = str(caught.value)
    assert "\n" not in message
    assert message.startswith("motor HAT not found at I2C address 0x60 (ValueError: No I2C")
    assert message.endswith("check the HAT is seated and I2C is enabled (raspi-config)")
    assert caught.value.exit_code == EXIT_UNAVAILABLE


def test_open_motorkit_passes_address_and_frequency(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = []

    def motorkit(address: int, pwm_frequency: float) -> FakeMotorKit:
        calls.append((address, pwm_frequency))
        return FakeMotorKit()

    _stub_motorkit(monkeypatch, motorkit)
    assert isinstance(open_motorkit(0x61, 1000.0), FakeMotorKit)
    assert calls == [(0x61, 1000.0)]


@pytest.mark.skipif(Path("/dev/i2c-1").exists(), reason="this machine has an I2C bus")
def test_open_motorkit_off_a_pi_is_hardware_unavailable() -> None:
    code = (
        "from mazebot.io.motors import open_motorkit\n"
        "from mazebot.errors import HardwareUnavailable\n"
        "try:\n"
        "    open_motorkit(0x60, 1600.0)\n"
        "except HardwareUnavailable as e:\n"
        "    print(e)\n"
        "else:\n"
        "    raise SystemExit('opened a motor HAT on a machine without I2C?')\n"
    )
    result = subprocess.run(
        [sys.executable, "-W", "ignore", "-c", code],
        check=True,
        capture_output=True,
        text=True,
        timeout=120,
    )
    lines = result.stdout.splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("motor HAT not found at I2C address 0x60 (")


# --- the hang guard ------------------------------------------------------------------


def test_the_hang_guard_brakes_a_throttle_the_loop_no_longer_refreshes(
    kit: FakeMotorKit, clock: FakeClock, loop: FakeLoop
) -> None:
    motors = make(kit, clock, loop, command_ttl_s=0.3)
    guard = TtlGuard(motors)
    motors.set(0.5, 0.5)  # at 100.0 s: the loop's timer is armed, and then the loop hangs
    assert not guard.check(100.2)
    assert kit.throttles()[1] == 0.5
    assert guard.check(100.31)  # the loop's own timer never fired
    assert kit.throttles()[1] == 0.0 and kit.throttles()[2] == 0.0 and guard.brakes == 1
    assert not guard.check(100.5)  # braked: nothing to do until the next drive
    motors.set(0.0, 0.0)
    assert not guard.check(101.0)  # a stop is no stale throttle


def test_the_hang_guard_thread_stops_the_wheels_of_a_blocked_loop() -> None:
    import time

    async def drive_then_hang() -> dict[int, float | None]:
        clock = RealClock()
        kit = FakeMotorKit(clock)
        motors = DifferentialMotors(kit, clock=clock, command_ttl_s=0.1)
        guard = TtlGuard(motors)
        guard.start()
        try:
            motors.set(0.4, 0.4)
            time.sleep(1.0)  # noqa: ASYNC251  # the event loop is blocked: its TTL timer cannot fire
            return kit.throttles()
        finally:
            guard.close()

    throttles = asyncio.run(drive_then_hang())
    assert throttles[1] == 0.0 and throttles[2] == 0.0


# --- the kit's taps (mazebot.taps): what reached the HAT, and nothing a tap does stops a write


def test_on_write_hears_each_write_that_reached_the_hat(
    kit: FakeMotorKit, clock: FakeClock, loop: FakeLoop
) -> None:
    motors = make(kit, clock, loop)
    heard: list[ThrottleWrite] = []
    kit.on_write += (heard.append,)
    clock.t = 2.0
    motors.set(0.4, -0.2)
    assert heard == [ThrottleWrite(2.0, 1, 0.4), ThrottleWrite(2.0, 2, -0.2)]
    kit.fail_writes(channels=[2], times=1)  # the right write fails; then both brake
    with pytest.raises(MotorWriteError):
        motors.set(0.5, 0.5)
    assert heard[2:] == [ThrottleWrite(2.0, 1, 0.5), ThrottleWrite(2.0, 1, 0.0), ThrottleWrite(2.0, 2, 0.0)]


def test_a_failing_write_listener_never_stops_a_write(
    kit: FakeMotorKit, clock: FakeClock, loop: FakeLoop, caplog: pytest.LogCaptureFixture
) -> None:
    motors = make(kit, clock, loop)
    heard: list[ThrottleWrite] = []

    def broken(write: ThrottleWrite) -> None:
        raise RuntimeError("a logger's bug")

    kit.on_write = (broken, heard.append)
    with caplog.at_level(logging.ERROR, logger="mazebot.taps"):
        motors.set(0.6, 0.6)  # no MotorWriteError: the writes happened
        assert (kit.motor1.throttle, kit.motor2.throttle) == (0.6, 0.6)
        motors.stop()
    assert (kit.motor1.throttle, kit.motor2.throttle) == (0.0, 0.0)
    assert motors.write_errors == 0 and len(heard) == 4  # the other listener heard every write
    assert "motor kit on_write" in caplog.text


def test_a_failing_before_write_never_stops_a_brake(
    kit: FakeMotorKit, clock: FakeClock, loop: FakeLoop, caplog: pytest.LogCaptureFixture
) -> None:
    motors = make(kit, clock, loop)
    motors.set(0.7, 0.7)

    def world_broken() -> None:
        raise RuntimeError("simulator step failed")

    kit.before_write = world_broken
    with caplog.at_level(logging.ERROR, logger="mazebot.io.motors"):
        motors.stop()
    assert (kit.motor1.throttle, kit.motor2.throttle) == (0.0, 0.0)
    assert kit.command_log[-1].throttle == 0.0 and motors.write_errors == 0
    assert "before_write tap failed" in caplog.text
