"""What a robot says on Zenoh, and where: key expressions and payloads as pure functions.

Every robot lives under ``mazebot/<name>/`` (docs/fleet.md)::

    mazebot/<name>/alive     liveliness token: present while the daemon runs (how watchers find robots)
    mazebot/<name>/packet    the phone page's packets (docs/protocol.md), the same bytes the page gets:
                             deltas, and a full map every ``resync_every``-th packet and on a new epoch
    mazebot/<name>/pose      JSON: pose in the map frame with its 3x3 covariance
    mazebot/<name>/scan      JSON: one lidar revolution, exact (the recording's ``mazebot.Scan``)
    mazebot/<name>/state     JSON: run state and active faults, on every change
    mazebot/<name>/fault     JSON: each fault as it is raised
    mazebot/<name>/info      queryable, JSON: the page's ``hello`` fields, the robot's name and version
    mazebot/<name>/full      queryable: the full packet of the last sequence number (a watcher that
                             missed a delta asks here instead of waiting for the next resync)
    mazebot/<name>/control   queryable: ``{"type": "start"|"stop", "token": PIN}`` (the page's own
                             message), answered with the page's ``reply`` JSON

Nothing here imports zenoh.
"""

from __future__ import annotations

import json
import socket
from typing import Any

import numpy as np

from mazebot.config import ROBOT_NAME
from mazebot.errors import ConfigError

PREFIX = "mazebot"
TOPICS = ("packet", "pose", "scan", "state", "fault")
QUERYABLES = ("info", "full", "control")


def key(name: str, what: str) -> str:
    """``mazebot/<name>/<what>``."""
    return f"{PREFIX}/{name}/{what}"


def every_robot(what: str) -> str:
    """The key expression that matches ``what`` of every robot: ``mazebot/*/<what>``."""
    return f"{PREFIX}/*/{what}"


def robot_of(key_expr: str) -> str | None:
    """The robot name in ``mazebot/<name>/...``, or None for a key that is not a robot's."""
    parts = str(key_expr).split("/")
    if len(parts) < 3 or parts[0] != PREFIX or not ROBOT_NAME.fullmatch(parts[1]):
        return None
    return parts[1]


def robot_name(configured: str, hostname: str | None = None) -> str:
    """``[zenoh] robot_name``, or the host name made into one key chunk (``pi-4.local`` -> ``pi-4``)."""
    if configured:
        return configured
    host = (hostname if hostname is not None else socket.gethostname()).split(".")[0]
    name = "".join(c if c.isalnum() or c in "-_" else "_" for c in host)[:64]
    if not name or not ROBOT_NAME.fullmatch(name):
        raise ConfigError(f"zenoh.robot_name: the host name {host!r} is no robot name; set [zenoh] robot_name")
    return name


def dumps(obj: Any) -> bytes:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


def pose_message(time_s: float | None, pose: tuple[float, float, float], covariance: np.ndarray | None,
                 t_ms: float) -> dict[str, Any]:
    """``{"time_s", "x_m", "y_m", "theta_rad", "covariance": [9] | null, "t_ms"}``: ``time_s`` on the
    robot's clock (the odometry reading the pose is of), ``t_ms`` Unix milliseconds when sent."""
    cov = None
    if covariance is not None:
        c = np.asarray(covariance, dtype=np.float64)
        if c.shape == (3, 3) and np.all(np.isfinite(c)):
            cov = [float(v) for v in c.reshape(-1)]
    return {
        "time_s": None if time_s is None else float(time_s),
        "x_m": float(pose[0]), "y_m": float(pose[1]), "theta_rad": float(pose[2]),
        "covariance": cov,
        "t_ms": round(t_ms, 1),
    }


def state_message(run_state: str, faults: list[tuple[str, str]], t_ms: float) -> dict[str, Any]:
    """``{"state", "faults": [{"source", "message"}], "t_ms"}``: active faults, newest last."""
    return {"state": run_state, "faults": [{"source": s, "message": m} for s, m in faults], "t_ms": round(t_ms, 1)}
