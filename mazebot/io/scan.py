"""One lidar revolution as numpy arrays: what the lidar driver hands to SLAM."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Scan:
    """One full revolution of the lidar, in the lidar's own frame.

    Angles grow clockwise seen from above on the RPLidar (its datasheet convention);
    ``angle_rad`` here is already converted to the robot convention (counter-clockwise,
    0 = straight ahead), so SLAM never has to know the device's quirks.

    Invalid samples (distance 0 from the device, or quality 0) are kept and flagged in
    ``valid`` rather than dropped, so consumers can count dropouts.
    """

    angle_rad: np.ndarray  # float64, counter-clockwise from the robot's heading
    range_m: np.ndarray  # float64, 0.0 where the device reported no return
    quality: np.ndarray  # uint8, the device's signal quality (0..63 standard, 0/1 express)
    time_s: np.ndarray  # float64, clock time at which each sample was received
    valid: np.ndarray  # bool, sample has a usable range
    revolution: int = 0  # running count of revolutions since the scan started

    def __len__(self) -> int:
        return int(self.angle_rad.shape[0])

    @property
    def start_time_s(self) -> float:
        return float(self.time_s[0]) if len(self) else 0.0

    @property
    def end_time_s(self) -> float:
        return float(self.time_s[-1]) if len(self) else 0.0
