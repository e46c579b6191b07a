"""A recording as a ROS 2 bag: ``mazebot export-bag RUN.mcap OUT/``.

The bag is rosbag2 (metadata version 8, MCAP storage, CDR messages), written with the
pure-Python ``rosbags`` library (https://ternaris.gitlab.io/rosbags/), so ``ros2 bag play
OUT/`` feeds rviz2, slam_toolbox or Nav2 with no ROS on the robot. Topics:

- ``/scan`` ``sensor_msgs/msg/LaserScan`` in ``laser``, from the exact samples of
  ``/mazebot/scan_raw``: a LaserScan needs equal angle steps, so each revolution goes onto
  one bearing per sample (the nearest, counter-clockwise from the heading as in ROS) and a
  bearing without a valid return is ``+inf`` (REP 117: "no return"). Every ray is taken at
  the header's time (``time_increment`` 0), the middle of the revolution;
- ``/odom`` ``nav_msgs/msg/Odometry`` (``odom`` → ``base_link``), the twist the body-frame
  velocity between two readings;
- ``/tf`` ``tf2_msgs/msg/TFMessage`` (``map → odom``, ``odom → base_link``) and
  ``/tf_static`` (``base_link → laser``) with transient-local durability, as tf2 expects;
- ``/map`` ``nav_msgs/msg/OccupancyGrid`` (-1 unknown, 0 free, 100 occupied), transient
  local, so a subscriber that joins late (rviz2, Nav2's costmap) still gets the last map.

The offered QoS of every topic is written into ``metadata.yaml`` (``offered_qos_profiles``),
which ``ros2 bag play`` replays with. ``odometry_only`` leaves ``map → odom`` and ``/map``
out, so slam_toolbox can build its own from ``/scan`` and the odometry.

Bad input is one line (:class:`RecordingError`); the bag is written into a hidden folder
beside ``OUT`` and moved into place when complete, so a failure leaves nothing behind.
"""

from __future__ import annotations

import base64
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np

from mazebot.errors import UsageError
from mazebot.record.reader import Recording, RecordingError
from mazebot.record.schemas import LASER_FRAME, MAP_FRAME, ODOM_FRAME, ROBOT_FRAME, equal_bearings, scan_from_json

#: rosbag2's metadata version that ROS 2 Jazzy writes and reads (rosbag2_storage/bag_metadata.hpp)
BAG_VERSION: Final = 8
TOPICS = {
    "/scan": "sensor_msgs/msg/LaserScan",
    "/odom": "nav_msgs/msg/Odometry",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/tf_static": "tf2_msgs/msg/TFMessage",
    "/map": "nav_msgs/msg/OccupancyGrid",
}
#: topics a late subscriber must still get (tf2's static broadcaster, map_server's map)
LATCHED = ("/tf_static", "/map")


class MissingRosbags(UsageError):
    """``export-bag`` was asked for without the optional ``rosbags`` package."""


@dataclass
class BagSummary:
    out: str
    messages: dict[str, int]


def _qos(latched: bool) -> Any:
    """Reliable, keep-last: volatile depth 10, or transient-local depth 1 for a latched topic.

    Reliable offers suit reliable and best-effort subscribers alike (ROS 2 "QoS compatibilities").
    Unset times are rmw's "infinite" (2147483647 s, 4294967295 ns), as rosbags' converter writes them.
    """
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    forever = QosTime(2147483647, 4294967295)
    return Qos(
        QosHistory.KEEP_LAST,
        1 if latched else 10,
        QosReliability.RELIABLE,
        QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE,
        forever,
        forever,
        QosLiveliness.AUTOMATIC,
        forever,
        False,
    )


def _time(types: Any, t_ns: int) -> Any:
    return types["builtin_interfaces/msg/Time"](sec=int(t_ns // 1_000_000_000), nanosec=int(t_ns % 1_000_000_000))


def _header(types: Any, t_ns: int, frame: str) -> Any:
    return types["std_msgs/msg/Header"](stamp=_time(types, t_ns), frame_id=frame)


def _quaternion(types: Any, q: dict[str, float]) -> Any:
    return types["geometry_msgs/msg/Quaternion"](x=q["x"], y=q["y"], z=q["z"], w=q["w"])


def _pose(types: Any, pose: dict[str, Any]) -> Any:
    p = pose["position"]
    return types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=p["x"], y=p["y"], z=p["z"]),
        orientation=_quaternion(types, pose["orientation"]),
    )


