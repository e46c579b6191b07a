"""Two DC motors on an H-bridge board wired to GPIO pins, shaped like the motor HAT's ``MotorKit``.

``[motors] backend = "gpio"``. :class:`GpioMotorKit` has ``motor1`` and ``motor2`` (the
board's two channels, ``gpio_motor1_pins`` and ``gpio_motor2_pins``), each with the HAT's
``throttle`` (-1..1, 0 brakes, ``None`` coasts), so :class:`mazebot.io.motors.DifferentialMotors`
drives it with the same safety rules (time-to-live, brake on open and on close).

Two kinds of board, both through gpiozero (https://gpiozero.readthedocs.io/en/stable/api_output.html):

* ``in1_in2``: gpiozero ``Motor``: a PWM on IN1 drives forward, on IN2 backward. Brake is
  both inputs high (L298 datasheet, "Fast Motor Stop" with C = D and enable high; DRV8833
  datasheet, IN1 = IN2 = 1 "brake, slow decay"; TB6612FNG datasheet, "short brake"); coast is
  both low (DRV8833 and TB6612; the L298N coasts only with its enable low, so a third pin,
  the enable, is switched off to coast).
* ``phase_enable``: gpiozero ``PhaseEnableMotor``: PHASE sets the direction, a PWM on ENABLE
  the speed; ENABLE low is the board's stop (the DRV8835 in PHASE/ENABLE mode brakes, its
  datasheet's table 2), so brake and coast are the same here.

Kept apart from :mod:`mazebot.io.motors` like :mod:`mazebot.io.motor_hat`: ``mazebot motors
stop`` imports only this module and gpiozero (no numpy).
"""

from __future__ import annotations

import warnings
from typing import Any

from mazebot.errors import HardwareUnavailable


class GpioMotor:
    """One channel of the H-bridge: the HAT's ``throttle`` on a gpiozero motor."""

    def __init__(self, device: Any, brake_both_high: bool) -> None:
        self.device = device  # gpiozero Motor or PhaseEnableMotor
        self._brake_both_high = brake_both_high
        self._throttle: float | None = None

    @property
    def throttle(self) -> float | None:
        return self._throttle

    @throttle.setter
    def throttle(self, value: float | None) -> None:
        if value is not None and not -1.0 <= value <= 1.0:  # as adafruit_motor's DCMotor
            raise ValueError(f"throttle must be None or between -1.0 and +1.0, got {value}")
        d = self.device
        if value is None or (value == 0.0 and not self._brake_both_high):
            d.stop()
            if value is None and getattr(d, "enable_device", None) is not None and self._brake_both_high:
                d.enable_device.off()  # an L298N coasts only with its enable low
        elif value == 0.0:
            if getattr(d, "enable_device", None) is not None:
                d.enable_device.on()
            d.forward_device.value = 1.0  # both inputs high: brake
            d.backward_device.value = 1.0
        else:
            if getattr(d, "enable_device", None) is not None and self._brake_both_high:
                d.enable_device.on()
            d.value = value
        self._throttle = value

    def close(self) -> None:
        self.device.close()


class GpioMotorKit:
    """``motor1`` and ``motor2`` of an H-bridge on GPIO; ``close()`` releases the pins (after braking)."""

    def __init__(self, motor1: GpioMotor, motor2: GpioMotor) -> None:
        self.motor1 = motor1
        self.motor2 = motor2

    @property
    def motor3(self) -> GpioMotor:
        raise AttributeError("a GPIO H-bridge has channels 1 and 2 only")

    @property
    def motor4(self) -> GpioMotor:
        raise AttributeError("a GPIO H-bridge has channels 1 and 2 only")

    def close(self) -> None:
        for motor in (self.motor1, self.motor2):
            try:
                motor.throttle = 0.0
            finally:
                motor.close()


def _device(driver: str, pins: list[int], frequency_hz: float, pin_factory: Any) -> Any:
    from gpiozero import Motor, PhaseEnableMotor

    if driver == "phase_enable":
        phase, enable = pins
        device = PhaseEnableMotor(phase, enable, pwm=True, pin_factory=pin_factory)
        device.enable_device.frequency = frequency_hz
        return device
    enable_pin = pins[2] if len(pins) == 3 else None
    device = Motor(pins[0], pins[1], enable=enable_pin, pwm=True, pin_factory=pin_factory)
    device.forward_device.frequency = frequency_hz
    device.backward_device.frequency = frequency_hz
    return device


def open_gpio_motorkit(cfg: Any, pin_factory: Any = None) -> GpioMotorKit:
    """The ``[motors]`` section's H-bridge on ``pin_factory`` (default: gpiozero's, lgpio on a Pi).

    Both channels are braked before this returns. Any failure (no GPIO off a Pi, a pin held by
    another program) is one :class:`HardwareUnavailable` line; a channel already opened is closed.
    """
    opened: list[Any] = []
    try:
        with warnings.catch_warnings():  # gpiozero warns of each pin library it does not find: the error says it
            warnings.simplefilter("ignore")
            for pins in (cfg.gpio_motor1_pins, cfg.gpio_motor2_pins):
                opened.append(_device(cfg.gpio_driver, list(pins), cfg.pwm_frequency_hz, pin_factory))
    except Exception as error:  # gpiozero's BadPinFactory, GPIOPinInUse, lgpio.error, ImportError
        for device in opened:
            device.close()
        reason = " ".join(f"{type(error).__name__}: {error}".split())
        raise HardwareUnavailable(
            f"motor H-bridge on GPIO {cfg.gpio_motor1_pins} and {cfg.gpio_motor2_pins} cannot be used ({reason}); "
            "check [motors] gpio_motor1_pins/gpio_motor2_pins and that no other program holds them"
        ) from error
    brake_both_high = cfg.gpio_driver == "in1_in2"
    kit = GpioMotorKit(GpioMotor(opened[0], brake_both_high), GpioMotor(opened[1], brake_both_high))
    kit.motor1.throttle = 0.0
    kit.motor2.throttle = 0.0
    return kit
