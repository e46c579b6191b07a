"""The GPIO H-bridge backend on gpiozero's own MockFactory with MockPWMPin: duty and direction
pins per throttle, brake and coast, the time-to-live and stop on close of DifferentialMotors."""

from __future__ import annotations

import asyncio
import subprocess
import sys
from pathlib import Path

import pytest
from gpiozero.pins.mock import MockFactory, MockPWMPin

from mazebot.clock import RealClock
from mazebot.config import Config, MotorsConfig
from mazebot.errors import ConfigError, HardwareUnavailable
from mazebot.io.motor_gpio import open_gpio_motorkit
from mazebot.io.motors import DifferentialMotors


@pytest.fixture
def pins() -> MockFactory:
    factory = MockFactory(pin_class=MockPWMPin)
    yield factory
    factory.close()


def _levels(factory: MockFactory, *numbers: int) -> list[float]:
    return [round(float(factory.pin(n).state), 6) for n in numbers]


def test_in1_in2_pwm_and_direction_per_throttle(pins: MockFactory) -> None:
    cfg = MotorsConfig(backend="gpio", gpio_motor1_pins=[5, 6, 12], gpio_motor2_pins=[13, 19], pwm_frequency_hz=1000)
    kit = open_gpio_motorkit(cfg, pins)
    assert _levels(pins, 5, 6, 12, 13, 19) == [1.0, 1.0, 1.0, 1.0, 1.0]  # opened braked: both inputs high
    assert pins.pin(5).frequency == 1000
    kit.motor1.throttle = 0.4
    assert _levels(pins, 5, 6, 12) == [0.4, 0.0, 1.0]  # PWM on IN1, IN2 low, ENA high
    kit.motor1.throttle = -0.7
    assert _levels(pins, 5, 6, 12) == [0.0, 0.7, 1.0]
    kit.motor1.throttle = 0.0
    assert _levels(pins, 5, 6) == [1.0, 1.0]  # brake
    kit.motor1.throttle = None
    assert _levels(pins, 5, 6, 12) == [0.0, 0.0, 0.0]  # coast: the L298N's enable off too
    kit.motor2.throttle = 1.0
    assert _levels(pins, 13, 19) == [1.0, 0.0]
    with pytest.raises(ValueError):
        kit.motor2.throttle = 1.5
    kit.close()


def test_phase_enable_direction_pin_and_pwm_enable(pins: MockFactory) -> None:
    cfg = MotorsConfig(backend="gpio", gpio_driver="phase_enable", gpio_motor1_pins=[20, 21],
                       gpio_motor2_pins=[24, 25])
    kit = open_gpio_motorkit(cfg, pins)
    kit.motor1.throttle = 0.3
    assert _levels(pins, 20, 21) == [0.0, 0.3]
    kit.motor1.throttle = -0.3
    assert _levels(pins, 20, 21) == [1.0, 0.3]
    kit.motor1.throttle = 0.0
    assert _levels(pins, 21) == [0.0]  # enable low: the board's stop
    kit.close()


def test_the_differential_drive_on_gpio_expires_a_stale_command_and_stops_on_close(pins: MockFactory) -> None:
    cfg = MotorsConfig(backend="gpio", gpio_motor1_pins=[5, 6], gpio_motor2_pins=[13, 19], right_invert=True,
                       command_ttl_s=0.05)
    kit = open_gpio_motorkit(cfg, pins)

    async def go() -> tuple[list[float], list[float]]:
        motors = DifferentialMotors.from_config(cfg, kit, RealClock())
        motors.set(0.5, 0.5)
        driving = _levels(pins, 5, 6, 13, 19)
        await asyncio.sleep(0.2)  # never refreshed: the time-to-live brakes
        expired = _levels(pins, 5, 6, 13, 19)
        motors.set(0.5, 0.5)
        motors.close()
        return driving, expired

    driving, expired = asyncio.run(go())
    assert driving == [0.5, 0.0, 0.0, 0.5]  # the right motor inverted: IN2 of channel 2
    assert expired == [1.0, 1.0, 1.0, 1.0]
    assert _levels(pins, 5, 6, 13, 19) == [1.0, 1.0, 1.0, 1.0]  # closed: braked
    kit.close()


def test_a_pin_in_use_is_one_line_and_releases_the_channel_already_opened(pins: MockFactory) -> None:
    from gpiozero import OutputDevice

    holder = OutputDevice(13, pin_factory=pins)  # another program's pin
    cfg = MotorsConfig(backend="gpio", gpio_motor1_pins=[5, 6], gpio_motor2_pins=[13, 19])
    with pytest.raises(HardwareUnavailable) as caught:
        open_gpio_motorkit(cfg, pins)
    assert "\n" not in str(caught.value) and "gpio_motor1_pins" in str(caught.value)
    OutputDevice(5, pin_factory=pins).close()  # channel 1 was released
    holder.close()


@pytest.mark.parametrize(("section", "words"), [
    ({"backend": "gpio", "gpio_motor1_pins": [5]}, "gpio_motor1_pins for in1_in2 takes"),
    ({"backend": "gpio", "gpio_driver": "phase_enable", "gpio_motor1_pins": [5, 6, 7]}, "PHASE, ENABLE"),
    ({"backend": "gpio", "gpio_motor2_pins": [5, 19]}, "must all differ"),
    ({"backend": "gpio", "left_channel": 3}, "channels are 1 and 2"),
])
def test_bad_gpio_pins_are_refused(section: dict, words: str) -> None:
    with pytest.raises(ValueError, match=words):
        MotorsConfig(**section)


def test_motor_pins_may_not_be_encoder_pins(tmp_path: Path) -> None:
    from mazebot.config import load_config

    cfg = tmp_path / "config.toml"
    cfg.write_text('[motors]\nbackend = "gpio"\ngpio_motor1_pins = [17, 6]\n')
    with pytest.raises(ConfigError, match="share GPIO"):
        load_config(cfg)
    assert Config().motors.backend == "motorkit"


def test_motors_stop_on_gpio_imports_neither_numpy_nor_scipy(tmp_path: Path) -> None:
    """Off a Pi gpiozero finds no GPIO: exit 69, after the same imports as on the robot."""
    cfg = tmp_path / "config.toml"
    cfg.write_text('[motors]\nbackend = "gpio"\n')
    proc = subprocess.run([sys.executable, "-X", "importtime", "-m", "mazebot", "motors", "stop", "--config",
                           str(cfg)], capture_output=True, text=True, timeout=60, check=False, cwd=tmp_path)
    assert "mazebot.io.motor_gpio" in proc.stderr
    for heavy in ("numpy", "scipy", "aiohttp", "mazebot.slam", "mazebot.web"):
        assert f"| {heavy}\n" not in proc.stderr and f"| {heavy}." not in proc.stderr
