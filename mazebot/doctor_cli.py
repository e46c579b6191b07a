"""``mazebot doctor [--sim [--sim-fault NAME]]``: check every part, one line each; exit 0 when all pass.

On the robot the parts are opened as the daemon opens them (motor driver first, so the
wheels can always be stopped); with ``--sim`` the same checks run on the simulated robot
(:mod:`mazebot.sim.doctor_sim`) through the same drivers: the lidar emulator on a
pseudo-terminal opened as a serial port, the encoders on gpiozero's mock pins, the motors
on the simulator's motor HAT. ``--sim-fault`` breaks one part there, to see its line.

Never run it while ``mazebot run`` drives the robot: both would own the lidar and motors.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
from collections.abc import AsyncIterator
from contextlib import AsyncExitStack
from typing import Any

from mazebot.config import Config, load_config
from mazebot.doctor import (
    Parts,
    SystemProbe,
    Verdict,
    check_serial_port,
    lidar_checks,
    motor_checks,
    passed,
    system_checks,
)
from mazebot.errors import EXIT_OK, MazebotError

#: Exit code when a check failed (EX_UNAVAILABLE would say a device is missing; here any part can fail).
EXIT_FAILED = 1


def _robot_parts(config: Config) -> Parts:
    m = config.motors

    def open_kit() -> Any:
        if m.backend == "gpio":
            from mazebot.io.motor_gpio import open_gpio_motorkit

            return open_gpio_motorkit(m)
        from mazebot.io.motor_hat import open_motorkit

        return open_motorkit(m.i2c_address, m.pwm_frequency_hz)

    def open_pins() -> Any:
        from mazebot.hardware import lgpio_pin_factory

        return lgpio_pin_factory()

    name = (f"GPIO H-bridge ({m.gpio_driver}) on pins {m.gpio_motor1_pins} and {m.gpio_motor2_pins}"
            if m.backend == "gpio" else f"motor HAT at I2C address {m.i2c_address:#04x}")
    return Parts(SystemProbe(), config.lidar, open_kit, name, open_pins)


async def run_checks(config: Config, parts: Parts) -> list[Verdict]:
    """Every check, in the order a maker fixes things; motors braked on every way out."""
    from mazebot.io.encoders import WheelEncoders
    from mazebot.io.motors import DifferentialMotors, MotorWriteError
    from mazebot.io.rplidar import RPLidar
    from mazebot.web.auth import resolve_state_dir

    state_dir = parts.state_dir or resolve_state_dir(config.daemon.state_dir)
    verdicts = system_checks(parts.probe, state_dir)
    async with AsyncExitStack() as stack:
        # the motor board first, and braked at once: whatever else fails, the wheels can be stopped
        motors = None
        try:
            kit = parts.open_kit()
            if hasattr(kit, "close"):
                stack.callback(kit.close)
            motors = DifferentialMotors.from_config(config.motors, kit, parts.clock)
            stack.callback(motors.close)
            verdicts.append(Verdict("motor driver", "ok", f"{parts.kit_name} answers"))
        except (MazebotError, OSError) as exc:
            verdicts.append(Verdict("motor driver", "FAIL", " ".join(str(exc).split()),
                                    "" if isinstance(exc, MotorWriteError)  # its message says what to do
                                    else "seat the HAT, enable I2C (raspi-config) or check [motors] backend and pins"))
        port = check_serial_port(parts.probe, parts.lidar.port)
        verdicts.append(port)
        if port.status == "ok":
            lidar = RPLidar.from_config(parts.lidar, parts.clock, link_factory=parts.link_factory)
            stack.push_async_callback(lidar.close)
            verdicts.extend(await lidar_checks(lidar))
            await lidar.close()  # stops the scan and the lidar's motor before the wheels turn
        else:
            verdicts.extend(Verdict(p, "skip", "no serial port") for p in
                            ("lidar info", "lidar health", "lidar scan modes", "lidar rotation", "lidar revolution"))
        encoders = None
        try:
            pins = parts.open_pins()
            if parts.close_pins:
                stack.callback(pins.close)
            encoders = WheelEncoders.from_config(config.encoders, pins)
            stack.callback(encoders.close)
        except Exception as exc:  # ImportError/lgpio.error off a Pi, a pin taken by another program
            verdicts.append(Verdict("encoders", "FAIL", f"GPIO not available ({type(exc).__name__}: "
                                    f"{' '.join(str(exc).split())})",
                                    "run on the Raspberry Pi with lgpio, with the [encoders] pins free"))
        if motors is not None and encoders is not None:
            try:
                verdicts.extend(await motor_checks(motors, encoders, parts.clock, config.encoders.ticks_per_rev))
            finally:
                motors.stop()
        else:
            verdicts.extend(Verdict(p, "skip", "needs both the motor driver and the encoders")
                            for p in ("motor channels", "left encoder", "right encoder"))
    return verdicts


@contextlib.asynccontextmanager
async def _parts(config: Config, sim: bool, fault: str | None) -> AsyncIterator[Parts]:
    if not sim:
        yield _robot_parts(config)
        return
    from mazebot.sim.doctor_sim import sim_parts

    async with sim_parts(config, fault) as parts:
        yield parts


async def doctor(config: Config, *, sim: bool = False, fault: str | None = None) -> list[Verdict]:
    async with _parts(config, sim, fault) as parts:
        return await run_checks(config, parts)


def _cmd_doctor(args: argparse.Namespace) -> int:
    from mazebot.errors import UsageError

    if args.sim_fault and not args.sim:
        raise UsageError("--sim-fault only makes sense with --sim")
    if args.sim_fault:
        from mazebot.sim.doctor_sim import SIM_FAULTS

        if args.sim_fault not in SIM_FAULTS:
            raise UsageError(f"--sim-fault {args.sim_fault!r}: expected one of {', '.join(SIM_FAULTS)}")
    config = load_config(args.config)
    if args.log_level:
        from mazebot.logs import setup_logging

        setup_logging(args.log_level)
    else:  # the verdict lines say what the drivers' warnings would (a lidar reset, a failed brake)
        logging.getLogger("mazebot").addHandler(logging.NullHandler())
    verdicts = asyncio.run(doctor(config, sim=args.sim, fault=args.sim_fault))
    if args.json:
        print(json.dumps({"passed": passed(verdicts), "checks": [v.as_json() for v in verdicts]}))
    else:
        for v in verdicts:
            print(v.line())
        failed = sum(v.status == "FAIL" for v in verdicts)
        print(f"{'all checks passed' if not failed else f'{failed} check(s) failed'}")
    return EXIT_OK if passed(verdicts) else EXIT_FAILED


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "doctor", help="check every part of the robot, one line each",
        description="Check the serial port, the lidar (info, health, scan modes, rotation, a revolution), "
        "the motor driver, each encoder while its motor is pulsed briefly (sign and channel mapping), the Pi's "
        "under-voltage and throttling flags, CPU temperature, free space and the clock. Exit 0 only when "
        "nothing failed. Do not run it while `mazebot run` is running.",
    )
    p.add_argument("--config", default=None, help="config file (default: the one `mazebot config path` prints)")
    p.add_argument("--sim", action="store_true", help="check the simulated robot instead of the hardware")
    p.add_argument("--sim-fault", default=None, metavar="FAULT",
                   help="with --sim: break one part first (lidar-missing, lidar-silent, lidar-health, lidar-blind, "
                   "lidar-jammed, serial-permission, hat-missing, encoder-dead, encoder-inverted, motors-swapped, "
                   "undervoltage, hot, disk-full, clock-unset)")
    p.add_argument("--log-level", default=None, choices=["debug", "info", "warning", "error"],
                   help="show the drivers' log on stderr too (default: only the verdicts)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_cmd_doctor)
