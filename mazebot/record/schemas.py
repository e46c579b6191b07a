"""The channels of a mazebot recording: topic, schema and how a message becomes JSON bytes.

Where Foxglove has a well-known schema, the channel uses it under its exact name, so
Foxglove's 3D, Log and plot panels open the file without any set-up (schema names and
fields from docs.foxglove.dev/docs/visualization/message-schemas/: ``foxglove.LaserScan``,
``foxglove.PoseInFrame``, ``foxglove.Grid``, ``foxglove.Log``, ``foxglove.FrameTransform``; "You must use the schema
names specified above for Foxglove to recognize the schema"). Messages are JSON
(MCAP message encoding ``json``, schema encoding ``jsonschema``): times are
``{"sec", "nsec"}`` objects, ``bytes`` fields base64 strings, enums their integer value.

A ``foxglove.LaserScan`` assumes equally spaced bearings, which an RPLidar revolution
does not have, and it has no per-sample times; replay needs the exact samples, so every
revolution is also written, bit for bit (little-endian arrays in base64), on
``/mazebot/scan_raw``. The other ``mazebot.*`` channels have no Foxglove equivalent.

The encoders here run in the recorder's writer thread, never on the event loop: the loop
only enqueues the (immutable) objects.
"""

from __future__ import annotations

import base64
import functools
import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from mazebot.io.scan import Scan

MESSAGE_ENCODING = "json"
SCHEMA_ENCODING = "jsonschema"
#: Frame ids, named as in ROS REP 105 ("Coordinate Frames for Mobile Platforms"): ``map`` is the
#: start pose, corrected by SLAM; ``odom`` is where wheel odometry alone puts the start (it drifts,
#: but never jumps); ``base_link`` the axle centre; ``laser`` the lidar's centre.
MAP_FRAME = "map"
ODOM_FRAME = "odom"
ROBOT_FRAME = "base_link"
LASER_FRAME = "laser"

# Foxglove log levels (foxglove.LogLevel): UNKNOWN 0, DEBUG 1, INFO 2, WARNING 3, ERROR 4, FATAL 5.
LOG_LEVELS = {"DEBUG": 1, "INFO": 2, "WARNING": 3, "ERROR": 4, "CRITICAL": 5}

_TIME = {
    "type": "object",
    "title": "time",
    "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0}},
}
_VECTOR3 = {
    "type": "object",
    "title": "foxglove.Vector3",
    "properties": {k: {"type": "number"} for k in "xyz"},
}
_QUATERNION = {
    "type": "object",
    "title": "foxglove.Quaternion",
    "properties": {k: {"type": "number"} for k in "xyzw"},
}
_POSE = {
    "type": "object",
    "title": "foxglove.Pose",
    "properties": {"position": _VECTOR3, "orientation": _QUATERNION},
}


def _schema(title: str, properties: dict[str, Any], description: str) -> bytes:
    return json.dumps(
        {"title": title, "description": description, "type": "object", "properties": properties},
        sort_keys=True,
    ).encode()


def _array(item_type: str) -> dict[str, Any]:
    return {"type": "array", "items": {"type": item_type}}


def _b64(description: str) -> dict[str, Any]:
    return {"type": "string", "contentEncoding": "base64", "description": description}


