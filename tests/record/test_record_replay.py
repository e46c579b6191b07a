"""Record → replay → same map; the MCAP file through the real ``mcap`` reader; saved runs and resume.

One simulated run (the minimaze, scripted drive, virtual time) is recorded and saved
once per module; the tests check it against ground truth: the live SLAM's final map,
the daemon's own counters, the saved files read back.
"""

from __future__ import annotations

import math
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader

from mazebot.bench import runner
from mazebot.bench.runner import RunSpec, run_one
from mazebot.config import Config
from mazebot.errors import UsageError
from mazebot.persist.export import export_json, export_pgm, export_png, export_svg, three_state
from mazebot.persist.resume import resume_slam
from mazebot.persist.runs import find_run
from mazebot.persist.snapshot import load_run
from mazebot.record.reader import Recording
from mazebot.record.replay import occupied_iou, recorded_config, replay, write_outputs
from mazebot.record.schemas import scan_from_json
from mazebot.run_session import RunSession
from mazebot.slam.ekf import OdometryHistory
from mazebot.slam.map_export import read_ros_map
from mazebot.slam.odometry import DiffDriveOdometry
from mazebot.slam.slam import SlamParams

pytestmark = pytest.mark.slow  # whole simulated runs recorded and replayed

MAZE = str(Path(__file__).resolve().parents[2] / "mazebot" / "sim" / "mazes" / "minimaze.txt")

EXPECTED_SCHEMAS = {
    "/scan": "foxglove.LaserScan",
    "/pose": "foxglove.PoseInFrame",
    "/odom": "foxglove.PoseInFrame",
    "/tf": "foxglove.FrameTransform",
    "/map": "foxglove.Grid",
    "/log": "foxglove.Log",
    "/mazebot/scan_raw": "mazebot.Scan",
    "/mazebot/encoders": "mazebot.EncoderTicks",
    "/mazebot/motors": "mazebot.MotorCommand",
    "/mazebot/run_state": "mazebot.RunState",
    "/mazebot/slam": "mazebot.SlamStep",
}


@dataclass
class LiveRun:
    recording: Path
    state: Any
    run_dir: Path
    config: Config


def _run_with_session(config: Config, session: RunSession, spec: RunSpec) -> tuple[dict, Any]:
    original = runner.run_daemon

    def with_session(*args: Any, **kwargs: Any) -> Any:
        kwargs["session"] = session
        return original(*args, **kwargs)

    runner.run_daemon = with_session  # type: ignore[assignment]
    try:
        return run_one(config, spec)
    finally:
        runner.run_daemon = original  # type: ignore[assignment]


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> LiveRun:
    base = tmp_path_factory.mktemp("live")
    config = Config()
    config.daemon.state_dir = str(base / "state")
    session = RunSession.from_options(config, record=str(base / "live.mcap"))
    _, record = _run_with_session(config, session, RunSpec(maze_path=MAZE, size=None, seed=1))
    assert record.driver.done
    assert session.run_dir is not None
    return LiveRun(base / "live.mcap", record.state, session.run_dir, config)


def test_recording_has_foxglove_schemas_and_every_message(live: LiveRun) -> None:
    with live.recording.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None
        by_topic = {c.topic: summary.schemas[c.schema_id] for c in summary.channels.values()}
        assert {t: s.name for t, s in by_topic.items()} == EXPECTED_SCHEMAS
        assert all(s.encoding == "jsonschema" for s in by_topic.values())
        assert {c.message_encoding for c in summary.channels.values()} == {"json"}
        counted = {c.topic: 0 for c in summary.channels.values()}
        for _, channel, _ in reader.iter_messages():
            counted[channel.topic] += 1
    state = live.state
    assert state.record.dropped == 0
    assert counted["/scan"] == counted["/mazebot/scan_raw"] == state.sensors.lidar_revolutions
    steps = Recording.open(live.recording).messages(["/mazebot/slam"])
    slam_updates = sum(1 for m in steps if m.data["kind"] == "update")
    assert slam_updates == state.slam.scans
    assert counted["/mazebot/encoders"] > 8 * state.slam.scans  # 50 Hz odometry vs 5.5 Hz lidar
    assert counted["/pose"] > 0 and counted["/map"] > 0 and counted["/mazebot/motors"] > 0
    assert sum(counted.values()) == state.record.messages


