"""How well each scan sits in the map the other scans make: a figure that needs no reference.

The laser logs' corrected poses are another SLAM system's output, with errors of their
own, so the errors against them mix two systems' mistakes. This module measures a
trajectory by itself: for a scan ``k`` it builds a target from the other scans at their
poses (those more than ``exclude`` scans away in the log, within ``radius_m``: the map
the robot saw there before and after, not the neighbours it was matched with) and
registers scan ``k`` against it with the SLAM's own point-to-line ICP, starting at its
pose. The correction ICP finds, ``pose_k⁻¹ ∘ registered``, is how far the scan sits from
where the rest of the map says it should: near zero for a crisp map, a doubled wall or a
map bent along a corridor shows as corrections of its heading and position.

Run on the SLAM's trajectory and on the log's corrected poses with the same scans, it
tells whether a disagreement between the two is the SLAM's or the reference's: on the
Radish logs (branch ``reallogs3``) the corrected poses sit 0.3° RMS off their own map,
the SLAM's 0.08-0.12°, and Freiburg 101's first corrected pose is 0.6° off it.

It is the idea of a map's self-consistency used to judge laser SLAM without ground truth
(compare the "relations" of Kümmerle et al., "On measuring the accuracy of SLAM
algorithms", Autonomous Robots 2009, which are scan-to-scan matches checked by hand).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mazebot.geometry import relative_pose
from mazebot.slam.icp import IcpResult, Target, match_scan
from mazebot.slam.preprocess import voxel_downsample
from mazebot.slam_config import IcpParams


@dataclass(frozen=True)
class Neighbourhood:
    """The map a scan is registered against: which other scans make it, and how their points are thinned.

    The scans more than ``exclude`` away in the log (not the neighbours it was matched
    with), the ``max_scans`` nearest within ``radius_m``, at least ``min_scans`` of them;
    points thinned to one per ``voxel_m`` voxel, normals over ``normal_radius_m``.
    """

    exclude: int = 3
    radius_m: float = 10.0
    voxel_m: float = 0.05
    normal_radius_m: float = 0.3
    max_scans: int = 40
    min_scans: int = 5


def scan_corrections(
    poses: np.ndarray,
    scans_xy: Sequence[np.ndarray],
    judged: Sequence[int],
    icp: IcpParams,
    around: Neighbourhood = Neighbourhood(),
    *,
    min_fitness: float = 0.7,
) -> np.ndarray:
    """The ICP correction ``(dx_m, dy_m, dθ_rad)`` (in scan ``k``'s frame) of every judged scan ``k``.

    ``poses`` (N, 3) are the scans' poses (of the sensor), ``scans_xy`` their points in the
    sensor frame. A scan with too few others ``around`` it, or whose registration did not
    converge to at least ``min_fitness`` inliers, is left out (a corridor seen once has
    nothing to be consistent with). Returns (M, 4): the scan's index and its correction.
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    if len(scans_xy) != poses.shape[0]:
        raise ValueError(f"{poses.shape[0]} poses but {len(scans_xy)} scans")
    thinned = thin_scans(scans_xy, around.voxel_m)
    out = []
    for k in judged:
        found = register_scan(poses, thinned, k, icp, around)
        if found is None or not found.converged or found.fitness < min_fitness:
            continue
        out.append((float(k), *relative_pose(poses[k], found.pose)))
    return np.array(out, dtype=np.float64).reshape(-1, 4)


def thin_scans(scans_xy: Sequence[np.ndarray], voxel_m: float) -> list[np.ndarray]:
    """Each scan's points (sensor frame) thinned to one per ``voxel_m`` voxel, as :func:`register_scan` takes them."""
    thinned = [np.asarray(s, dtype=np.float64).reshape(-1, 2) for s in scans_xy]
    return [s[voxel_downsample(s, voxel_m)] for s in thinned]


def register_scan(
    poses: np.ndarray, thinned: Sequence[np.ndarray], k: int, icp: IcpParams, around: Neighbourhood = Neighbourhood()
) -> IcpResult | None:
    """Scan ``k`` registered by ICP against the map of the others ``around`` it at ``poses``, from its own pose.

    None when too few others are there (or scan ``k`` has no points). ``thinned`` are the
    scans of :func:`thin_scans`. The result (map frame) says by its information which
    directions the map fixes the scan in (``degenerate``: one it does not, along a corridor).
    """
    distance = np.hypot(poses[:, 0] - poses[k, 0], poses[:, 1] - poses[k, 1])
    far_in_log = np.abs(np.arange(poses.shape[0]) - k) > around.exclude
    near = np.flatnonzero((distance < around.radius_m) & far_in_log)
    near = near[np.argsort(distance[near], kind="stable")[: around.max_scans]]
    sensor = np.zeros(2)
    others = [(poses[j], thinned[j], sensor) for j in sorted(near.tolist()) if thinned[j].shape[0]]
    if len(others) < around.min_scans or thinned[k].shape[0] == 0:
        return None
    target = Target.from_scans(others, voxel_size_m=around.voxel_m, normal_radius_m=around.normal_radius_m)
    return match_scan(target, thinned[k], poses[k], icp, sensor_xy=sensor)


def consistency(corrections: np.ndarray) -> dict[str, float]:
    """Summary of :func:`scan_corrections`: heading RMS / p90 (°), shift RMS / p90 (m), scans judged."""
    c = np.asarray(corrections, dtype=np.float64).reshape(-1, 4)
    if c.shape[0] == 0:
        nan = float("nan")
        return {"heading_rms_deg": nan, "heading_p90_deg": nan, "shift_rms_m": nan, "shift_p90_m": nan, "scans": 0}
    heading = np.degrees(np.abs(c[:, 3]))
    shift = np.hypot(c[:, 1], c[:, 2])
    return {
        "heading_rms_deg": round(float(np.sqrt(np.mean(heading**2))), 3),
        "heading_p90_deg": round(float(np.percentile(heading, 90)), 3),
        "shift_rms_m": round(float(np.sqrt(np.mean(shift**2))), 4),
        "shift_p90_m": round(float(np.percentile(shift, 90)), 4),
        "scans": int(c.shape[0]),
    }


def judged_scans(count: int, at_most: int) -> list[int]:
    """Every scan's index if there are at most ``at_most``, else ``at_most`` spread evenly (the first always)."""
    if count <= at_most:
        return list(range(count))
    return sorted({round(i * (count - 1) / (at_most - 1)) for i in range(at_most)})


def first_scan_heading_deg(corrections: np.ndarray) -> float | None:
    """The heading correction (°) the map asks of the first scan, where the map frame is anchored (None: not judged)."""
    c = np.asarray(corrections, dtype=np.float64).reshape(-1, 4)
    first = c[c[:, 0] == 0]
    return None if first.shape[0] == 0 else round(math.degrees(float(first[0, 3])), 3)
