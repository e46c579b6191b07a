"""How close `mazebot calibrate --sim` comes to the simulated robot's true build, over seeds.

The true robot differs from its config: wheels 3 % and 2 % larger, track 6 % wider, the
lidar turned 3° on its mount, the left encoder backwards, the motor channels swapped.
Prints one line per seed: each recovered value's error against the truth.

    .venv/bin/python bench/calibration_accuracy.py 1 2 3
"""

from __future__ import annotations

import sys

from mazebot.calibration.progress import Progress
from mazebot.calibration.result import calibrated_config
from mazebot.calibration.routine import STEPS
from mazebot.calibration_cli import run_calibration
from mazebot.config import Config


def main(seeds: list[int]) -> None:
    for seed in seeds:
        config = Config()
        sim = config.sim
        sim.seed = seed
        sim.wheel_diameter_left_scale, sim.wheel_diameter_right_scale, sim.track_width_scale = 1.03, 1.02, 1.06
        sim.lidar_mount_yaw_error_deg = 3.0
        sim.left_encoder_reversed = sim.motor_channels_swapped = True
        new = calibrated_config(config, run_calibration(config, Progress(STEPS), sim=True))
        d, ratio = new.drive.wheel_diameter_m, new.drive.wheel_diameter_ratio
        left_m, right_m = d * 2 / (1 + ratio), d * 2 * ratio / (1 + ratio)
        wiring_ok = (new.motors.left_channel, new.motors.right_channel, new.encoders.left_invert) == (2, 1, True)
        print(
            f"seed {seed}: left wheel {left_m / (0.065 * 1.03) - 1:+.3%}, "
            f"right wheel {right_m / (0.065 * 1.02) - 1:+.3%}, "
            f"track {new.drive.track_width_m / 0.159 - 1:+.3%}, yaw {new.lidar.mount_yaw_deg - 3.0:+.3f}°, "
            f"deadband {new.control.motor_deadband} (true 0.08), wiring {'fixed' if wiring_ok else 'WRONG'}",
            flush=True,
        )


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or [1, 2, 3])
