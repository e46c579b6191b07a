"""The ``[motors]`` section of ``config.toml``, and reading it alone.

Apart from :mod:`mazebot.config` (which includes it in the whole configuration) because
``mazebot motors stop``, the safety net systemd runs after every exit of the daemon, needs
only this section: importing it does not build the other sections' models nor import the
SLAM's and the simulator's parameters, which is most of the time the command takes.
"""

from __future__ import annotations

import os
from typing import Literal

from pydantic import Field, ValidationError, model_validator

from mazebot.config_file import default_config_path, read_config_file, validation_problems
from mazebot.config_section import BcmPin, Section
from mazebot.errors import ConfigError


class MotorsConfig(Section):
    """Two DC gear motors on the Adafruit DC & Stepper Motor HAT, or on an H-bridge board on GPIO pins."""

    backend: Literal["motorkit", "gpio", "fake"] = Field(
        "motorkit",
        description="motorkit: the Adafruit HAT over I2C; gpio: an H-bridge on GPIO pins (L298N, DRV8833, "
        "TB6612, phase/enable boards); fake: no hardware (tests)",
    )
    gpio_driver: Literal["in1_in2", "phase_enable"] = Field(
        "in1_in2",
        description="gpio: in1_in2: two PWM inputs per motor (L298N, DRV8833, TB6612); phase_enable: a direction "
        "pin and a PWM enable pin (DRV8835 in PHASE/ENABLE mode, Cytron MDD10A DIR/PWM)",
    )
    gpio_motor1_pins: list[BcmPin] = Field(
        [5, 6],
        description="gpio: BCM pins of channel 1; in1_in2: IN1, IN2 and, if wired, the enable (ENA, held high); "
        "phase_enable: PHASE, ENABLE",
    )
    gpio_motor2_pins: list[BcmPin] = Field([13, 19], description="gpio: BCM pins of channel 2, as for channel 1")
    i2c_address: int = Field(0x60, ge=0x03, le=0x77, description="I2C address of the HAT")
    pwm_frequency_hz: float = Field(
        1600.0, ge=24, le=2000,
        description="PWM frequency of the HAT's PCA9685 (MotorKit's default is 1600 Hz) or of the gpio pins"
    )
    left_channel: Literal[1, 2, 3, 4] = Field(1, description="HAT motor terminal of the left wheel")
    right_channel: Literal[1, 2, 3, 4] = Field(
        2, description="HAT motor terminal of the right wheel"
    )
    left_invert: bool = Field(False, description="reverse the left motor's polarity in software")
    right_invert: bool = Field(True, description="reverse the right motor's polarity (mirrored)")
    command_ttl_s: float = Field(
        0.3, gt=0, le=2, description="a throttle not refreshed within this time becomes a stop"
    )

    @model_validator(mode="after")
    def _channels_distinct(self) -> MotorsConfig:
        if self.left_channel == self.right_channel:
            raise ValueError(f"left and right motors share channel {self.left_channel}")
        if self.backend == "gpio":
            if {self.left_channel, self.right_channel} != {1, 2}:
                raise ValueError('with backend = "gpio" the channels are 1 and 2 (gpio_motor1_pins, gpio_motor2_pins)')
            counts = (2, 3) if self.gpio_driver == "in1_in2" else (2,)
            named = (("gpio_motor1_pins", self.gpio_motor1_pins), ("gpio_motor2_pins", self.gpio_motor2_pins))
            for name, pins in named:
                if len(pins) not in counts:
                    wanted = "IN1, IN2 and optionally the enable" if self.gpio_driver == "in1_in2" else "PHASE, ENABLE"
                    raise ValueError(f"{name} for {self.gpio_driver} takes {wanted}, got {pins}")
            pins = [*self.gpio_motor1_pins, *self.gpio_motor2_pins]
            if len(set(pins)) != len(pins):
                raise ValueError(f"the motors' GPIO pins must all differ, got {pins}")
        return self


def load_motors_config(path: str | os.PathLike[str] | None = None) -> MotorsConfig:
    """Only the ``[motors]`` section of a config file, validated as :func:`mazebot.config.load_config` does.

    For ``mazebot motors stop``, the safety net systemd runs after every exit of the daemon:
    a mistake in any other section must not keep it from zeroing the HAT, and building
    only this section's model keeps the command quick.
    """
    if path is None:
        path = default_config_path()
        if path is None:
            return MotorsConfig()
    data = read_config_file(path)
    section = data.get("motors", {})
    if not isinstance(section, dict):
        raise ConfigError(f"{path}: motors: expected a [motors] table, found {section!r}")
    try:
        return MotorsConfig.model_validate(section, strict=True)
    except ValidationError as exc:
        raise validation_problems(exc, str(path), "motors.") from None
