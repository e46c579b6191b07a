"""The submaps' far walls kept (``[slam.normals] pool_far_normals_beyond_m``) on a place seen again.

The Intel log with ``--odom-noise 0.1,0.1``: after its first loop (scans 12-95) the robot comes
back to its start. With the far walls kept the chain has drifted only 0.1-0.4 m and 1-2° by then,
and the sequential submap holds the start's keyframes (near the robot) beside the recent ones: two
passes that no loop closure has made agree yet. The match of scan 97 or 98 snaps onto the earlier
pass, and the sequential edge into it takes the loop's drift as a step (1.1-2.0° and 0.1-0.5 m off
the corrected poses' increment on seeds 1, 3 and 4) with the information of a good match; the
loop closures that follow cannot undo it, and the finished map stays bent after its start.
``pool_far_normals_one_pass`` leaves the earlier pass out of the sequential submap until a loop
closure from a recent keyframe has joined it: the edges follow the increment.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from mazebot.config import load_config
from mazebot.geometry import relative_pose, wrap_angle
from mazebot.slam.carmen import read_carmen
from mazebot.slam.slam import Slam, SlamParams
from mazebot.slam.slam_cli import from_first_pose, laser_log_params, log_updates, noisy_odometry
from tests.data_paths import carmen_log

#: the scans back at the start whose sequential edges took the jump
BACK_AT_START = (97, 98)


def sequential_edge_errors(seed: int, one_pass: bool) -> list[tuple[float, float]]:
    """``(metres, degrees)`` off the corrected relative pose of the sequential edges into ``BACK_AT_START``
    (``slam run``'s laser-log settings, the far hits pooled beyond 4 m)."""
    lasers = read_carmen(carmen_log("intel.gfs.log")).lasers[: max(BACK_AT_START) + 1]
    reference = np.array([r.pose for r in lasers])
    odometry = noisy_odometry(reference, 0.1, 0.1, np.random.default_rng(seed))
    config = load_config(None)
    params = laser_log_params(SlamParams.from_config(config.slam, config.lidar))
    normals = replace(params.normals, pool_far_normals_beyond_m=4.0, pool_far_normals_one_pass=one_pass)
    slam = Slam(replace(params, normals=normals), initial_pose=np.zeros(3))
    scan_of = {}
    for k, update in enumerate(log_updates(slam, lasers, from_first_pose(odometry, reference))):
        if update.keyframe is not None:
            scan_of[update.keyframe] = k
    ei, ej, z, _ = slam.graph.edge_arrays
    errors = []
    for i, j, measured in zip(ei, ej, z, strict=True):
        if j == i + 1 and scan_of[int(j)] in BACK_AT_START:
            off = measured - relative_pose(reference[scan_of[int(i)]], reference[scan_of[int(j)]])
            errors.append((math.hypot(off[0], off[1]), math.degrees(abs(wrap_angle(off[2])))))
    return errors


@pytest.mark.parametrize("seed", [1, 3, 4])
def test_back_at_the_start_the_sequential_edges_keep_to_the_increment_with_the_far_walls_kept(seed: int) -> None:
    """Within 5 cm and 0.5° of the corrected increment (the corrected poses scatter by about 1.5 cm
    and 0.45° a scan; here within 3 cm and 0.15°); with the earlier pass in the sequential submap
    seed 1 is 0.11 m and 1.1°, seed 3 0.36 m and 1.3°, seed 4 0.48 m and 2.0° off."""
    errors = sequential_edge_errors(seed, one_pass=True)
    assert len(errors) == len(BACK_AT_START)
    for metres, degrees in errors:
        assert metres < 0.05 and degrees < 0.5, errors
