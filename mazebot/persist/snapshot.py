"""A run's SLAM state as files: map, pose graph, keyframe scans; and back into a Slam.

Files in a run folder (each written atomically, :func:`mazebot.persist.runs.write_atomic`;
``meta.json`` last, so it describes files that are all complete):

- ``map.pgm`` + ``map.yaml``: ROS ``map_server`` (see :mod:`mazebot.slam.map_export`);
- ``grid.npz``: the log-odds grid itself (float32), its cell size and origin, so a
  resumed run continues the exact map, not its three-state picture;
- ``graph.g2o``: the keyframe pose graph in g2o 2D (``VERTEX_SE2``/``EDGE_SE2``);
- ``keyframes.npz``: every keyframe's scan in its own robot frame (hits, match points,
  beams), concatenated with offsets;
- ``trajectory.csv``: ``time_s,x_m,y_m,theta_rad`` of each keyframe (map frame);
- ``meta.json``: when, how many scans/keyframes, the last pose, the maze wall direction.

:func:`take_snapshot` runs on the event loop and only copies what later SLAM steps could
change (poses, the grid's array, the graph); :func:`save_snapshot` does the encoding and
the disk writes, in a thread.
"""

from __future__ import annotations

import copy
import datetime as dt
import io
import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np

from mazebot.errors import UsageError
from mazebot.persist.runs import META_FILE, write_atomic
from mazebot.slam.g2o import format_g2o, read_g2o
from mazebot.slam.grid import OccupancyGrid
from mazebot.slam.keyframes import Keyframe
from mazebot.slam.map_export import encode_pgm, encode_yaml
from mazebot.slam.posegraph import PoseGraph
from mazebot.slam.slam import Slam

FORMAT_VERSION = 1


@dataclass
class SlamSnapshot:
    """Everything a save needs, detached from the live Slam (safe to hand to a thread)."""

    keyframes: list[Keyframe]  # their arrays never change; poses are copied into ``poses``
    poses: np.ndarray  # (K, 3)
    graph: PoseGraph
    log_odds: np.ndarray
    origin_cells: tuple[int, int]
    resolution_m: float
    three_state: np.ndarray
    pose: tuple[float, float, float]
    scans: int
    wall_reference_rad: float | None
    extra: dict[str, Any] = field(default_factory=dict)
    cell_offset_m: tuple[float, float] = (0.0, 0.0)  # the grid's cell corners modulo the resolution


def take_snapshot(slam: Slam, extra: dict[str, Any] | None = None) -> SlamSnapshot:
    """Copy the parts of ``slam`` that change (a few hundred microseconds for a 6x6 maze)."""
    grid = slam.grid
    return SlamSnapshot(
        keyframes=list(slam.keyframes),
        poses=slam.keyframe_poses().copy(),
        graph=copy.deepcopy(slam.graph),
        log_odds=grid.log_odds.copy(),
        origin_cells=grid.origin_cells,
        resolution_m=grid.resolution_m,
        three_state=grid.three_state(),
        pose=tuple(float(v) for v in slam.pose),  # type: ignore[arg-type]
        scans=slam.scans,
        wall_reference_rad=slam.wall_reference_rad,
        extra=dict(extra or {}),
        cell_offset_m=(float(grid.cell_offset_m[0]), float(grid.cell_offset_m[1])),
    )


def _npz(**arrays: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **cast(dict[str, Any], arrays))  # numpy's stubs take a keyword for allow_pickle
    return buffer.getvalue()


def keyframes_npz(snapshot: SlamSnapshot) -> bytes:
    """All keyframe scans in one file: concatenated arrays plus per-keyframe offsets."""
    kfs = snapshot.keyframes

    def cat(name: str, width: int, dtype: Any) -> tuple[np.ndarray, np.ndarray]:
        parts = [np.asarray(getattr(kf, name), dtype=dtype).reshape(-1, width) for kf in kfs]
        offsets = np.cumsum([0] + [p.shape[0] for p in parts]).astype(np.int64)
        return (np.concatenate(parts) if parts else np.zeros((0, width), dtype)), offsets

    hits, hit_off = cat("hits", 2, np.float32)
    match, match_off = cat("match_points", 2, np.float32)
    ends, ends_off = cat("ray_ends", 2, np.float32)
    ray_hit, _ = cat("ray_hit", 1, bool)
    return _npz(
        format_version=np.array(FORMAT_VERSION),
        time_s=np.array([kf.time_s for kf in kfs], dtype=np.float64),
        pose=snapshot.poses.reshape(-1, 3),
        sensor_xy=np.array([kf.sensor_xy for kf in kfs], dtype=np.float64).reshape(-1, 2),
        hits=hits,
        hits_offsets=hit_off,
        match_points=match,
        match_offsets=match_off,
        ray_ends=ends,
        ray_hit=ray_hit.reshape(-1),
        ray_offsets=ends_off,
    )


