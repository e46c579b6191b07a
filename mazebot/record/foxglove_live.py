"""Foxglove live: the running robot on the Foxglove WebSocket protocol, with the official SDK.

``[foxglove] enabled = true`` (and ``pip install 'mazebot[foxglove]'``) makes the daemon
serve what a recording holds, live, on its own port: open Foxglove, *Open connection*,
``ws://ROBOT:8765``. The server is the ``foxglove-sdk`` package's (Rust, on its own
tokio threads: ``foxglove.start_server`` returns at once and serves from those threads;
https://docs.foxglove.dev/docs/sdk). The daemon's side of it is this module's
:class:`FoxgloveLive`, fed by :mod:`mazebot.tasks.foxglove_task` on the event loop:

- typed channels of the SDK (protobuf, built and encoded in Rust): ``/scan``
  ``foxglove.LaserScan`` (equal bearings, ``+inf`` for no return), ``/tf``
  ``foxglove.FrameTransform`` (the recording's chain: :func:`~mazebot.record.schemas.transform_chain`),
  ``/pose`` and ``/odom`` ``foxglove.PoseInFrame``, ``/goal`` ``foxglove.PoseInFrame``,
  ``/path`` ``foxglove.PosesInFrame`` (the planned waypoints), ``/map`` ``foxglove.Grid``,
  ``/log`` ``foxglove.Log``;
- the recording's own JSON channels, ``/mazebot/run_state``, ``/mazebot/motors`` and
  ``/mazebot/encoders``, under their schema names with the recording's JSON schemas and
  encoders (:data:`mazebot.record.schemas.SCHEMAS`, :func:`~mazebot.record.schemas.encode`):
  one definition for the file and the wire.

Per message the loop does only what a subscribed client needs: a channel nobody is
subscribed to (``has_sinks()`` false) costs one call and no message is built. The SDK
drops the oldest message of a client whose queue is full (``message_backlog_size``), so
a slow laptop never holds the robot back.

Without the package nothing of this is imported; with ``enabled = true`` and no package
the daemon stops at start with one line (:class:`MissingFoxglove`).
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from mazebot.errors import ConfigError
from mazebot.io.scan import Scan
from mazebot.record.schemas import (
    CHANNELS,
    LASER_FRAME,
    LOG_LEVELS,
    MAP_FRAME,
    SCHEMA_ENCODING,
    SCHEMAS,
    Transform,
    encode,
    equal_bearings,
)

#: the recording's JSON channels that are sent live too (their topic's schema in ``CHANNELS``)
JSON_TOPICS = ("/mazebot/run_state", "/mazebot/motors", "/mazebot/encoders")


class MissingFoxglove(ConfigError):
    """``[foxglove] enabled = true`` without the optional ``foxglove-sdk`` package."""


def _import_foxglove() -> Any:
    try:
        import foxglove
    except ImportError:
        raise MissingFoxglove(
            "[foxglove] enabled = true needs the foxglove-sdk package: pip install 'mazebot[foxglove]'"
        ) from None
    return foxglove


class FoxgloveLive:
    """The SDK's WebSocket server and the daemon's channels on it (its own ``foxglove.Context``).

    Example::

        live = FoxgloveLive.start("127.0.0.1", 8765)
        live.scan(scan, time.time())
        live.stop()
    """

    def __init__(self, foxglove: Any, context: Any) -> None:
        from foxglove import channels, messages

        self._m = messages
        self.context = context  # kept: the SDK forgets a dropped context's channels (none is advertised)
        self.server: Any = None
        self.port = 0
        c = {"context": context}
        self._scan = channels.LaserScanChannel("/scan", **c)
        self._tf = channels.FrameTransformChannel("/tf", **c)
        self._pose = channels.PoseInFrameChannel("/pose", **c)
        self._odom = channels.PoseInFrameChannel("/odom", **c)
        self._goal = channels.PoseInFrameChannel("/goal", **c)
        self._path = channels.PosesInFrameChannel("/path", **c)
        self._map = channels.GridChannel("/map", **c)
        self._log = channels.LogChannel("/log", **c)
        self._json = {
            topic: foxglove.Channel(
                topic,
                schema=foxglove.Schema(
                    name=CHANNELS[topic].schema, encoding=SCHEMA_ENCODING, data=SCHEMAS[CHANNELS[topic].schema]
                ),
                message_encoding="json",
                context=context,
            )
            for topic in JSON_TOPICS
        }
        # LOG_LEVELS' numbers are foxglove.LogLevel's: Unknown 0 .. Fatal 5
        names = ("Unknown", "Debug", "Info", "Warning", "Error", "Fatal")
        self._levels = {value: getattr(messages.LogLevel, name) for value, name in enumerate(names)}

    @classmethod
    def start(cls, host: str, port: int, *, name: str = "mazebot", backlog: int = 256) -> FoxgloveLive:
        """Bind ``host:port`` and serve from the SDK's threads; returns once listening."""
        foxglove = _import_foxglove()
        context = foxglove.Context()
        live = cls(foxglove, context)  # the channels first: a client is told of them in its first answer
        try:
            live.server = foxglove.start_server(
                name=name, host=host, port=port, context=context, message_backlog_size=backlog
            )
        except Exception as exc:  # the SDK's bind error: port in use, no such address
            raise ConfigError(f"[foxglove] cannot listen on {host}:{port}: {exc}") from None
        live.port = live.server.port
        return live

    def stop(self) -> None:
        if self.server is not None:
            self.server.stop()
            self.server = None

    # -- messages: each returns at once when no client is subscribed ---------------------

    def _stamp(self, epoch_s: float) -> Any:
        return self._m.Timestamp.from_epoch_secs(epoch_s)

    def _yaw(self, theta_rad: float) -> Any:
        return self._m.Quaternion(x=0.0, y=0.0, z=math.sin(theta_rad / 2.0), w=math.cos(theta_rad / 2.0))

    def _pose_msg(self, x_m: float, y_m: float, theta_rad: float) -> Any:
        return self._m.Pose(position=self._m.Vector3(x=x_m, y=y_m, z=0.0), orientation=self._yaw(theta_rad))

    def scan(self, scan: Scan, epoch_s: float) -> None:
        if not self._scan.has_sinks() or len(scan) == 0:
            return
        ranges, intensities, step_rad = equal_bearings(scan)
        msg = self._m.LaserScan(
            timestamp=self._stamp(epoch_s),
            frame_id=LASER_FRAME,
            pose=self._pose_msg(0.0, 0.0, 0.0),
            start_angle=0.0,
            end_angle=step_rad * (len(ranges) - 1),
            ranges=ranges.tolist(),
            intensities=intensities.tolist(),
        )
        self._scan.log(msg, log_time=round(epoch_s * 1e9))

    def transforms(self, chain: tuple[Transform, ...], epoch_s: float) -> None:
        if not self._tf.has_sinks():
            return
        m, stamp, t_ns = self._m, self._stamp(epoch_s), round(epoch_s * 1e9)
        for t in chain:
            self._tf.log(
                m.FrameTransform(
                    timestamp=stamp,
                    parent_frame_id=t.parent,
                    child_frame_id=t.child,
                    translation=m.Vector3(x=t.x_m, y=t.y_m, z=0.0),
                    rotation=self._yaw(t.theta_rad),
                ),
                log_time=t_ns,
            )

    def pose(self, topic: str, frame: str, pose: tuple[float, float, float], epoch_s: float) -> None:
        channel = {"/pose": self._pose, "/odom": self._odom, "/goal": self._goal}[topic]
        if not channel.has_sinks():
            return
        channel.log(
            self._m.PoseInFrame(timestamp=self._stamp(epoch_s), frame_id=frame, pose=self._pose_msg(*pose)),
            log_time=round(epoch_s * 1e9),
        )

    def path(self, waypoints: list[tuple[float, float]], epoch_s: float) -> None:
        if not self._path.has_sinks():
            return
        poses = [self._pose_msg(float(x), float(y), 0.0) for x, y in waypoints]
        self._path.log(
            self._m.PosesInFrame(timestamp=self._stamp(epoch_s), frame_id=MAP_FRAME, poses=poses),
            log_time=round(epoch_s * 1e9),
        )

    @property
    def map_wanted(self) -> bool:
        """A client is subscribed to ``/map`` (the three-state grid is worth computing)."""
        return self._map.has_sinks()

    def grid(self, three_state: np.ndarray, resolution_m: float, origin_m: tuple[float, float], epoch_s: float
             ) -> None:
        """The map as one INT8 field ``occupancy`` (-1, 0, 100), row 0 south, like the recording's."""
        if not self._map.has_sinks():
            return
        m = self._m
        cols = three_state.shape[1]
        self._map.log(
            m.Grid(
                timestamp=self._stamp(epoch_s),
                frame_id=MAP_FRAME,
                pose=self._pose_msg(float(origin_m[0]), float(origin_m[1]), 0.0),
                column_count=int(cols),
                cell_size=m.Vector2(x=resolution_m, y=resolution_m),
                row_stride=int(cols),
                cell_stride=1,
                fields=[m.PackedElementField(name="occupancy", offset=0, type=m.PackedElementFieldNumericType.Int8)],
                data=np.ascontiguousarray(three_state, dtype=np.int8).tobytes(),
            ),
            log_time=round(epoch_s * 1e9),
        )

    def log(self, level: str, name: str, message: str, file: str, line: int, epoch_s: float) -> None:
        if not self._log.has_sinks():
            return
        self._log.log(
            self._m.Log(
                timestamp=self._stamp(epoch_s),
                level=self._levels[LOG_LEVELS.get(level, 0)],
                message=message,
                name=name,
                file=file,
                line=int(line),
            ),
            log_time=round(epoch_s * 1e9),
        )

    def json(self, topic: str, obj: dict[str, Any], epoch_s: float) -> None:
        """One of :data:`JSON_TOPICS`, encoded exactly as the recording encodes it."""
        channel = self._json[topic]
        if not channel.has_sinks():
            return
        t_ns = round(epoch_s * 1e9)
        channel.log(encode(topic, obj, t_ns), log_time=t_ns)


class LiveLogHandler(logging.Handler):
    """Log records of the ``mazebot`` logger onto ``/log`` (any thread may log; the SDK is thread-safe)."""

    def __init__(self, live: FoxgloveLive) -> None:
        super().__init__(logging.INFO)
        self._live = live

    def emit(self, record: logging.LogRecord) -> None:
        if getattr(record, "secret", False):
            return  # a line carrying a secret (the first-start PIN) never leaves the robot
        self._live.log(record.levelname, record.name, record.getMessage(), record.pathname, record.lineno,
                       record.created)

