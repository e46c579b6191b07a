"""``mazebot calibrate [--sim] [--write]``: guided calibration with the lidar as the ruler."""

from __future__ import annotations

import argparse
import asyncio
import sys
from contextlib import AsyncExitStack
from pathlib import Path
from typing import Any

from mazebot.errors import EXIT_OK, UsageError

HELP = "measure wiring, wheel sizes, track width and lidar yaw with the lidar as the ruler"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "calibrate", help=HELP,
        description="Put the robot in an open space (walls within a few metres, 1 m free ahead: the straight "
                    "runs go 0.8 m out and back). It pulses each motor, ramps the throttle, drives straight and "
                    "turns in place, "
                    "measuring each motion by scan matching, and prints the config changes. "
                    "With --sim, the simulated robot in the room world (its true wiring and sizes are [sim] keys).",
    )
    p.add_argument("--config", default=None, help="config file (default: the one `mazebot config path` prints)")
    p.add_argument("--sim", action="store_true", help="calibrate the simulated robot (virtual clock)")
    p.add_argument("--write", action="store_true",
                   help="write the calibrated config to the config file (atomically, the old one kept as .bak)")
    p.add_argument("--out", default="calibration", help="folder of the report (calibration.json, calibration.png)")
    p.set_defaults(func=_cmd_calibrate)


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from mazebot.calibration.progress import Progress
    from mazebot.calibration.result import (
        calibrated_config,
        config_diff,
        report_json,
        report_png,
        write_calibrated_config,
    )
    from mazebot.calibration.routine import STEPS
    from mazebot.config import default_config_path, load_config
    from mazebot.files import write_atomic

    path = Path(args.config) if args.config else default_config_path()
    config = load_config(path)
    printed: dict[str, tuple[str, str]] = {}
    progress = Progress(STEPS, on_change=lambda step: _print_step(progress, step, printed))
    result = run_calibration(config, progress, sim=args.sim)
    new = calibrated_config(config, result)
    diff = config_diff(config, new)
    out = Path(args.out)
    write_atomic(out / "calibration.json", report_json(result, diff, progress.as_json()))
    write_atomic(out / "calibration.png", report_png(result))
    print("changes:" if diff else "no changes: the config matches the robot")
    for key, old, value in diff:
        print(f"  {key}: {old!r} -> {value!r}")
    print(f"report: {out / 'calibration.json'}, {out / 'calibration.png'}")
    if args.write:
        target = path or Path("config.toml")
        backup = write_calibrated_config(target, config, new, sim=args.sim)
        print(f"written: {target}" + (f" (the old one: {backup})" if backup is not None else ""))
    return EXIT_OK


def _print_step(progress: Any, step: Any, printed: dict[str, tuple[str, str]]) -> None:
    """One line per change of a step's state or detail (a new figure alone is in the report)."""
    if printed.get(step.name) == (step.state, step.detail):
        return
    printed[step.name] = (step.state, step.detail)
    n, total = progress.index(step.name), len(progress.steps)
    line = f"[{n}/{total}] {step.title}: {step.state}"
    if step.detail:
        line += f" - {step.detail}"
    print(line, file=sys.stdout, flush=True)


def run_calibration(config: Any, progress: Any, *, sim: bool) -> Any:
    """Open the hardware (simulated on the virtual clock, or the robot's), run the routine, close it all."""
    from mazebot.calibration.routine import Calibrator
    from mazebot.clock import RealClock

    if sim:
        from mazebot.sim.backend import sim_hardware_builder
        from mazebot.sim.virtual_time import run_virtual

        config = config.model_copy(deep=True)
        if config.sim.world != "room":
            config.sim.world = "room"  # a maze's 1 ft cells leave no room for straight runs
        builder = sim_hardware_builder()
    else:
        from mazebot.main import robot_hardware_builder

        builder = robot_hardware_builder()

    async def main() -> Any:
        clock = RealClock()
        async with AsyncExitStack() as stack:
            hw = await builder(config, clock, stack)
            tasks = [asyncio.create_task(factory(), name=name) for name, factory in hw.extra_tasks]
            try:
                return await Calibrator(hw, config, clock, progress).run()
            finally:
                hw.motors.stop()
                for task in tasks:
                    task.cancel()
                await asyncio.gather(*tasks, return_exceptions=True)

    if sim:
        return run_virtual(main())
    if config.motors.backend == "fake":
        raise UsageError("[motors] backend is fake: nothing to calibrate; use --sim")
    return asyncio.run(main())