SCHEMAS: dict[str, bytes] = {
    "foxglove.LaserScan": _schema(
        "foxglove.LaserScan",
        {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "pose": _POSE,
            "start_angle": {"type": "number"},
            "end_angle": {"type": "number"},
            "ranges": _array("number"),
            "intensities": _array("number"),
        },
        "A single scan from a planar laser range-finder",
    ),
    "foxglove.PoseInFrame": _schema(
        "foxglove.PoseInFrame",
        {"timestamp": _TIME, "frame_id": {"type": "string"}, "pose": _POSE},
        "A timestamped pose for an object or reference frame in 3D space",
    ),
    "foxglove.Grid": _schema(
        "foxglove.Grid",
        {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "pose": _POSE,
            "column_count": {"type": "integer", "minimum": 0},
            "cell_size": {"type": "object", "properties": {"x": {"type": "number"}, "y": {"type": "number"}}},
            "row_stride": {"type": "integer", "minimum": 0},
            "cell_stride": {"type": "integer", "minimum": 0},
            "fields": {
                "type": "array",
                "items": {
                    "type": "object",
                    "title": "foxglove.PackedElementField",
                    "properties": {
                        "name": {"type": "string"},
                        "offset": {"type": "integer"},
                        "type": {"type": "integer", "description": "foxglove.NumericType: 1 UINT8, 2 INT8, ..."},
                    },
                },
            },
            "data": _b64("Grid cell data, row-major (y-major)"),
        },
        "A 2D grid of data",
    ),
    "foxglove.FrameTransform": _schema(
        "foxglove.FrameTransform",
        {
            "timestamp": _TIME,
            "parent_frame_id": {"type": "string"},
            "child_frame_id": {"type": "string"},
            "translation": _VECTOR3,
            "rotation": _QUATERNION,
        },
        "A transform between two reference frames in 3D space",
    ),
    "foxglove.Log": _schema(
        "foxglove.Log",
        {
            "timestamp": _TIME,
            "level": {"type": "integer", "description": "foxglove.LogLevel: 1 DEBUG .. 5 FATAL"},
            "message": {"type": "string"},
            "name": {"type": "string"},
            "file": {"type": "string"},
            "line": {"type": "integer", "minimum": 0},
        },
        "A log message",
    ),
    "mazebot.Scan": _schema(
        "mazebot.Scan",
        {
            "revolution": {"type": "integer"},
            "count": {"type": "integer"},
            "angle_rad": _b64("float64 little-endian, counter-clockwise from the heading"),
            "range_m": _b64("float64 little-endian, 0 = no return"),
            "quality": _b64("uint8"),
            "time_s": _b64("float64 little-endian, daemon clock time of each sample"),
            "valid": _b64("uint8 0/1"),
        },
        "One lidar revolution, every sample exactly as the driver handed it to SLAM",
    ),
    "mazebot.EncoderTicks": _schema(
        "mazebot.EncoderTicks",
        {
            "time_s": {"type": "number"},
            "pose_time_s": {"type": ["number", "null"]},
            "left_ticks": {"type": "integer"},
            "right_ticks": {"type": "integer"},
            "invalid_transitions": {"type": "integer"},
        },
        "One reading of both wheels' tick totals (the odometry task's input)",
    ),
    "mazebot.MotorCommand": _schema(
        "mazebot.MotorCommand",
        {"time_s": {"type": "number"}, "left": {"type": "number"}, "right": {"type": "number"}},
        "Throttles in [-1, 1] sent to the motor driver (stop is 0, 0)",
    ),
    "mazebot.RunState": _schema(
        "mazebot.RunState",
        {"time_s": {"type": "number"}, "state": {"type": "string"}},
        "The robot's run state after a change (idle, running, stopped, done, fault)",
    ),
    "mazebot.SlamStep": _schema(
        "mazebot.SlamStep",
        {
            "kind": {"type": "string", "enum": ["update", "final", "apply"]},
            "scan_end_time_s": {"type": "number"},
            "odometry_latest_s": {"type": "number"},
            "scans": {"type": "integer"},
        },
        "What SLAM consumed, in order: which revolution with odometry up to which reading, when the "
        "end-of-exploration job was asked for, and when a loop-closure result was merged (after how many "
        "scans), so a replay takes the same steps",
    ),
    "mazebot.Stats": _schema(
        "mazebot.Stats",
        {"time_s": {"type": "number"}, "messages": {"type": "integer"}, "dropped": {"type": "integer"}},
        "The recorder's own counters",
    ),
}


