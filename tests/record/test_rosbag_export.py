"""``mazebot export-bag``: a recorded run as a ROS 2 bag, read back with rosbags' own reader.

The bag is checked against the MCAP it came from: message types, frames, the QoS in the
metadata, a revolution's ranges, the odometry and the map.
"""

from __future__ import annotations

import base64
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rosbags.interfaces import QosDurability
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from mazebot.bench.runner import RunSpec, run_one
from mazebot.config import Config
from mazebot.record.reader import Recording
from mazebot.record.rosbag_export import export_bag
from mazebot.record.schemas import equal_bearings, scan_from_json
from mazebot.run_session import RunSession

pytestmark = pytest.mark.slow  # a whole simulated run recorded first

MAZE = str(Path(__file__).resolve().parents[2] / "mazebot" / "sim" / "mazes" / "minimaze.txt")
STORE = get_typestore(Stores.ROS2_HUMBLE)


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A short recorded simulated run (the minimaze's scripted tour, virtual time)."""
    from mazebot.bench import runner

    base = tmp_path_factory.mktemp("bag")
    config = Config()
    config.daemon.state_dir = str(base / "state")
    config.lidar.mount_x_m = 0.02  # an offset, so base_link -> laser is not the identity
    session = RunSession.from_options(config, record=str(base / "run.mcap"))
    original = runner.run_daemon

    def with_session(*args, **kwargs):
        kwargs["session"] = session
        return original(*args, **kwargs)

    runner.run_daemon = with_session
    try:
        run_one(config, RunSpec(maze_path=MAZE, size=None, seed=1))
    finally:
        runner.run_daemon = original
    return base / "run.mcap"


@pytest.fixture(scope="module")
def bag(recording: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("out") / "run_bag"
    export_bag(recording, out)
    return out


def _messages(bag: Path, topic: str) -> list[tuple[int, object]]:
    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        return [(t, STORE.deserialize_cdr(raw, c.msgtype)) for c, t, raw in reader.messages(connections=conns)]


def _ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def test_bag_has_the_ros_types_mcap_storage_and_latched_map_and_static_tf(bag: Path) -> None:
    with Reader(bag) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == {
            "/scan": "sensor_msgs/msg/LaserScan",
            "/odom": "nav_msgs/msg/Odometry",
            "/tf": "tf2_msgs/msg/TFMessage",
            "/tf_static": "tf2_msgs/msg/TFMessage",
            "/map": "nav_msgs/msg/OccupancyGrid",
        }
        durability = {c.topic: c.ext.offered_qos_profiles[0].durability for c in reader.connections}
        assert all(c.ext.serialization_format == "cdr" for c in reader.connections)
    assert durability["/map"] is durability["/tf_static"] is QosDurability.TRANSIENT_LOCAL
    assert durability["/scan"] is durability["/tf"] is QosDurability.VOLATILE
    metadata = (bag / "metadata.yaml").read_text()
    assert "storage_identifier: mcap" in metadata and "offered_qos_profiles" in metadata
    assert [p.suffix for p in bag.iterdir() if p.name != "metadata.yaml"] == [".mcap"]


def test_scans_are_the_recorded_revolutions_with_inf_for_no_return(recording: Path, bag: Path) -> None:
    raw = [scan_from_json(m.data) for m in Recording.open(recording).messages(["/mazebot/scan_raw"])]
    scans = _messages(bag, "/scan")
    assert len(scans) == len([s for s in raw if len(s)]) > 20
    _, msg = scans[len(scans) // 2]
    revolution = [s for s in raw if len(s)][len(scans) // 2]
    assert msg.header.frame_id == "laser"
    assert len(msg.ranges) == len(revolution)
    assert msg.angle_increment == pytest.approx(2 * math.pi / len(revolution))
    assert (msg.range_min, msg.range_max) == pytest.approx((0.15, 12.0))  # float32 in the message
    # every valid sample is on the bearing nearest its angle, within float32
    step = msg.angle_increment
    valid = revolution.valid & (revolution.range_m > 0)
    bearing = np.rint(np.remainder(revolution.angle_rad, 2 * math.pi) / step).astype(int) % len(revolution)
    hits = np.asarray(msg.ranges)[bearing[valid]]
    assert np.mean(np.isclose(hits, revolution.range_m[valid], rtol=1e-6)) > 0.9  # the rest: two on one bearing
    assert np.isposinf(msg.ranges).sum() == len(revolution) - len(set(bearing[valid].tolist()))
    # the stamp is mid-revolution on the recording's epoch clock
    # the revolution's span, rounded to the message's float32 (sensor_msgs/LaserScan)
    assert msg.scan_time == float(np.float32(np.ptp(revolution.time_s)))


def test_equal_bearings_marks_invalid_and_missing_bearings_inf() -> None:
    from mazebot.io.scan import Scan

    angle = np.array([0.0, math.pi / 2, math.pi, 3 * math.pi / 2 + 0.1])
    scan = Scan(angle, np.array([1.0, 2.0, 3.0, 4.0]), np.array([9, 8, 7, 6], dtype=np.uint8),
                np.arange(4) * 0.01, np.array([True, False, True, True]), revolution=1)
    ranges, intensities, step = equal_bearings(scan)
    assert step == pytest.approx(math.pi / 2)
    assert ranges.tolist() == [1.0, math.inf, 3.0, 4.0] and intensities.tolist() == [9, 0, 7, 6]


def test_transforms_and_odometry_match_the_recording(recording: Path, bag: Path) -> None:
    static = _messages(bag, "/tf_static")
    assert len(static) == 1
    (laser,) = static[0][1].transforms
    assert (laser.header.frame_id, laser.child_frame_id) == ("base_link", "laser")
    assert laser.transform.translation.x == pytest.approx(0.02)
    tf = _messages(bag, "/tf")
    pairs = {(t.header.frame_id, t.child_frame_id) for _, m in tf for t in m.transforms}
    assert pairs == {("map", "odom"), ("odom", "base_link")}
    recorded_odom = {m.log_time_ns: m.data for m in Recording.open(recording).messages(["/odom"])}
    odom = _messages(bag, "/odom")
    assert len(odom) == len(recorded_odom)
    speeds = []
    for t, msg in odom:
        assert (msg.header.frame_id, msg.child_frame_id) == ("odom", "base_link")
        assert _ns(msg.header.stamp) == t
        want = recorded_odom[t]["pose"]["position"]
        assert (msg.pose.pose.position.x, msg.pose.pose.position.y) == (want["x"], want["y"])
        speeds.append(msg.twist.twist.linear.x)
    # the scripted tour drives forward at the planner's speeds: never faster than the drive's limit
    assert 0.05 < max(speeds) < Config().drive.max_speed_mps * 1.5


def test_map_is_the_last_recorded_grid(recording: Path, bag: Path) -> None:
    grids = [m.data for m in Recording.open(recording).messages(["/map"])]
    maps = _messages(bag, "/map")
    assert len(maps) == len(grids)
    msg, last = maps[-1][1], grids[-1]
    assert msg.header.frame_id == "map"
    assert msg.info.width == last["column_count"]
    assert msg.info.resolution == pytest.approx(last["cell_size"]["x"])
    assert msg.info.origin.position.x == last["pose"]["position"]["x"]
    cells = np.frombuffer(base64.b64decode(last["data"]), dtype=np.int8)
    assert np.array_equal(msg.data, cells) and set(np.unique(cells).tolist()) == {-1, 0, 100}


def test_odometry_only_leaves_map_and_its_correction_out(recording: Path, tmp_path: Path) -> None:
    out = tmp_path / "odo"
    export_bag(recording, out, odometry_only=True)
    with Reader(out) as reader:
        assert "/map" not in {c.topic for c in reader.connections}
    pairs = {(t.header.frame_id, t.child_frame_id) for _, m in _messages(out, "/tf") for t in m.transforms}
    assert pairs == {("odom", "base_link")}


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "mazebot", "export-bag", *args], capture_output=True, text=True,
                          timeout=120)


def test_bad_input_is_one_line_and_leaves_nothing(recording: Path, tmp_path: Path) -> None:
    not_mcap = tmp_path / "x.mcap"
    not_mcap.write_text("hello")
    done = _cli(str(not_mcap), str(tmp_path / "b1"))
    assert done.returncode == 2 and "not a readable MCAP file" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
    (tmp_path / "taken").mkdir()
    done = _cli(str(recording), str(tmp_path / "taken"))
    assert done.returncode == 2 and "exists already" in done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken", "x.mcap"]  # nothing half-written
    done = _cli(str(recording), str(tmp_path / "good"))
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["good", "taken", "x.mcap"]
