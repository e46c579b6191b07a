"""Beam endpoints moved along their beams onto the wall they hit: range noise averaged out of the map.

The A1's range noise is about 1 % of the range (3 mm at 30 cm, 1 cm at 1 m). The
occupancy grid marks the 2 cm cell each endpoint falls in, and within one scan a hit
wins over the misses of every other beam crossing that cell (:mod:`mazebot.slam.grid`).
So when a wall face lies a few millimetres behind a cell edge, some of the eight or so
beams that hit it from close by fall short into the free cell in front in nearly every
scan, and that cell ends up occupied: the wall shows two cells thick and the free space
stops a cell short of it (the bench's coverage figure missed exactly those cells).

A beam's bearing is precise (the head's angle encoder) and its range is not, so each
hit is moved *along its own beam* onto the line fitted through its neighbours: the
``half_window`` samples on either side in scan order (neighbouring beams, so the same
face seen from the same place), those within ``radius_m`` of it, by principal component
analysis. The line averages the noise of about ``2 * half_window + 1`` ranges, so the
endpoint scatter shrinks by about the square root of that (moving least squares reduced
to lines: Alexa et al., "Computing and rendering point set surfaces", IEEE TVCG 2003;
the same idea as :func:`mazebot.slam.keyframes.smooth_onto_lines` for the ICP submap,
done here along the beam and with scan-order neighbours, which needs no kd-tree).

A hit keeps its measured range when its neighbourhood is not a line (a corner, the edge
of an occlusion, fewer than ``min_neighbours`` points), when the beam meets the line at
a grazing angle (``|cos| < min_cos_incidence``: a small error of the line's direction
would move the endpoint far along the beam), or when the move would exceed
``max_shift_m`` (a fit that is wrong rather than noisy).
"""

from __future__ import annotations

import numpy as np

from mazebot.slam_config import EndpointSmoothing as EndpointSmoothing  # the [slam.smoothing] section


def smooth_endpoints(
    points_xy: np.ndarray, origins_xy: np.ndarray, params: EndpointSmoothing | None = None, circular: bool = True
) -> np.ndarray:
    """Hits (N, 2) in scan order, each moved along its beam from ``origins_xy`` (N, 2) onto its local line.

    ``circular``: the hits are one full turn of the head, so the first and last are
    neighbours. Returns a new array; hits that cannot be fitted keep their position.
    """
    p = params or EndpointSmoothing()
    pts = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    origins = np.asarray(origins_xy, dtype=np.float64).reshape(-1, 2)
    n = pts.shape[0]
    if n < p.min_neighbours:
        return pts.copy()
    offsets = np.arange(-p.half_window, p.half_window + 1)
    idx = np.arange(n)[:, None] + offsets[None, :]
    inside = np.ones(idx.shape, dtype=bool)
    if circular:
        idx %= n
    else:
        inside = (idx >= 0) & (idx < n)
        idx = idx.clip(0, n - 1)
    nb = pts[idx]  # (N, W, 2)
    gap = nb - pts[:, None, :]
    near = inside & (gap[..., 0] * gap[..., 0] + gap[..., 1] * gap[..., 1] <= p.radius_m**2)
    w = near.astype(np.float64)
    count = w.sum(axis=1)
    mean = np.einsum("nw,nwd->nd", w, nb) / np.maximum(count, 1.0)[:, None]
    d = (nb - mean[:, None, :]) * w[:, :, None]
    cxx = np.einsum("nw,nw->n", d[..., 0], d[..., 0])
    cyy = np.einsum("nw,nw->n", d[..., 1], d[..., 1])
    cxy = np.einsum("nw,nw->n", d[..., 0], d[..., 1])
    phi = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy)  # direction of the line
    normal = np.column_stack((-np.sin(phi), np.cos(phi)))
    half_trace = 0.5 * (cxx + cyy)
    root = np.sqrt((0.5 * (cxx - cyy)) ** 2 + cxy**2)
    lam_max, lam_min = half_trace + root, half_trace - root
    line = (count >= p.min_neighbours) & (lam_min <= p.max_line_spread * np.maximum(lam_max, 1e-18))

    # the beam o + t u meets the line n·(x - mean) = 0 at t = n·(mean - o) / n·u
    beam = pts - origins
    range_m = np.hypot(beam[:, 0], beam[:, 1])
    u = beam / np.maximum(range_m, 1e-12)[:, None]
    cos_inc = np.einsum("nd,nd->n", normal, u)
    steep = np.abs(cos_inc) >= p.min_cos_incidence
    t = np.einsum("nd,nd->n", normal, mean - origins) / np.where(steep, cos_inc, 1.0)
    ok = line & steep & (np.abs(t - range_m) <= p.max_shift_m) & (range_m > 0)
    out = pts.copy()
    out[ok] = origins[ok] + u[ok] * t[ok, None]
    return out