def _yaw(q: dict[str, float]) -> float:
    return 2.0 * math.atan2(q["z"], q["w"])


def _ns(stamp: dict[str, int]) -> int:
    return int(stamp["sec"]) * 1_000_000_000 + int(stamp["nsec"])


class _Converter:
    """Recorded JSON messages to ROS 2 messages, one topic at a time."""

    def __init__(self, types: Any, epoch_offset_ns: int, range_min_m: float, range_max_m: float) -> None:
        self.t = types
        self.epoch_offset_ns = epoch_offset_ns  # daemon clock seconds -> the recording's epoch stamps
        self.range_min_m = range_min_m
        self.range_max_m = range_max_m
        self._last_odom: tuple[int, float, float, float] | None = None

    def scan(self, data: dict[str, Any]) -> tuple[int, Any] | None:
        scan = scan_from_json(data)
        if len(scan) == 0:
            return None
        ranges, intensities, step_rad = equal_bearings(scan)
        start_s, end_s = float(scan.time_s.min()), float(scan.time_s.max())
        stamp_ns = round(((start_s + end_s) / 2) * 1e9) + self.epoch_offset_ns
        msg = self.t["sensor_msgs/msg/LaserScan"](
            header=_header(self.t, stamp_ns, LASER_FRAME),
            angle_min=0.0,
            angle_max=step_rad * (len(ranges) - 1),
            angle_increment=step_rad,
            time_increment=0.0,
            scan_time=end_s - start_s,
            range_min=self.range_min_m,
            range_max=self.range_max_m,
            ranges=ranges,
            intensities=intensities,
        )
        return stamp_ns, msg

    def odom(self, data: dict[str, Any]) -> tuple[int, Any]:
        t = self.t
        stamp_ns = _ns(data["timestamp"])
        pos, q = data["pose"]["position"], data["pose"]["orientation"]
        x, y, th = pos["x"], pos["y"], _yaw(q)
        v_mps = w_radps = 0.0
        if self._last_odom is not None and stamp_ns > self._last_odom[0]:
            t0, x0, y0, th0 = self._last_odom
            dt_s = (stamp_ns - t0) * 1e-9
            # the displacement in the body frame (REP 105: the twist is in child_frame_id)
            v_mps = (math.cos(th0) * (x - x0) + math.sin(th0) * (y - y0)) / dt_s
            w_radps = math.remainder(th - th0, math.tau) / dt_s
        self._last_odom = (stamp_ns, x, y, th)
        vec = t["geometry_msgs/msg/Vector3"]
        msg = t["nav_msgs/msg/Odometry"](
            header=_header(t, stamp_ns, ODOM_FRAME),
            child_frame_id=ROBOT_FRAME,
            pose=t["geometry_msgs/msg/PoseWithCovariance"](
                pose=_pose(t, data["pose"]), covariance=np.zeros(36, dtype=np.float64)
            ),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](
                twist=t["geometry_msgs/msg/Twist"](
                    linear=vec(x=v_mps, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=w_radps)
                ),
                covariance=np.zeros(36, dtype=np.float64),
            ),
        )
        return stamp_ns, msg

    def transform(self, data: dict[str, Any]) -> Any:
        t = self.t
        tr = data["translation"]
        return t["geometry_msgs/msg/TransformStamped"](
            header=_header(t, _ns(data["timestamp"]), data["parent_frame_id"]),
            child_frame_id=data["child_frame_id"],
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](x=tr["x"], y=tr["y"], z=tr["z"]),
                rotation=_quaternion(t, data["rotation"]),
            ),
        )

    def tf_message(self, transforms: list[Any]) -> Any:
        return self.t["tf2_msgs/msg/TFMessage"](transforms=transforms)

    def grid(self, data: dict[str, Any]) -> tuple[int, Any]:
        t = self.t
        stamp_ns = _ns(data["timestamp"])
        cells = np.frombuffer(base64.b64decode(data["data"]), dtype=np.int8).copy()
        cols = int(data["column_count"])
        msg = t["nav_msgs/msg/OccupancyGrid"](
            header=_header(t, stamp_ns, MAP_FRAME),
            info=t["nav_msgs/msg/MapMetaData"](
                map_load_time=_time(t, stamp_ns),
                resolution=float(data["cell_size"]["x"]),
                width=cols,
                height=cells.size // cols if cols else 0,
                origin=_pose(t, data["pose"]),
            ),
            data=cells,  # row-major from the origin (bottom-left), as foxglove.Grid and ROS both have it
        )
        return stamp_ns, msg


