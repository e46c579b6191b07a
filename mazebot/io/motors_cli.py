"""``mazebot motors stop``: zero every channel of the motor HAT, whatever left them running.

The systemd unit runs it after every exit of the daemon (``ExecStopPost``), so a
process that died without its ``finally`` blocks still leaves the wheels stopped.
"""

from __future__ import annotations

import argparse

from mazebot.config import load_config
from mazebot.errors import EXIT_OK
from mazebot.io.motors import CHANNELS, open_motorkit


def _cmd_stop(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    kit = open_motorkit(config.motors.i2c_address, config.motors.pwm_frequency_hz)
    for channel in CHANNELS:  # all four: a miswired config must not leave one turning
        getattr(kit, f"motor{channel}").throttle = 0.0
    print(f"motors stopped (HAT at I2C address 0x{config.motors.i2c_address:02x})")
    return EXIT_OK


def register(sub: argparse._SubParsersAction) -> None:
    motors = sub.add_parser("motors", help="direct motor HAT commands")
    msub = motors.add_subparsers(dest="motors_command", required=True)
    stop = msub.add_parser("stop", help="zero every motor channel of the HAT")
    stop.add_argument("--config", default=None, help="config file (for the HAT's I2C address)")
    stop.set_defaults(func=_cmd_stop)
