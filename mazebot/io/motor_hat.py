"""The Adafruit DC & Stepper Motor HAT itself: its four channels and how to open it.

Kept apart from :mod:`mazebot.io.motors` (the differential drive with its safety rules,
which needs asyncio and the config models) so that ``mazebot motors stop``, the
safety net systemd runs after every exit of the daemon, imports next to nothing
before it writes the zero throttles.
"""

from __future__ import annotations

from typing import Final, Protocol

from mazebot.errors import HardwareUnavailable

#: The HAT's DC motor terminals M1-M4 (``kit.motor1`` ... ``kit.motor4``).
CHANNELS: Final = (1, 2, 3, 4)


class MotorLike(Protocol):
    """One DC motor: ``throttle`` in [-1, 1], 0 brakes, ``None`` coasts."""

    throttle: float | None


class MotorKitLike(Protocol):
    """Anything shaped like ``adafruit_motorkit.MotorKit`` for DC motors."""

    @property
    def motor1(self) -> MotorLike: ...

    @property
    def motor2(self) -> MotorLike: ...

    @property
    def motor3(self) -> MotorLike: ...

    @property
    def motor4(self) -> MotorLike: ...


def open_motorkit(i2c_address: int, pwm_frequency_hz: float) -> MotorKitLike:
    """Open the real motor HAT over I²C.

    Imports ``adafruit_motorkit`` here, not at module import: it imports Blinka's
    ``board``, which fails on anything but a supported board. Every way this fails
    off a Pi or without a HAT (no ``board`` support, no I²C bus, nothing answering at
    the address) becomes one :class:`HardwareUnavailable` line. ``AttributeError`` is
    included because Blinka on an unrecognised Linux machine imports fine but has no
    ``board.I2C``.
    """
    try:
        from adafruit_motorkit import MotorKit

        kit: MotorKitLike = MotorKit(address=i2c_address, pwm_frequency=pwm_frequency_hz)
        return kit
    except (ImportError, OSError, RuntimeError, ValueError, AttributeError) as error:
        reason = " ".join(f"{type(error).__name__}: {error}".split())
        raise HardwareUnavailable(
            f"motor HAT not found at I2C address 0x{i2c_address:02x} ({reason}); "
            "check the HAT is seated and I2C is enabled (raspi-config)"
        ) from error