def _epoch_offset_ns(recording: Recording) -> int:
    """Recorded stamps minus the daemon clock's time in a payload: the shift the tap applied."""
    for m in recording.messages(["/mazebot/encoders"]):
        return m.log_time_ns - round(float(m.data["time_s"]) * 1e9)
    return 0


def export_bag(mcap_path: str | os.PathLike[str], out: str | os.PathLike[str], *, odometry_only: bool = False
               ) -> BagSummary:
    """Write the recording at ``mcap_path`` as a rosbag2 folder ``out`` (which must not exist)."""
    try:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise MissingRosbags("export-bag needs the rosbags package: pip install 'mazebot[ros]'") from None
    from mazebot.record.replay import recorded_config

    out = Path(out)
    if out.exists():
        raise UsageError(f"{out} exists already; export-bag writes a new folder (remove it or pick another)")
    if not out.parent.is_dir():
        raise UsageError(f"{out.parent} is not a folder; export-bag writes OUT inside an existing folder")
    recording = Recording.open(mcap_path)
    if "/tf" not in recording.schemas:
        raise RecordingError(f"{recording.path} has no /tf (recorded by an older mazebot); it cannot become a bag")
    config = recorded_config(recording)
    store = get_typestore(Stores.ROS2_HUMBLE)  # these five types are the same in Humble, Jazzy and Kilted
    conv = _Converter(store.types, _epoch_offset_ns(recording), config.lidar.min_range_m, config.lidar.max_range_m)
    wanted = ["/mazebot/scan_raw", "/odom", "/tf", "/map"]
    topics = dict(TOPICS)
    if odometry_only:
        wanted.remove("/map")
        del topics["/map"]
    staging = out.with_name(f".{out.name}.partial")  # the bag is built in here, then moved out whole
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir()
    partial = staging / out.name  # rosbags names the storage file after the bag's folder
    counts = dict.fromkeys(topics, 0)
    try:
        with Writer(partial, version=BAG_VERSION, storage_plugin=StoragePlugin.MCAP) as writer:
            conns = {
                topic: writer.add_connection(
                    topic, msgtype, typestore=store, offered_qos_profiles=[_qos(topic in LATCHED)]
                )
                for topic, msgtype in topics.items()
            }

            def write(topic: str, stamp_ns: int, msg: Any) -> None:
                writer.write(conns[topic], stamp_ns, store.serialize_cdr(msg, topics[topic]))
                counts[topic] += 1

            pending: list[Any] = []  # the dynamic transforms of one instant, sent as one TFMessage
            pending_ns = -1
            static_sent = False
            for m in recording.messages(wanted):
                if m.topic != "/tf" and pending:
                    write("/tf", pending_ns, conv.tf_message(pending))
                    pending = []
                if m.topic == "/mazebot/scan_raw":
                    converted = conv.scan(m.data)
                    if converted is not None:
                        write("/scan", *converted)
                elif m.topic == "/odom":
                    write("/odom", *conv.odom(m.data))
                elif m.topic == "/map":
                    write("/map", *conv.grid(m.data))
                elif m.data["child_frame_id"] == LASER_FRAME:
                    if not static_sent:
                        write("/tf_static", m.log_time_ns, conv.tf_message([conv.transform(m.data)]))
                        static_sent = True
                elif not (odometry_only and m.data["parent_frame_id"] == MAP_FRAME):
                    if pending and m.log_time_ns != pending_ns:
                        write("/tf", pending_ns, conv.tf_message(pending))
                        pending = []
                    pending.append(conv.transform(m.data))
                    pending_ns = m.log_time_ns
            if pending:
                write("/tf", pending_ns, conv.tf_message(pending))
        partial.rename(out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return BagSummary(str(out), counts)