def test_laser_scan_message_follows_the_foxglove_schema(live: LiveRun) -> None:
    msg = next(Recording.open(live.recording).messages(["/scan"])).data
    assert set(msg) == {"timestamp", "frame_id", "pose", "start_angle", "end_angle", "ranges", "intensities"}
    assert set(msg["timestamp"]) == {"sec", "nsec"} and msg["timestamp"]["sec"] > 1_600_000_000  # epoch seconds
    assert msg["pose"]["orientation"] == {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}
    assert len(msg["ranges"]) == len(msg["intensities"]) > 100


def _yaw(q: dict[str, float]) -> float:
    assert q["x"] == q["y"] == 0.0  # planar: a rotation about z only
    return 2.0 * math.atan2(q["z"], q["w"])


def _se2(a: tuple[float, float, float], b: tuple[float, float, float]) -> tuple[float, float, float]:
    """``a ⊕ b`` written out here, not taken from the code under test."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], a[2] + b[2])


def test_transform_chain_gives_back_every_recorded_pose(live: LiveRun) -> None:
    """map -> odom -> base_link composes to ``/pose``; odom -> base_link is ``/odom``; laser hangs off base_link."""
    rec = Recording.open(live.recording)
    tf: dict[int, dict[tuple[str, str], dict]] = {}
    odom: dict[int, dict] = {}
    poses: dict[int, dict] = {}
    for m in rec.messages(["/tf", "/odom", "/pose"]):
        if m.topic == "/tf":
            d = m.data
            assert m.log_time_ns == d["timestamp"]["sec"] * 1_000_000_000 + d["timestamp"]["nsec"]
            tf.setdefault(m.log_time_ns, {})[(d["parent_frame_id"], d["child_frame_id"])] = d
        else:
            (odom if m.topic == "/odom" else poses)[m.log_time_ns] = m.data
    assert len(tf) == len(odom) > 50
    assert set(odom) <= set(poses)
    corrections = []
    for t, frames in tf.items():
        assert set(frames) == {("map", "odom"), ("odom", "base_link"), ("base_link", "laser")}
        edge = {k: (v["translation"]["x"], v["translation"]["y"], _yaw(v["rotation"])) for k, v in frames.items()}
        o = odom[t]
        assert o["frame_id"] == "odom"
        assert edge[("odom", "base_link")] == pytest.approx(
            (o["pose"]["position"]["x"], o["pose"]["position"]["y"], _yaw(o["pose"]["orientation"])), abs=1e-12
        )
        assert edge[("base_link", "laser")] == (live.config.lidar.mount_x_m, live.config.lidar.mount_y_m, 0.0)
        x, y, th = _se2(edge[("map", "odom")], edge[("odom", "base_link")])
        p = poses[t]
        assert p["frame_id"] == "map"
        px, py, pth = p["pose"]["position"]["x"], p["pose"]["position"]["y"], _yaw(p["pose"]["orientation"])
        assert (x, y) == pytest.approx((px, py), abs=1e-9)
        assert math.remainder(th - pth, math.tau) == pytest.approx(0.0, abs=1e-9)
        corrections.append(edge[("map", "odom")])
    # SLAM corrected the wheel odometry (slip, the simulated wheels' errors) during the tour: map -> odom moved
    drift_m = max(math.hypot(c[0], c[1]) for c in corrections)
    assert 1e-3 < drift_m < 1.0


def test_odom_is_the_dead_reckoning_of_the_recorded_encoder_ticks(live: LiveRun) -> None:
    """``/odom`` against the recorded tick totals integrated again by the odometry model.

    ``/odom`` is stamped with the time its pose is true at (``pose_time_s``: the newest encoder
    edge counted, as lgpio stamps it), not the time of the reading; so each is matched to the
    reading whose ``pose_time_s`` it carries (the last one, where a reading and an edge sample
    before it share one), after the recording's one shift from the clock's seconds to the epoch.
    """
    cfg = live.config
    rec = Recording.open(live.recording)
    model = DiffDriveOdometry(cfg.encoders.ticks_per_rev, cfg.drive.wheel_diameter_m, cfg.drive.track_width_m)
    epoch_s, pose_s, poses = [], [], []
    for m in rec.messages(["/mazebot/encoders"]):
        model.update(m.data["left_ticks"], m.data["right_ticks"])
        epoch_s.append(m.log_time_ns * 1e-9 - m.data["time_s"])
        if m.data.get("pose_time_s") is not None:
            pose_s.append(m.data["pose_time_s"])
            poses.append((model.pose.x_m, model.pose.y_m))
    offset_s = float(np.median(epoch_s))  # one shift for the whole recording (RecordingTap.epoch_offset_s)
    order = np.argsort(pose_s, kind="stable")
    times_s, xy = np.asarray(pose_s)[order], np.asarray(poses)[order]
    odom = list(rec.messages(["/odom"]))
    matched = 0
    for m in odom:
        t_s = m.log_time_ns * 1e-9 - offset_s
        k = int(np.searchsorted(times_s, t_s + 1e-6, side="right")) - 1  # the epoch in float seconds: 0.24 µs apart
        if k < 0 or t_s - times_s[k] > 1e-6:
            continue
        pos = m.data["pose"]["position"]
        assert (pos["x"], pos["y"]) == pytest.approx(tuple(xy[k]), abs=1e-9), (t_s, times_s[k])
        matched += 1
    assert matched >= 0.9 * len(odom) and matched > 50, (matched, len(odom))


def test_replay_reproduces_the_live_map(live: LiveRun) -> None:
    result = replay(Recording.open(live.recording))
    assert result.mode == "steps"
    assert result.updates == live.state.slam.scans
    assert result.missing_scans == 0 and result.odometry_mismatches == 0
    iou = occupied_iou(live.state.map, result.slam.grid)
    assert iou >= 0.98, iou
    assert len(result.slam.closures) == live.state.slam.loop_closures


def test_replaying_twice_writes_the_same_bytes(live: LiveRun, tmp_path: Path) -> None:
    outputs = []
    for name in ("a", "b"):
        files = write_outputs(replay(Recording.open(live.recording)), tmp_path / name)
        outputs.append({k: p.read_bytes() for k, p in files.items()})
    assert outputs[0] == outputs[1]
    assert len(outputs[0]["trajectory"].splitlines()) == live.state.slam.scans


def test_saved_run_exports_round_trip(live: LiveRun, tmp_path: Path) -> None:
    saved = load_run(find_run(live.run_dir.parent, "latest"))
    assert len(saved.keyframes) == live.state.slam.keyframes
    expected = live.state.map.three_state()
    np.testing.assert_array_equal(three_state(saved), expected)  # the saved grid is the final live grid
    pgm, yaml = export_pgm(saved, tmp_path / "maze")
    raw = pgm.read_bytes()
    pixels = np.frombuffer(raw[-expected.size :], dtype=np.uint8).reshape(expected.shape)[::-1]
    assert set(np.unique(pixels)) <= {0, 205, 254}
    assert np.array_equal(pixels == 0, expected == 100) and np.array_equal(pixels == 254, expected == 0)
    ros = read_ros_map(yaml)
    np.testing.assert_array_equal(ros.three_state, expected)
    assert ros.resolution_m == live.state.map.resolution_m
    assert ros.origin[:2] == pytest.approx(live.state.map.origin_m)
    png = export_png(saved, tmp_path / "maze")[0].read_bytes()
    assert png.startswith(b"\x89PNG\r\n\x1a\n")
    assert "<polyline" in export_svg(saved, tmp_path / "maze")[0].read_text()


def test_cell_graph_of_the_minimaze(live: LiveRun, tmp_path: Path) -> None:
    import json

    saved = load_run(live.run_dir)
    graph = json.loads(export_json(saved, tmp_path / "graph")[0].read_text())
    assert graph["explored_order"] is None  # no planner recorded it: null, not invented
    assert graph["start"] is not None and graph["open_links"]
    dead_ends = {tuple(c) for c in graph["dead_ends"]}
    kinds = {tuple(c["cell"]): c["kind"] for c in graph["cells"]}
    assert dead_ends and all(kinds[c] == "dead_end" for c in dead_ends)


def _first_scan_and_odometry(recording: Recording) -> tuple[Any, OdometryHistory]:
    config = recorded_config(recording)
    odo = DiffDriveOdometry(config.encoders.ticks_per_rev, config.drive.wheel_diameter_m, config.drive.track_width_m)
    history = OdometryHistory(config.slam.odometry_history_s)
    scan = None
    for msg in recording.messages(["/mazebot/scan_raw", "/mazebot/encoders"]):
        if msg.topic == "/mazebot/encoders":
            odo.update(msg.data["left_ticks"], msg.data["right_ticks"])
            history.append(msg.data["time_s"], odo.pose.x_m, odo.pose.y_m, odo.pose.theta_rad)
            if scan is not None and history.latest[0] >= scan.end_time_s:
                return scan, history
        elif scan is None:
            scan = scan_from_json(msg.data)
    raise AssertionError("no scan covered by odometry")


@pytest.mark.parametrize("guess", [(0.07, -0.06, 0.2), (-0.08, 0.05, -0.25), (0.0, 0.0, 0.0)])
def test_resume_relocalizes_from_an_unknown_pose(live: LiveRun, guess: tuple[float, float, float]) -> None:
    recording = Recording.open(live.recording)
    scan, history = _first_scan_and_odometry(recording)
    saved = load_run(live.run_dir)
    # the live SLAM kept this very revolution as keyframe 0: its pose is the reference
    reference = next(kf.pose for kf in saved.keyframes if kf.time_s == scan.end_time_s)
    params = SlamParams.from_config(live.config.slam, live.config.lidar)
    slam = resume_slam(params, saved, guess=guess, background=False)
    update = slam.update(scan, history)
    assert slam.relocalization is not None and slam.relocalization.accepted
    error_m = math.hypot(*(update.pose[:2] - reference[:2]))
    assert error_m < 0.01, (update.pose, reference)
    assert abs(math.remainder(update.pose[2] - reference[2], math.tau)) < 0.01
    assert update.matched  # SLAM's own first match agrees with the saved map


def test_resumed_daemon_run_continues_the_saved_map(live: LiveRun, tmp_path: Path) -> None:
    config = live.config.model_copy(deep=True)
    session = RunSession.from_options(config, resume=live.run_dir.name)
    saved_keyframes = len(session.resume.keyframes)
    spec = RunSpec(maze_path=MAZE, size=None, seed=2, max_sim_s=20.0)
    _, record = _run_with_session(config, session, spec)
    state = record.state
    assert state.active_fault is None
    assert state.slam.keyframes > saved_keyframes  # the saved keyframes, and new ones
    assert occupied_iou(live.state.map, state.map) > 0.8  # the same maze, in the same frame
    resumed = load_run(session.run_dir)
    assert resumed.meta["resumed_from"] == str(live.run_dir)
    assert len(resumed.keyframes) == state.slam.keyframes


def _mazebot(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "mazebot", *args], capture_output=True, text=True, timeout=120)


def test_replay_of_a_file_that_is_not_mcap_is_one_line_exit_2(tmp_path: Path) -> None:
    bad = tmp_path / "notes.mcap"
    bad.write_text("hello, not a recording\n")
    done = _mazebot("replay", str(bad))
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and "not a readable MCAP file" in done.stderr
    missing = _mazebot("replay", str(tmp_path / "nope.mcap"))
    assert missing.returncode == 2 and "not found" in missing.stderr and "Traceback" not in missing.stderr


def test_export_of_a_missing_run_is_one_line_exit_2(tmp_path: Path) -> None:
    config = tmp_path / "config.toml"
    config.write_text(f'[daemon]\nstate_dir = "{tmp_path}"\n')
    done = _mazebot("export-map", "20000101-000000", "--config", str(config))
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and "not found" in done.stderr


def test_replay_cli_writes_map_and_trajectory(live: LiveRun, tmp_path: Path) -> None:
    done = _mazebot("replay", str(live.recording), "--fast", "--out", str(tmp_path / "out"))
    assert done.returncode == 0, done.stderr
    ros = read_ros_map(tmp_path / "out" / "map.yaml")
    np.testing.assert_array_equal(ros.three_state, live.state.map.three_state())


def _flat_yaml(text: str) -> dict[str, str]:
    """The map_server YAML is flat ``key: value`` lines (no PyYAML here)."""
    pairs = (line.split(":", 1) for line in text.splitlines() if line.strip())
    return {key.strip(): value.strip() for key, value in pairs}


def test_exported_pgm_reads_back_by_map_server_rules(live: LiveRun, tmp_path: Path) -> None:
    """Not with our own reader: the YAML's keys and map_server's formula (wiki.ros.org/map_server)."""
    saved = load_run(live.run_dir)  # not "latest": the resume test above saved a newer run
    expected = live.state.map.three_state()  # row 0 south
    pgm, yaml = export_pgm(saved, tmp_path / "maze")
    meta = _flat_yaml(yaml.read_text())
    assert set(meta) >= {"image", "resolution", "origin", "negate", "occupied_thresh", "free_thresh"}
    assert meta["image"] == pgm.name and meta["negate"] == "0"
    assert float(meta["resolution"]) == pytest.approx(live.state.map.resolution_m, rel=1e-9)
    origin = [float(v) for v in meta["origin"].strip("[]").split(",")]
    assert origin == pytest.approx([*live.state.map.origin_m, 0.0], abs=1e-9)  # the bottom-left pixel's corner
    raw = pgm.read_bytes()
    header = raw[: -expected.size].splitlines()
    tokens = b" ".join(line.split(b"#")[0] for line in header).split()  # netpbm: '#' starts a comment
    assert tokens == [b"P5", str(expected.shape[1]).encode(), str(expected.shape[0]).encode(), b"255"]
    image = np.frombuffer(raw[-expected.size :], dtype=np.uint8).reshape(expected.shape)  # row 0 north
    p = (255.0 - image[::-1]) / 255.0  # negate: 0
    occupied = p > float(meta["occupied_thresh"])
    free = p < float(meta["free_thresh"])
    np.testing.assert_array_equal(occupied, expected == 100)
    np.testing.assert_array_equal(free, expected == 0)
    np.testing.assert_array_equal(~(occupied | free), expected == -1)


def test_the_record_switch_records_into_the_run_folder(tmp_path: Path) -> None:
    config = Config()
    config.daemon.state_dir = str(tmp_path)
    config.record.enabled = True
    session = RunSession.from_options(config)
    assert session.run_dir is not None and session.record_path == session.run_dir / "recording.mcap"
    config.persist.enabled = False
    with pytest.raises(UsageError, match=r"\[record\] path"):
        RunSession.from_options(config)
    config.record.path = str(tmp_path / "elsewhere.mcap")
    assert RunSession.from_options(config).record_path == tmp_path / "elsewhere.mcap"