@dataclass(frozen=True)
class Channel:
    """One recorded topic: its schema name and how a message object becomes a dict."""

    topic: str
    schema: str
    to_json: Callable[[Any, int], dict[str, Any]] | None  # (message, log_time_ns) -> JSON object
    to_bytes: Callable[[Any, int], bytes] | None = None  # ... or straight to JSON text


def stamp(log_time_ns: int) -> dict[str, int]:
    """A Foxglove ``time`` from nanoseconds."""
    return {"sec": int(log_time_ns // 1_000_000_000), "nsec": int(log_time_ns % 1_000_000_000)}


def _b64_array(values: np.ndarray, dtype: str) -> str:
    return base64.b64encode(np.ascontiguousarray(values, dtype=dtype).tobytes()).decode("ascii")


def yaw_quaternion(theta_rad: float) -> dict[str, float]:
    """Rotation about +z by ``theta_rad`` as a quaternion."""
    return {"x": 0.0, "y": 0.0, "z": math.sin(theta_rad / 2.0), "w": math.cos(theta_rad / 2.0)}


def _pose(x_m: float, y_m: float, theta_rad: float) -> dict[str, Any]:
    return {"position": {"x": x_m, "y": y_m, "z": 0.0}, "orientation": yaw_quaternion(theta_rad)}


#: ``/scan`` is for display; ranges go in whole millimetres. The RPLidar A1 resolves 0.5 mm
#: below 1.5 m and 1 % of the range beyond (Slamtec A1M8 datasheet, "Distance resolution"),
#: so a millimetre keeps what a viewer can see; the exact samples are on ``/mazebot/scan_raw``.
SCAN_DISPLAY_STEP_M = 0.001
#: Ranges up to this many millimetres are written from a table of texts (the A1 reaches 12 m).
_TABLE_MM = 20_000


@functools.cache
def _number_texts(count: int, step: float) -> tuple[str, ...]:
    """JSON texts of ``i * step`` for i < count: formatting a float is the slow part of JSON."""
    return tuple(repr(round(i * step, 6)) for i in range(count))


def _json_numbers(values: np.ndarray, step: float, table_size: int) -> str:
    """``values`` rounded to ``step`` as a JSON array body ("0.5,1.25,..."), fast for small ones."""
    units = np.rint(values / step).astype(np.int64)
    texts = _number_texts(table_size, step)
    if units.size and (units.min() < 0 or units.max() >= table_size):
        return ",".join(texts[u] if 0 <= u < table_size else repr(round(u * step, 6)) for u in units.tolist())
    return ",".join([texts[u] for u in units.tolist()])


def laser_scan_bytes(scan: Scan, log_time_ns: int) -> bytes:
    """The revolution resampled onto equal bearings (one per sample, sorted), for display only.

    Written straight to JSON text: the ranges and intensities are ~700 numbers a revolution,
    and ``json.dumps`` of floats was most of the recorder's encoding time.
    """
    n = len(scan)
    head = {
        "timestamp": stamp(log_time_ns),
        "frame_id": LASER_FRAME,
        "pose": _pose(0.0, 0.0, 0.0),
        "start_angle": 0.0,
        "end_angle": 0.0,
    }
    if n == 0:
        return (json.dumps(head, separators=(",", ":"))[:-1] + ',"ranges":[],"intensities":[]}').encode()
    angle = np.remainder(scan.angle_rad, 2 * math.pi)
    order = np.argsort(angle, kind="stable")
    step = 2 * math.pi / n
    # NaN is not JSON: no return is written as 0 (below any lidar's minimum range)
    bins, strength = np.zeros(n), np.zeros(n)  # range and intensity of each bearing's sample
    index = np.minimum((angle[order] / step).astype(int), n - 1)
    bins[index] = np.where(scan.valid, scan.range_m, 0.0)[order]
    strength[index] = np.asarray(scan.quality, dtype=float)[order]
    head["end_angle"] = step * (n - 1)
    ranges = _json_numbers(bins, SCAN_DISPLAY_STEP_M, _TABLE_MM)
    intensities = _json_numbers(strength, 1.0, 256)
    text = f'{json.dumps(head, separators=(",", ":"))[:-1]},"ranges":[{ranges}],"intensities":[{intensities}]}}'
    return text.encode()


def equal_bearings(scan: Scan) -> tuple[np.ndarray, np.ndarray, float]:
    """Ranges and intensities on ``len(scan)`` equal bearings from 0 rad; ``+inf`` where none returned.

    A sample goes to its nearest bearing (two on one bearing: the later in the revolution wins).
    For binary messages (ROS 2 bags, Foxglove live), which can carry ``+inf`` (REP 117: no
    return); JSON cannot, so the recording's ``/scan`` has :func:`laser_scan_bytes`.
    """
    n = len(scan)
    step_rad = 2 * math.pi / n
    ranges = np.full(n, np.inf, dtype=np.float32)
    intensities = np.zeros(n, dtype=np.float32)
    index = np.rint(np.remainder(scan.angle_rad, 2 * math.pi) / step_rad).astype(np.int64) % n
    ok = scan.valid & np.isfinite(scan.range_m) & (scan.range_m > 0)
    ranges[index[ok]] = scan.range_m[ok]
    intensities[index[ok]] = scan.quality[ok]
    return ranges, intensities, step_rad


def raw_scan_json(scan: Scan, _log_time_ns: int) -> dict[str, Any]:
    return {
        "revolution": int(scan.revolution),
        "count": len(scan),
        "angle_rad": _b64_array(scan.angle_rad, "<f8"),
        "range_m": _b64_array(scan.range_m, "<f8"),
        "quality": _b64_array(scan.quality, "u1"),
        "time_s": _b64_array(scan.time_s, "<f8"),
        "valid": _b64_array(scan.valid, "u1"),
    }


def scan_from_json(obj: dict[str, Any]) -> Scan:
    """The exact :class:`Scan` a ``mazebot.Scan`` message was written from."""

    def arr(key: str, dtype: str) -> np.ndarray:
        return np.frombuffer(base64.b64decode(obj[key]), dtype=dtype).copy()

    return Scan(
        angle_rad=arr("angle_rad", "<f8").astype(np.float64),
        range_m=arr("range_m", "<f8").astype(np.float64),
        quality=arr("quality", "u1"),
        time_s=arr("time_s", "<f8").astype(np.float64),
        valid=arr("valid", "u1").astype(bool),
        revolution=int(obj["revolution"]),
    )


def pose_json(pose: tuple[float, float, float], log_time_ns: int) -> dict[str, Any]:
    return {"timestamp": stamp(log_time_ns), "frame_id": MAP_FRAME, "pose": _pose(*pose)}


def grid_json(grid: tuple[np.ndarray, float, tuple[float, float]], log_time_ns: int) -> dict[str, Any]:
    """A three-state map as a ``foxglove.Grid`` of one INT8 field ``occupancy`` (-1, 0, 100), row 0 south."""
    three_state, resolution_m, origin_m = grid
    cols = three_state.shape[1]
    return {
        "timestamp": stamp(log_time_ns),
        "frame_id": MAP_FRAME,
        "pose": _pose(float(origin_m[0]), float(origin_m[1]), 0.0),
        "column_count": int(cols),
        "cell_size": {"x": resolution_m, "y": resolution_m},
        "row_stride": int(cols),
        "cell_stride": 1,
        "fields": [{"name": "occupancy", "offset": 0, "type": 2}],  # NumericType INT8 = 2
        "data": _b64_array(three_state, "i1"),
    }


@dataclass(frozen=True)
class Transform:
    """The pose of ``child`` in ``parent`` (x_m, y_m, theta_rad): one edge of the frame tree."""

    parent: str
    child: str
    x_m: float
    y_m: float
    theta_rad: float


def transform_chain(
    pose: tuple[float, float, float],
    odometry: tuple[float, float, float],
    lidar_mount_xy_m: tuple[float, float],
) -> tuple[Transform, Transform, Transform]:
    """``map -> odom -> base_link -> laser`` (REP 105) for one instant.

    ``pose`` is the robot in the map, ``odometry`` the robot in the odometry frame, both of the
    same odometry reading (the odometry task writes them together). ``map -> odom`` is SLAM's
    correction, taken as ``pose ⊕ odometry⁻¹`` so that the chain gives back exactly the pose
    that was published (the live ``map_from_odom`` may already be newer than that reading).
    The lidar sits at its mounting offset with no rotation: the driver has already turned its
    angles into the robot's frame (``mazebot.io.rplidar``).
    """
    from mazebot.geometry import compose, inverse  # the one home of SE(2) arithmetic

    mx, my, mt = (float(v) for v in compose(pose, inverse(odometry)))
    return (
        Transform(MAP_FRAME, ODOM_FRAME, mx, my, mt),
        Transform(ODOM_FRAME, ROBOT_FRAME, *(float(v) for v in odometry)),
        Transform(ROBOT_FRAME, LASER_FRAME, float(lidar_mount_xy_m[0]), float(lidar_mount_xy_m[1]), 0.0),
    )


def transform_json(t: Transform, log_time_ns: int) -> dict[str, Any]:
    return {
        "timestamp": stamp(log_time_ns),
        "parent_frame_id": t.parent,
        "child_frame_id": t.child,
        "translation": {"x": t.x_m, "y": t.y_m, "z": 0.0},
        "rotation": yaw_quaternion(t.theta_rad),
    }


def odom_json(pose: tuple[float, float, float], log_time_ns: int) -> dict[str, Any]:
    """The robot (``base_link``) in the odometry frame: dead reckoning alone."""
    return {"timestamp": stamp(log_time_ns), "frame_id": ODOM_FRAME, "pose": _pose(*pose)}


def log_json(entry: tuple[str, str, str, str, int], log_time_ns: int) -> dict[str, Any]:
    level, name, message, file, line = entry
    return {
        "timestamp": stamp(log_time_ns),
        "level": LOG_LEVELS.get(level, 0),
        "message": message,
        "name": name,
        "file": file,
        "line": int(line),
    }


def plain_json(obj: dict[str, Any], _log_time_ns: int) -> dict[str, Any]:
    return obj


#: Every channel a recording has, by topic.
CHANNELS: dict[str, Channel] = {
    c.topic: c
    for c in (
        Channel("/scan", "foxglove.LaserScan", None, laser_scan_bytes),
        Channel("/mazebot/scan_raw", "mazebot.Scan", raw_scan_json),
        Channel("/mazebot/encoders", "mazebot.EncoderTicks", plain_json),
        Channel("/mazebot/motors", "mazebot.MotorCommand", plain_json),
        Channel("/pose", "foxglove.PoseInFrame", pose_json),
        Channel("/tf", "foxglove.FrameTransform", transform_json),
        Channel("/odom", "foxglove.PoseInFrame", odom_json),
        Channel("/map", "foxglove.Grid", grid_json),
        Channel("/log", "foxglove.Log", log_json),
        Channel("/mazebot/run_state", "mazebot.RunState", plain_json),
        Channel("/mazebot/slam", "mazebot.SlamStep", plain_json),
    )
}


def encode(topic: str, message: Any, log_time_ns: int) -> bytes:
    """JSON bytes of ``message`` on ``topic`` (compact, keys in a fixed order)."""
    channel = CHANNELS[topic]
    if channel.to_bytes is not None:
        return channel.to_bytes(message, log_time_ns)
    assert channel.to_json is not None
    return json.dumps(channel.to_json(message, log_time_ns), separators=(",", ":"), allow_nan=False).encode()
