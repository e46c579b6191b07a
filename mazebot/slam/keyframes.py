"""Keyframes and the local submap ICP matches each new scan against.

A **keyframe** is a scan SLAM keeps: a vertex of the pose graph, a source of the local
submap and of loop closures, and what the occupancy grid is rebuilt from after a loop
closure moved the poses. A scan becomes a keyframe when the robot has moved
``distance_m`` (0.10 m) or turned ``angle_rad`` (0.15 rad) since the last one: the
coarse defaults of ROS packages (0.5 m, 0.5 rad) are longer than a 1 ft maze cell.

Each keyframe stores its points in its own robot frame (so moving its pose moves them),
surface normals estimated once from its own scan (PCA of neighbours, as
:func:`mazebot.slam.icp.estimate_normals`), and its rays for the grid, in int16 quarter
millimetres (:data:`POINT_STEP_M`).

The **local submap** is the union of the last ``size`` keyframes in the map frame,
thinned to one point per ``voxel_m`` square (the one nearest its centre), with their normals: a
:class:`mazebot.slam.icp.Target`. Normals come precomputed, so building the target is a
transform, a voxel filter and a kd-tree (about a millisecond), done once per keyframe
(KISS-ICP's local map, Vizzo et al., RA-L 2023, with keyframes instead of a sliding
voxel map).
"""

from __future__ import annotations

import math
from collections.abc import Generator, Sequence
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from mazebot.geometry import relative_pose
from mazebot.slam.endpoint_smoothing import EndpointSmoothing, smooth_endpoints
from mazebot.slam.icp import Target, estimate_normals
from mazebot.slam.preprocess import PreparedScan, voxel_downsample
from mazebot.slam.wall_faces import NO_FACES, Faces, wall_faces
from mazebot.slam.wall_lattice import LatticeFaces, LatticeParams, measure_faces
from mazebot.slam_config import NormalParams as NormalParams  # the [slam.normals] section
from mazebot.steps import all_at_once

#: A keyframe's wall faces are measured again when its heading on the wall grid changed by more
#: than this (a few millimetres at the farthest face used, 1.2 m; smaller changes are followed to first order).
LATTICE_REMEASURE_RAD = 0.005


#: Keyframe coordinates (robot frame) are kept as int16 multiples of this: a quarter of a
#: millimetre, the RPLidar's own range unit (``dist_q2`` of its protocol: Slamtec, RPLIDAR
#: interface protocol), for ±8.19 m, which covers SLAM's ``[slam.prepare] max_range_m`` (8 m).
#: A keyframe with a coordinate beyond that keeps its points in float32. Each keyframe is kept
#: by the daemon and by its loop-closure worker, a thousand or more per 16×16 maze: in float32
#: they were most of what the robot's memory grew by (~13 kB a keyframe in each process).
#: The rounding (0.07 mm RMS) is twenty times below the A1's range noise (1 % of the range),
#: so the walls' directions and positions, averaged over many points, keep their precision
#: (a millimetre's grid did not: it pulled a wall that runs along an axis onto the grid).
POINT_STEP_M = 0.00025
#: Unit normals are kept in int16 as multiples of this (a direction to 2e-3 degrees).
NORMAL_STEP = 1.0 / 32767.0
_INT16_MAX = 32767
_NO_POINTS = np.zeros((0, 2), dtype=np.int16)


def pack(values: np.ndarray, step: float) -> np.ndarray:
    """``values`` as int16 multiples of ``step`` (nearest) if all fit, else as float32."""
    v = np.asarray(values, dtype=np.float64)
    q = np.rint(v / step)
    if q.size and float(np.max(np.abs(q))) > _INT16_MAX:
        return v.astype(np.float32)
    return q.astype(np.int16)


def unpack(packed: np.ndarray, step: float) -> np.ndarray:
    """The float64 values of :func:`pack`'s output."""
    if packed.dtype == np.int16:
        return packed * step
    return packed.astype(np.float64)


def unpack_all(packed: Sequence[np.ndarray], step: float) -> np.ndarray:
    """The float64 values of several :func:`pack` outputs, concatenated: one multiplication if all are int16."""
    if all(part.dtype == np.int16 for part in packed):
        return np.concatenate(packed) * step
    return np.concatenate([unpack(part, step) for part in packed])


