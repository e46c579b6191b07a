"""``mazebot motors stop``: zero every channel of the motor HAT, whatever left them running.

The systemd unit runs it after every exit of the daemon (``ExecStopPost``), so a
process that died without its ``finally`` blocks still leaves the wheels stopped. It
must be quick and must not fail for a reason that has nothing to do with the HAT: it
imports only the motor driver and the ``[motors]`` section of the config (never numpy,
scipy or the SLAM; a test checks), and a config it cannot use still gets the HAT at the
default address zeroed before the problem is reported.
"""

from __future__ import annotations

import argparse
import sys

from mazebot.errors import EXIT_OK, ConfigError


def _cmd_stop(args: argparse.Namespace) -> int:
    from mazebot.io.motor_hat import CHANNELS, open_motorkit
    from mazebot.logs import error_line
    from mazebot.motors_config import MotorsConfig, load_motors_config

    problem: ConfigError | None = None
    try:
        motors = load_motors_config(args.config)
    except ConfigError as exc:
        problem = exc
        motors = MotorsConfig()
        print(error_line(f"mazebot: {exc}; stopping the HAT at the default I2C address 0x{motors.i2c_address:02x}"),
              file=sys.stderr)
    if motors.backend == "gpio":
        from mazebot.io.motor_gpio import open_gpio_motorkit

        open_gpio_motorkit(motors).close()  # both channels braked, then the pins released
        print(f"motors stopped (H-bridge on GPIO {motors.gpio_motor1_pins} and {motors.gpio_motor2_pins})")
        return problem.exit_code if problem is not None else EXIT_OK
    kit = open_motorkit(motors.i2c_address, motors.pwm_frequency_hz)
    for channel in CHANNELS:  # all four: a miswired config must not leave one turning
        getattr(kit, f"motor{channel}").throttle = 0.0
    print(f"motors stopped (HAT at I2C address 0x{motors.i2c_address:02x})")
    return problem.exit_code if problem is not None else EXIT_OK


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    motors = sub.add_parser("motors", help="direct motor HAT commands",
                            description="Direct commands to the Adafruit DC & Stepper Motor HAT.")
    msub = motors.add_subparsers(dest="motors_command", required=True, metavar="{stop}")
    stop = msub.add_parser("stop", help="zero every motor channel of the HAT (or of the GPIO H-bridge)",
                           description="Zero all four motor channels of the HAT (the systemd unit runs this "
                                       "after every exit of the daemon). Reads only [motors] of the config.")
    stop.add_argument("--config", default=None, metavar="PATH",
                      help="config file, for [motors] i2c_address and pwm_frequency_hz "
                           "(default: the one `mazebot config path` prints)")
    stop.set_defaults(func=_cmd_stop)
