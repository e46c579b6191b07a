"""A sequential edge carries the submap's own error: a floor under the match's covariance.

A sequential match is the scan registered against the local submap, the last keyframes' scans at
their poses; the pose graph takes it as the edge previous keyframe → this one. ICP's information
(:mod:`mazebot.slam.icp`) is its Hessian over the residuals' variance: it says how well the scan
fits the submap's points, not where the submap's walls are. They sit where the chain put the
keyframes that saw them, off by those keyframes' own errors, and every point of the scan moves
with them. So the edge's covariance is the match's plus the submap's, ``Σ' = Σ + F`` with
``F = diag(σ_m², σ_m², σ_θ²)`` (the measurement's covariance propagated into the estimate as in
Censi, "An accurate closed-form estimate of ICP's covariance", ICRA 2007: the submap's placement is
an input the Hessian holds fixed).

Measured on the ACES log at ``--odom-noise 0.05,0.05`` seed 2 against its corrected poses: the
sequential edges whose match fixed every direction claim a median heading std of 0.13° and err by
0.50° RMS; those left degenerate in a corridor claim 0.21° and err by 0.38° (along the corridor their
information is the odometry's and honest: 1.1 std RMS). A loop's mismatch is then placed on the
headings of the degenerate edges, the least sure, as a turn of the corridor, where it belongs on
every edge alike. A floor evens the headings' weights out.

In information form, defined for a singular ``Ω`` too (a degenerate match):
``Ω' = (Σ + F)⁻¹ = Ω (I + F Ω)⁻¹``.
"""

from __future__ import annotations

import numpy as np


def with_covariance_floor(information: np.ndarray, floor_std_m: float, floor_std_rad: float) -> np.ndarray:
    """``information`` (3×3, x y θ in the edge's frame) whose covariance has ``floor_std_m``² more on each
    position axis and ``floor_std_rad``² more on the heading (the module's docstring)."""
    omega = np.asarray(information, dtype=np.float64)
    if floor_std_m <= 0.0 and floor_std_rad <= 0.0:
        return omega.copy()
    floor = np.diag([floor_std_m**2, floor_std_m**2, floor_std_rad**2])
    out = omega @ np.linalg.inv(np.eye(3) + floor @ omega)
    return 0.5 * (out + out.T)