def save_snapshot(snapshot: SlamSnapshot, run_dir: Path, saved_at: dt.datetime | None = None) -> None:
    """Write every file of the run folder (atomically each; ``meta.json`` last)."""
    origin = (snapshot.origin_cells[0] * snapshot.resolution_m + snapshot.cell_offset_m[0],
              snapshot.origin_cells[1] * snapshot.resolution_m + snapshot.cell_offset_m[1])
    write_atomic(run_dir / "map.pgm", encode_pgm(snapshot.three_state))
    write_atomic(run_dir / "map.yaml", encode_yaml(snapshot.resolution_m, origin, "map.pgm").encode())
    write_atomic(
        run_dir / "grid.npz",
        _npz(
            log_odds=snapshot.log_odds,
            origin_cells=np.array(snapshot.origin_cells, dtype=np.int64),
            resolution_m=np.array(snapshot.resolution_m),
            cell_offset_m=np.array(snapshot.cell_offset_m, dtype=np.float64),
        ),
    )
    write_atomic(run_dir / "graph.g2o", "".join(format_g2o(snapshot.graph)).encode())
    write_atomic(run_dir / "keyframes.npz", keyframes_npz(snapshot))
    rows = ["time_s,x_m,y_m,theta_rad"] + [
        f"{kf.time_s!r},{p[0]!r},{p[1]!r},{p[2]!r}"
        for kf, p in zip(snapshot.keyframes, snapshot.poses.tolist(), strict=True)
    ]
    write_atomic(run_dir / "trajectory.csv", ("\n".join(rows) + "\n").encode())
    meta = {
        "format_version": FORMAT_VERSION,
        "saved_at": (saved_at or dt.datetime.now().astimezone()).isoformat(timespec="seconds"),
        "scans": snapshot.scans,
        "keyframes": len(snapshot.keyframes),
        "pose": list(snapshot.pose),
        "start_pose": [0.0, 0.0, 0.0],  # the map frame is the robot's pose at the start
        "wall_reference_rad": snapshot.wall_reference_rad,
        "map": {"rows": int(snapshot.log_odds.shape[0]), "cols": int(snapshot.log_odds.shape[1]),
                "resolution_m": snapshot.resolution_m, "origin_m": list(origin)},
        **snapshot.extra,
    }
    write_atomic(run_dir / META_FILE, (json.dumps(meta, indent=2) + "\n").encode())


@dataclass
class SavedRun:
    """A run folder read back."""

    path: Path
    meta: dict[str, Any]
    keyframes: list[Keyframe]
    graph: PoseGraph
    log_odds: np.ndarray
    origin_cells: tuple[int, int]
    resolution_m: float
    cell_offset_m: tuple[float, float] = (0.0, 0.0)  # runs saved before the grid could shift: none

    @property
    def trajectory_xy(self) -> np.ndarray:
        return np.array([kf.pose[:2] for kf in self.keyframes]).reshape(-1, 2)


def load_run(run_dir: Path, normal_params: Any = None) -> SavedRun:
    """Read a run folder; a missing or damaged file is a one-line :class:`UsageError`."""
    meta_path = run_dir / META_FILE
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
        # the files are opened here, not by np.load: it leaks its own handle when the archive is
        # damaged (numpy/lib/_npyio_impl.py, load(): the ExitStack lets go before NpzFile reads it)
        with open(run_dir / "grid.npz", "rb") as grid_file, np.load(grid_file) as g:
            log_odds = g["log_odds"].astype(np.float32)
            origin_cells = tuple(int(v) for v in g["origin_cells"])
            resolution_m = float(g["resolution_m"])
            offset = g["cell_offset_m"] if "cell_offset_m" in g.files else np.zeros(2)
            cell_offset_m = (float(offset[0]), float(offset[1]))
        with open(run_dir / "keyframes.npz", "rb") as keyframes_file, np.load(keyframes_file) as k:
            arrays = {name: k[name] for name in k.files}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:  # EOFError: an empty file
        raise UsageError(f"run {run_dir} cannot be read ({type(exc).__name__}: {exc})") from None
    graph = read_g2o(run_dir / "graph.g2o")
    keyframes = []
    for i in range(arrays["time_s"].shape[0]):
        h0, h1 = arrays["hits_offsets"][i : i + 2]
        m0, m1 = arrays["match_offsets"][i : i + 2]
        r0, r1 = arrays["ray_offsets"][i : i + 2]
        pose = arrays["pose"][i].astype(np.float64)
        kw = {} if normal_params is None else {"normal_params": normal_params}
        keyframes.append(
            Keyframe(
                index=i,
                time_s=float(arrays["time_s"][i]),
                pose=pose.copy(),
                hits=arrays["hits"][h0:h1].copy(),
                match_points=arrays["match_points"][m0:m1].copy(),
                sensor_xy=arrays["sensor_xy"][i].copy(),
                ray_ends=arrays["ray_ends"][r0:r1].copy(),
                ray_hit=arrays["ray_hit"][r0:r1].copy(),
                integrated_pose=pose.copy(),
                **kw,
            )
        )
    if len(graph) != len(keyframes):
        raise UsageError(f"run {run_dir}: graph.g2o has {len(graph)} poses but keyframes.npz {len(keyframes)}")
    return SavedRun(run_dir, meta, keyframes, graph, log_odds, origin_cells,  # type: ignore[arg-type]
                    resolution_m, cell_offset_m)


def saved_grid(saved: SavedRun, like: OccupancyGrid) -> OccupancyGrid:
    """The saved log-odds grid, with the sensor model of ``like`` (the configured one)."""
    return like.holding(saved.log_odds, saved.origin_cells, saved.cell_offset_m)