class Keyframe:
    """One kept scan, everything in its own robot frame; ``pose`` (3,) is its map-frame pose.

    Its points are stored as int16 quarter millimetres and its normals in int16 too (see
    :data:`POINT_STEP_M`: a few thousand keyframes, each kept in two processes, must fit a
    Raspberry Pi's memory). The properties give them back in float64 metres. ``hits`` (H, 2)
    are the scan's hits; ``points``
    (N, 2) and ``normals`` (N, 2) the hits with a usable normal, smoothed onto their local
    line (for the local submap), estimated the first time they are asked for: a keyframe
    made during an in-place turn often waits for the next submap, and the scan that made
    it stays cheap. ``match_points`` (M, 2) are the voxel-downsampled hits (source of loop
    closure ICP), ``sensor_xy`` (2,) the lidar centre; ``ray_ends`` (K, 2) and
    ``ray_hit`` (K,) the beams for the grid (the flags kept as bits). A rebuilt map starts every beam at the
    lidar's position at the end of the revolution (the live map used each sample's own,
    de-skewed origin; the difference, the robot's motion during one turn of the head,
    only touches cells under the robot).
    ``integrated_pose`` is the pose its rays were last written into the grid with.

    Slots instead of an instance dict: ~0.6 kB less per keyframe.
    """

    __slots__ = (
        "_bare",
        "_faces",
        "_hits",
        "_lattice",
        "_match",
        "_ray_count",
        "_ray_ends",
        "_ray_hit_bits",
        "_surface",
        "_walls",
        "index",
        "integrated_pose",
        "normal_params",
        "pose",
        "sensor_xy",
        "time_s",
    )

    def __init__(
        self,
        index: int,
        time_s: float,
        pose: np.ndarray,
        hits: np.ndarray,
        match_points: np.ndarray,
        sensor_xy: np.ndarray,
        ray_ends: np.ndarray,
        ray_hit: np.ndarray,
        integrated_pose: np.ndarray,
        normal_params: NormalParams | None = None,
    ) -> None:
        self.index = index
        self.time_s = time_s
        self.pose = pose
        self._hits = pack(np.asarray(hits).reshape(-1, 2), POINT_STEP_M)
        self._match = pack(np.asarray(match_points).reshape(-1, 2), POINT_STEP_M)
        self.sensor_xy = sensor_xy
        self._ray_ends = pack(np.asarray(ray_ends).reshape(-1, 2), POINT_STEP_M)
        flags = np.asarray(ray_hit, dtype=bool).reshape(-1)
        self._ray_hit_bits = np.packbits(flags)
        self._ray_count = int(flags.shape[0])
        self.integrated_pose = integrated_pose
        self.normal_params = normal_params or NormalParams()
        #: (points, normals) packed (:func:`pack`), once computed
        self._surface: tuple[np.ndarray, np.ndarray] | None = None
        #: the hits without a normal of their own, packed, computed with the surface if ``pool_far_normals_beyond_m``
        self._bare: np.ndarray | None = None
        self._walls: tuple[float, float, int] | None = None
        self._lattice: LatticeFaces | None = None
        self._faces: Faces | None = None

    def keep_surface_only(self) -> None:
        """Let go of the hits once the surface has been made from them.

        For the loop-closure worker's replica: its jobs read the surface, the match points
        and the rays, never the hits again (the daemon keeps them, to save the run).
        """
        if self._surface is not None:
            self._hits = _NO_POINTS

    def packed(self) -> dict[str, np.ndarray]:
        """The arrays it keeps, as kept (int16 or float32, the ray flags as bits), by name.

        For :mod:`mazebot.slam.shared_keyframes`, which moves them into shared memory; the
        surface's two arrays are there once it is computed.
        """
        arrays = {"hits": self._hits, "match": self._match, "ray_ends": self._ray_ends,
                  "ray_hit_bits": self._ray_hit_bits}
        if self._surface is not None:
            arrays["surface_points"], arrays["surface_normals"] = self._surface
        if self._bare is not None:
            arrays["bare_hits"] = self._bare
        return arrays

    def use_packed(self, arrays: dict[str, np.ndarray]) -> None:
        """Hold these arrays (named as :meth:`packed` names them, the same values) instead of its own."""
        self._hits = arrays.get("hits", self._hits)
        self._match = arrays.get("match", self._match)
        self._ray_ends = arrays.get("ray_ends", self._ray_ends)
        self._ray_hit_bits = arrays.get("ray_hit_bits", self._ray_hit_bits)
        if "surface_points" in arrays and "surface_normals" in arrays:
            self._surface = (arrays["surface_points"], arrays["surface_normals"])
        self._bare = arrays.get("bare_hits", self._bare)

    def caches(self) -> dict[str, Any]:
        """What it has computed from its arrays besides the surface (wall direction, lattice faces)."""
        return {"walls": self._walls, "lattice": self._lattice}

    def use_caches(self, caches: dict[str, Any]) -> None:
        self._walls = caches.get("walls")
        self._lattice = caches.get("lattice")

    @property
    def ray_count(self) -> int:
        return self._ray_count

    @classmethod
    def from_packed(
        cls,
        index: int,
        time_s: float,
        pose: np.ndarray,
        sensor_xy: np.ndarray,
        integrated_pose: np.ndarray,
        normal_params: NormalParams,
        ray_count: int,
        arrays: dict[str, np.ndarray],
    ) -> Keyframe:
        """A keyframe holding arrays already packed (:meth:`packed`'s names), as they are: no copy."""
        kf = cls.__new__(cls)
        kf.index, kf.time_s, kf.pose, kf.sensor_xy = index, time_s, pose, sensor_xy
        kf.integrated_pose, kf.normal_params, kf._ray_count = integrated_pose, normal_params, ray_count
        kf._hits = kf._match = kf._ray_ends = _NO_POINTS
        kf._ray_hit_bits = np.zeros(0, dtype=np.uint8)
        kf._surface, kf._bare, kf._walls, kf._lattice, kf._faces = None, None, None, None, None
        kf.use_packed(arrays)
        return kf

    def __repr__(self) -> str:
        return f"Keyframe(index={self.index}, time_s={self.time_s}, hits={self._hits.shape[0]})"

    @property
    def hits(self) -> np.ndarray:
        return unpack(self._hits, POINT_STEP_M)

    @property
    def match_points(self) -> np.ndarray:
        return unpack(self._match, POINT_STEP_M)

    @property
    def ray_ends(self) -> np.ndarray:
        return unpack(self._ray_ends, POINT_STEP_M)

    @property
    def ray_hit(self) -> np.ndarray:
        return np.unpackbits(self._ray_hit_bits, count=self._ray_count).astype(bool)

    @property
    def points(self) -> np.ndarray:
        return self.surface()[0]

    @property
    def normals(self) -> np.ndarray:
        return self.surface()[1]

    @property
    def surface_size(self) -> int:
        """How many points the surface has (computing it if need be)."""
        return int(self.packed_surface()[0].shape[0])

    @property
    def has_surface(self) -> bool:
        """The surface has been computed (asking for it costs nothing more)."""
        return self._surface is not None

    def surface(self) -> tuple[np.ndarray, np.ndarray]:
        """``(points, normals)``: hits with a usable normal (oriented to the lidar), smoothed; computed once."""
        points, normals = self.packed_surface()
        return unpack(points, POINT_STEP_M), unpack(normals, NORMAL_STEP)

    def packed_surface(self) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`surface` as kept (:func:`pack`'s int16 or float32), computed if need be: no copy made."""
        surface = self._surface
        if surface is None:
            hits = self.hits
            pts, nrm, good = _line_surface(hits, self.sensor_xy, self.normal_params)
            surface = (pack(pts, POINT_STEP_M), pack(nrm, NORMAL_STEP))
            if self.normal_params.pool_far_normals_beyond_m > 0.0:
                self._bare = pack(hits[~good], POINT_STEP_M)
            self._surface = surface  # a race with another thread computes the same values
        return surface

    def bare_hits(self) -> np.ndarray:
        """(B, 2) its hits its own scan gives no usable normal (robot frame); none unless ``pool_far_normals_beyond_m``.

        A submap gives them a normal from its keyframes' points pooled (:func:`build_target`).
        """
        self.packed_surface()
        bare = self._bare
        return np.zeros((0, 2)) if bare is None else unpack(bare, POINT_STEP_M)

    def wall_direction(self) -> tuple[float, float, int]:
        """Dominant wall direction in the robot frame, modulo 90°: ``(angle_rad, strength, count)``.

        The circular mean of four times the normals' angles (Mardia & Jupp, *Directional
        Statistics*, 2000: the mean of an axial variable of period π/2), divided by four:
        in a maze whose walls all meet at right angles every normal points along one of
        four directions ``δ + k·90°``, and four times its angle is ``4δ`` for all of them.
        ``strength`` is the mean resultant length (1: every normal on the grid, 0: no
        dominant grid); ``count`` the normals used. Cached, computed with the normals.
        """
        cached = self._walls
        if cached is None:
            nrm = self.normals
            if nrm.shape[0] == 0:
                cached = (0.0, 0.0, 0)
            else:
                four = 4.0 * np.arctan2(nrm[:, 1], nrm[:, 0])
                c, s = float(np.mean(np.cos(four))), float(np.mean(np.sin(four)))
                cached = (0.25 * math.atan2(s, c), math.hypot(c, s), int(nrm.shape[0]))
            self._walls = cached
        return cached

    def wall_faces(self) -> Faces:
        """Its straight wall faces in its own frame (:func:`mazebot.slam.wall_faces.wall_faces`), cached.

        Sorted by the axes of its own wall direction (:meth:`wall_direction`); none where its
        normals show no dominant grid.
        """
        if self._faces is None:
            direction, strength, _ = self.wall_direction()
            points, normals = self.surface()
            self._faces = wall_faces(points, normals, direction) if strength > 0 else NO_FACES
        return self._faces

    def lattice_faces(self, psi_rad: float, params: LatticeParams) -> LatticeFaces:
        """The keyframe's wall faces on the lattice (:func:`mazebot.slam.wall_lattice.measure_faces`), cached.

        ``psi_rad`` is the keyframe's heading on the wall grid; the faces are measured again
        only if it has changed by more than :data:`LATTICE_REMEASURE_RAD` since (the
        cached offsets follow smaller changes to first order) or the pitch has.
        """
        cached = self._lattice
        if (
            cached is None
            or cached.pitch_m != params.pitch_m
            or abs(math.remainder(psi_rad - cached.psi_rad, math.tau)) > LATTICE_REMEASURE_RAD
        ):
            points, normals = self.surface()
            cached = measure_faces(points, normals, self.sensor_xy, psi_rad, params)
            self._lattice = cached
        return cached

    @classmethod
    def from_scan(
        cls,
        index: int,
        pose: np.ndarray,
        prepared: PreparedScan,
        normals: NormalParams | None = None,
        map_max_range_m: float | None = None,
        rays: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> Keyframe:
        """A keyframe from a prepared scan at ``pose`` (normals are estimated when first needed).

        ``rays`` are the scan's grid rays if already made by :func:`map_rays` (SLAM makes
        them once per scan); otherwise they are made here, limited to ``map_max_range_m``.
        """
        ends, hit, _ = map_rays(prepared, map_max_range_m) if rays is None else rays
        pose = np.array(pose, dtype=np.float64).reshape(3)
        return cls(
            index=index,
            time_s=prepared.time_s,
            pose=pose,
            hits=prepared.points_full,
            match_points=prepared.points_match,
            sensor_xy=np.array(prepared.sensor_xy, dtype=np.float64),
            ray_ends=ends,
            ray_hit=hit,
            integrated_pose=pose.copy(),
            normal_params=normals or NormalParams(),
        )

    def rays(self, pose: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(pose, ends, hit, origins)`` for :meth:`mazebot.slam.grid.OccupancyGrid.rebuild` (robot frame)."""
        ends = self.ray_ends
        return (
            self.pose if pose is None else pose,
            ends,
            self.ray_hit,
            np.broadcast_to(self.sensor_xy, ends.shape),
        )


def oriented_normals(hits_xy: np.ndarray, sensor_xy: np.ndarray, params: NormalParams) -> tuple[np.ndarray, np.ndarray]:
    """``(normals, usable)`` of a scan's hits (robot frame), each normal turned towards the lidar at ``sensor_xy``."""
    view = np.broadcast_to(sensor_xy, hits_xy.shape)
    nrm, good = estimate_normals(hits_xy, params.neighbours, params.radius_m, params.max_line_spread, view)
    return _towards(nrm, hits_xy, view), good


def _towards(normals: np.ndarray, points_xy: np.ndarray, views_xy: np.ndarray) -> np.ndarray:
    """Each normal turned towards the lidar that made its point: the side of the wall the scan saw."""
    flip = np.einsum("ij,ij->i", normals, views_xy - points_xy) < 0
    return np.where(flip[:, None], -normals, normals)


def line_surface(hits_xy: np.ndarray, sensor_xy: np.ndarray, params: NormalParams) -> tuple[np.ndarray, np.ndarray]:
    """A keyframe's surface: ``(points, normals)`` of the hits with a usable normal, smoothed if ``params.smooth``."""
    pts, nrm, _ = _line_surface(hits_xy, sensor_xy, params)
    return pts, nrm


def _line_surface(
    hits_xy: np.ndarray, sensor_xy: np.ndarray, params: NormalParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`line_surface` and the mask (H,) of the hits that have a usable normal."""
    nrm, good = oriented_normals(hits_xy, sensor_xy, params)
    pts, nrm = hits_xy[good], nrm[good]
    if params.smooth:
        pts = smooth_onto_lines(
            pts, nrm, params.radius_m, params.neighbours, params.smooth_whole_face_only, params.smooth_max_span_m
        )
    return pts, nrm, good


def pooled_normals(
    points_xy: np.ndarray,
    views_xy: np.ndarray,
    bare_xy: np.ndarray,
    bare_views_xy: np.ndarray,
    params: NormalParams,
) -> tuple[np.ndarray, np.ndarray]:
    """``(normals (B, 2), usable (B,))`` of the bare hits, from the submap's points pooled with them.

    Along a corridor a scan's far hits fall on the walls at a grazing angle, so far apart
    (range times the beam step over the sine of the incidence: 0.3-1.9 m at 10-20 m for a
    SICK's 1° beams) that fewer than three lie within ``radius_m`` of one another, and its
    own scan gives them no normal. The keyframes of a submap saw the same walls from
    other places, their hits falling between each other's: pooled, the wall is dense
    enough for the same neighbour rule (:func:`mazebot.slam.icp.estimate_normals`, only
    points seen from the same side counting). Each normal is turned towards the lidar
    that made its hit; the hits keep their measured positions.
    """
    if bare_xy.shape[0] == 0:
        return np.zeros((0, 2)), np.zeros(0, dtype=bool)
    pool = np.vstack((bare_xy, points_xy))
    views = np.vstack((bare_views_xy, views_xy))
    queries = np.arange(bare_xy.shape[0])
    nrm, good = estimate_normals(pool, params.neighbours, params.radius_m, params.max_line_spread, views, queries)
    return _towards(nrm, bare_xy, bare_views_xy), good


def smoothed_match_points(
    hits_xy: np.ndarray, sensor_xy: np.ndarray, params: NormalParams, voxel_m: float
) -> np.ndarray:
    """A scan's points to match, smoothed onto their lines as the submap's are, thinned to one per ``voxel_m``.

    ICP pairs a scan's points as measured with a submap whose points were moved onto
    their local lines (:func:`smooth_onto_lines`). On a straight wall that pairing is
    unbiased, but where a neighbourhood is not one clean line (the ends of short faces
    facing the lidar a few metres off, door frames, pillars between alcoves) the submap's
    surface is moved off the measured one by millimetres in a way the raw scan is not,
    and the match turns by a few hundredths of a degree, the same way scan after scan
    along a corridor. The scan's hits smoothed the same way (the same neighbourhoods, the
    same rule) meet a submap made like themselves. Hits without a usable normal (isolated
    points, corners) keep their measured position; the thinning is
    :func:`mazebot.slam.preprocess.voxel_downsample`'s, as for the unsmoothed points.
    """
    pts = np.array(hits_xy, dtype=np.float64).reshape(-1, 2)
    if pts.shape[0] == 0:
        return pts
    nrm, good = oriented_normals(pts, sensor_xy, params)
    if np.any(good):
        pts[good] = smooth_onto_lines(
            pts[good], nrm[good], params.radius_m, params.neighbours, params.smooth_whole_face_only,
            params.smooth_max_span_m,
        )
    return pts[voxel_downsample(pts, voxel_m)]


def smooth_onto_lines(
    points_xy: np.ndarray,
    normals: np.ndarray,
    radius_m: float,
    neighbours: int,
    whole_face_only: bool = False,
    max_span_m: float = 0.0,
) -> np.ndarray:
    """Each point moved along its normal onto the line through the mean of its neighbours.

    The A1's range noise (~1 % of the range) scatters a wall's points by centimetres
    across the wall; the local line (the PCA of :func:`mazebot.slam.icp.estimate_normals`)
    averages that scatter away, so the submap ICP matches against is a thin line rather
    than a noisy band, whose nearest-neighbour bumps otherwise hold ICP short of the
    optimum by a good fraction of its starting error (moving least squares, Alexa et al.,
    "Computing and rendering point set surfaces", IEEE TVCG 2003, reduced to lines).
    Points keep their position along the wall, so corners stay where they were.

    ``whole_face_only``: a point is moved only where all ``neighbours`` nearest points lie
    within ``radius_m`` and on its own face (normals within 45°); elsewhere it keeps its
    measured position. A neighbourhood the points do not fill (a face shorter than the
    neighbourhood, its ends, sparse points a few metres off, a corner) fits a line that
    is an extrapolation of a few points, and moving the point onto it moves the submap's
    surface off the measured one: on a real corridor with alcoves on one side, that turns
    each match of a scan as measured by hundredths of a degree, the same way every scan.

    ``max_span_m`` (> 0): a point is moved only where its neighbours on its own face span at
    most that length along its line. The neighbourhood is a fixed count of points, so the
    length of wall it covers grows with the beams' spacing there (range over the cosine of
    the incidence times the angular step): a SICK's 0.5° beams are 2.6 cm apart head-on at
    3 m and 7 cm at 8 m, ten of them half a metre of wall, over which a building is not one
    line (pillars between alcoves, door frames, the ends of short faces) and the fitted line
    no longer says where the measured surface is. Within a short span the wall is a line
    and the range noise is all that is averaged away.
    """
    m = points_xy.shape[0]
    if m == 0:
        return points_xy.copy()
    k = min(neighbours, m)
    dist, idx = cKDTree(points_xy).query(points_xy, k=k, distance_upper_bound=radius_m)
    dist, idx = dist.reshape(m, k), idx.reshape(m, k)
    ok = np.isfinite(dist)
    # only neighbours on the same side of the wall (their normals agree)
    nrm_pad = np.vstack((normals, np.zeros((1, 2))))
    ok &= np.einsum("md,mkd->mk", normals, nrm_pad[idx]) > 0.7
    pad = np.vstack((points_xy, np.zeros((1, 2))))
    w = ok.astype(np.float64)
    mean = np.einsum("mk,mkd->md", w, pad[idx]) / np.maximum(w.sum(axis=1), 1.0)[:, None]
    offset = np.einsum("md,md->m", points_xy - mean, normals)
    if whole_face_only:
        offset = np.where(ok.all(axis=1), offset, 0.0)
    if max_span_m > 0.0:
        offset = np.where(_face_span_m(points_xy, normals, pad[idx], ok) <= max_span_m, offset, 0.0)
    return points_xy - offset[:, None] * normals


def _face_span_m(
    points_xy: np.ndarray, normals: np.ndarray, neighbours_xy: np.ndarray, on_face: np.ndarray
) -> np.ndarray:
    """(M,) the length of its line, in metres, that each point's neighbours on its face cover.

    ``neighbours_xy`` (M, k, 2) and ``on_face`` (M, k) as :func:`smooth_onto_lines` makes them;
    each neighbour's position along the line is its offset from the point along the line's
    direction (the normal turned by 90°).
    """
    along = np.column_stack((-normals[:, 1], normals[:, 0]))
    t = np.einsum("mkd,md->mk", neighbours_xy - points_xy[:, None, :], along)
    return np.where(on_face, t, -np.inf).max(axis=1) - np.where(on_face, t, np.inf).min(axis=1)


def map_rays(
    prepared: PreparedScan,
    max_range_m: float | None = None,
    smoothing: EndpointSmoothing | None = None,
    range_noise_rel: float = 0.0,
    hit_depth_m: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The scan's rays for the occupancy grid, robot frame: ``(ends (K, 2), hit (K,), origins (K, 2))``.

    With ``smoothing``, every hit is first moved along its beam onto the line through
    its neighbours (:mod:`mazebot.slam.endpoint_smoothing`): the range noise no longer
    spills a wall into the free cell in front of it.

    Hits farther than ``max_range_m`` from their origin become no-return rays: they
    still clear the space in front of the wall, but do not mark it. The A1's range noise
    is about 1 % of the range, so a far hit scatters over several cells beside the wall
    (where no later ray clears it); the maze's walls are all seen from close by at some
    point, so nothing is lost. Such a ray ends three noise standard deviations short
    of its hit (``range · (1 − 3 · range_noise_rel)``), so it never clears the wall it
    hit; with ``range_noise_rel`` 0 it ends at ``max_range_m``.

    ``hit_depth_m`` moves every hit that marks a wall this far beyond the face along its
    beam: a return comes from the face of the wall, and the cell to mark is the one
    holding the wall's body behind it. When a face lies just behind a cell edge, the
    endpoints left scattered around it (pose error, what smoothing leaves of the range
    noise) would otherwise mark the free cell in front in most revolutions, the wall
    would show two cells thick and the free space end one cell short of it. Keep it
    below the thinnest wall (the maze's is 12 mm) so the marked cell is still on it.
    """
    beams = prepared.beams()
    ends, hit, origins = beams.endpoints, beams.hit.copy(), beams.origins
    if smoothing is not None:
        n = prepared.points_full.shape[0]  # the hits come first, in scan order
        ends = ends.copy()
        ends[:n] = smooth_endpoints(ends[:n], origins[:n], smoothing)
    if max_range_m is None and hit_depth_m <= 0.0:
        return ends, hit, origins
    vec = ends - origins
    length = np.hypot(vec[:, 0], vec[:, 1])
    ends = ends.copy()
    if max_range_m is not None:
        far = hit & (length > max_range_m)
        if far.any():
            clear_m = length[far] * (1.0 - 3.0 * range_noise_rel) if range_noise_rel > 0 else max_range_m
            ends[far] = origins[far] + vec[far] * (clear_m / length[far])[:, None]
            hit[far] = False
    if hit_depth_m > 0.0:
        deep = hit & (length > 0.0)
        ends[deep] += vec[deep] * (hit_depth_m / length[deep])[:, None]
    return ends, hit, origins


class KeyframeSelector:
    """Decides when a scan becomes a keyframe: moved ``distance_m`` or turned ``angle_rad``.

    Example::

        select = KeyframeSelector(distance_m=0.10, angle_rad=0.15)
        select.is_keyframe(pose)     # True for the first pose, then after enough motion
        select.accept(pose)          # remember the pose of the new keyframe
    """

    def __init__(self, distance_m: float = 0.10, angle_rad: float = 0.15) -> None:
        if distance_m <= 0 or angle_rad <= 0:
            raise ValueError(f"keyframe distance and angle must be positive, got {distance_m}, {angle_rad}")
        self.distance_m = float(distance_m)
        self.angle_rad = float(angle_rad)
        self.last: np.ndarray | None = None

    def is_keyframe(self, pose: np.ndarray) -> bool:
        if self.last is None:
            return True
        moved = math.hypot(float(pose[0] - self.last[0]), float(pose[1] - self.last[1]))
        turned = abs(math.remainder(float(pose[2] - self.last[2]), math.tau))
        return moved >= self.distance_m or turned >= self.angle_rad

    def accept(self, pose: np.ndarray) -> None:
        self.last = np.array(pose, dtype=np.float64).reshape(3)


def build_target_steps(
    keyframes: Sequence[Keyframe],
    voxel_m: float,
    frame: np.ndarray | None = None,
    poses: Sequence[np.ndarray] | None = None,
    clip: tuple[np.ndarray, float] | None = None,
) -> Generator[None, None, Target | None]:
    """:func:`build_target` in stages (:mod:`mazebot.steps`): the union, the voxel filter, the kd-tree."""
    kept = [k for k, kf in enumerate(keyframes) if kf.surface_size]
    if not kept:
        return None
    surfaces = [keyframes[k].packed_surface() for k in kept]
    base = None if frame is None else np.asarray(frame, dtype=np.float64)
    pose_rows = []
    for k in kept:
        pose = keyframes[k].pose if poses is None else np.asarray(poses[k], dtype=np.float64)
        pose_rows.append(pose if base is None else relative_pose(base, pose))
    pose_arr = np.array(pose_rows, dtype=np.float64).reshape(-1, 3)
    # math.cos/sin, as geometry.transform_points() uses, so the result is the same to the bit
    cos = np.array([math.cos(float(t)) for t in pose_arr[:, 2]])
    sin = np.array([math.sin(float(t)) for t in pose_arr[:, 2]])
    sensors = np.array([keyframes[k].sensor_xy for k in kept], dtype=np.float64).reshape(-1, 2)
    views_kf = np.column_stack(
        (
            cos * sensors[:, 0] - sin * sensors[:, 1] + pose_arr[:, 0],
            sin * sensors[:, 0] + cos * sensors[:, 1] + pose_arr[:, 1],
        )
    )
    counts = np.array([pts.shape[0] for pts, _ in surfaces])
    local = unpack_all([pts for pts, _ in surfaces], POINT_STEP_M)
    local_nrm = unpack_all([nrm for _, nrm in surfaces], NORMAL_STEP)
    c, sn = np.repeat(cos, counts), np.repeat(sin, counts)
    points = np.column_stack(
        (
            c * local[:, 0] - sn * local[:, 1] + np.repeat(pose_arr[:, 0], counts),
            sn * local[:, 0] + c * local[:, 1] + np.repeat(pose_arr[:, 1], counts),
        )
    )
    normals = np.column_stack((c * local_nrm[:, 0] - sn * local_nrm[:, 1], sn * local_nrm[:, 0] + c * local_nrm[:, 1]))
    views = np.repeat(views_kf, counts, axis=0)
    if any(keyframes[k].normal_params.pool_far_normals_beyond_m > 0.0 for k in kept):
        points, normals, views = _with_pooled_normals(
            [keyframes[k] for k in kept], cos, sin, pose_arr, views_kf, points, normals, views
        )
    if clip is not None:
        near = np.hypot(*(points - np.asarray(clip[0], dtype=np.float64).reshape(1, 2)).T) <= clip[1]
        points, normals, views = points[near], normals[near], views[near]
        if points.shape[0] == 0:
            return None
    yield
    first = voxel_downsample(points, voxel_m)
    yield
    return Target(points[first], views[first], normals[first])


def _with_pooled_normals(
    keyframes: Sequence[Keyframe],
    cos: np.ndarray,
    sin: np.ndarray,
    pose_arr: np.ndarray,
    views_kf: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    views: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The submap's points, normals and viewpoints with its keyframes' bare hits that the pool gives a normal.

    The keyframes are :func:`build_target_steps`'s kept ones, with their cosines, sines and
    poses in the output frame; the submap is built once per keyframe (sequential) or per
    closure (loop), so the pooling is too.
    """
    bare = [kf.bare_hits() for kf in keyframes]
    counts = np.array([b.shape[0] for b in bare])
    if not counts.sum():
        return points, normals, views
    local = np.concatenate(bare)
    c, sn = np.repeat(cos, counts), np.repeat(sin, counts)
    bare_xy = np.column_stack(
        (
            c * local[:, 0] - sn * local[:, 1] + np.repeat(pose_arr[:, 0], counts),
            sn * local[:, 0] + c * local[:, 1] + np.repeat(pose_arr[:, 1], counts),
        )
    )
    bare_views = np.repeat(views_kf, counts, axis=0)
    far = np.hypot(*(bare_xy - bare_views).T) > keyframes[0].normal_params.pool_far_normals_beyond_m
    bare_xy, bare_views = bare_xy[far], bare_views[far]
    far_nrm, good = pooled_normals(points, views, bare_xy, bare_views, keyframes[0].normal_params)
    return (
        np.vstack((points, bare_xy[good])),
        np.vstack((normals, far_nrm[good])),
        np.vstack((views, bare_views[good])),
    )


build_target = all_at_once(
    build_target_steps,
    """The union of the keyframes' points and normals as an ICP target, one point per voxel.

    Points are expressed in the map frame, or in the frame of pose ``frame`` if given
    (loop closure matches in the candidate keyframe's frame). ``poses`` overrides the
    keyframes' own poses (a snapshot taken for a background job). ``clip`` ``(centre (2,),
    radius_m)`` keeps only points that close to a centre (in the output frame). None if empty.

    All keyframes are moved in one vectorized pass (each point with its keyframe's cosine,
    sine and translation), the same arithmetic as :func:`transform` point by point.
    """,
)

