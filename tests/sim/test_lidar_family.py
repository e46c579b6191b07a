"""Every RPLidar model the emulator plays, read by the daemon's own driver: the scan
modes GET_LIDAR_CONF reports, each capsule kind at its mode's sample rate, ranges that
agree with the world at the angles decoded (so decoder and emulator agree on each
kind's angle arithmetic), and the one-line answer to a wrong serial speed."""

from __future__ import annotations

import contextlib

import numpy as np
import pytest

from mazebot.clock import RealClock
from mazebot.errors import ConfigError, HardwareUnavailable
from mazebot.io import rplidar_protocol as proto
from mazebot.io.rplidar import RPLidar
from mazebot.io.rplidar_models import MODELS
from mazebot.sim.backend import SimLidarLine
from mazebot.sim.lidar_emulator import RPLidarEmulator
from mazebot.sim.lidar_samples import LidarParams, PoseHistory, SpinningLidar
from mazebot.sim.maze_file import load_maze, packaged_maze_path
from mazebot.sim.raycast import cast_rays
from mazebot.sim.virtual_time import run_virtual

MAZE = packaged_maze_path("default_6x6.txt")


def _line(key: str) -> tuple[SimLidarLine, RealClock]:
    world = load_maze(MAZE)
    clock = RealClock()
    poses = PoseHistory()
    poses.append(0.0, *world.start_pose)
    model = MODELS[key]
    params = LidarParams(rev_per_s=model.rev_per_s, rev_jitter=0.0, range_noise=0.0, dropout=0.0,
                         max_range_m=model.modes[0].max_distance_m)
    head = SpinningLidar(world, params, np.random.default_rng(1))
    return SimLidarLine(RPLidarEmulator(head, poses, clock, model=model)), clock


async def _scans(key: str, scan_mode: str, count: int) -> tuple[list, RPLidar, SimLidarLine]:
    line, clock = _line(key)
    lidar = RPLidar(lambda: line.connect_at(MODELS[key].baudrate), clock, scan_mode=scan_mode,  # type: ignore[arg-type]
                    spin_up_s=0.05, max_range_m=MODELS[key].modes[0].max_distance_m)
    scans = []
    try:
        async with contextlib.aclosing(lidar.scans()) as it:  # type: ignore[type-var]
            async for scan in it:
                scans.append(scan)
                if len(scans) == count:
                    break
    finally:
        await lidar.close()
        await line.close()
    return scans, lidar, line


@pytest.mark.parametrize("key", sorted(MODELS))
def test_the_driver_reads_the_scan_modes_of_each_model(key: str) -> None:
    async def run() -> tuple[list[proto.ScanModeInfo], int]:
        line, clock = _line(key)
        try:
            async with RPLidar(lambda: line.connect_at(MODELS[key].baudrate), clock) as lidar:
                return await lidar.get_scan_modes()
        finally:
            await line.close()

    modes, typical = run_virtual(run())
    model = MODELS[key]
    assert typical == model.typical_mode
    assert [(m.id, m.name, m.answer_type, m.max_distance_m) for m in modes] == [
        (m.id, m.name, m.answer_type, m.max_distance_m) for m in model.modes]
    # the SDK reads the sample period q8 and keeps its integer part
    assert [m.us_per_sample for m in modes] == [float(int(m.us_per_sample)) for m in model.modes]


@pytest.mark.parametrize(
    ("key", "scan_mode", "answer_type"),
    [("a1", "express", 0x82), ("a1", "auto", 0x84), ("a1", "boost", 0x84), ("a3", "stability", 0x84),
     ("c1", "auto", 0x85), ("s2", "denseboost", 0x85), ("c1", "standard", 0x81), ("a1", "standard", 0x81)],
)
def test_each_capsule_kind_decodes_to_the_world(key: str, scan_mode: str, answer_type: int) -> None:
    scans, lidar, _ = run_virtual(_scans(key, scan_mode, 3))
    assert lidar.active_mode.answer_type == answer_type
    model = MODELS[key]
    per_rev = lidar.active_mode.samples_per_s / model.rev_per_s
    world = load_maze(MAZE)
    x, y, theta = world.start_pose
    for scan in scans[1:]:
        assert abs(len(scan) - per_rev) <= 0.02 * per_rev + 100  # a turn (the SDK's flag may cut a capsule late)
        valid = scan.valid
        assert valid.mean() > 0.5
        truth = cast_rays(np.array([x, y]), theta + scan.angle_rad[valid], world.segments, world.circles, 30.0)
        err = np.abs(scan.range_m[valid] - truth)
        # within the format's resolution at the decoded angle (ultra: 2-4 mm units and
        # the offset the SDK derives from the quantized range; the world's corners)
        assert np.median(err) < 0.003, (key, scan_mode, np.median(err))
        assert np.mean(err < 0.02) > 0.97, (key, scan_mode, np.mean(err < 0.02))


def test_a_mode_the_unit_lacks_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match=r"offers no such mode; it has Standard, DenseBoost"):
        run_virtual(_scans("c1", "boost", 1))


@pytest.mark.parametrize(("key", "configured", "message"), [
    ("c1", 115200, "no answer at 115200 baud on /dev/ttyUSB0: a C1M1 speaks 460800, set [lidar] baudrate"),
    ("a1", 256000, "no answer at 256000 baud on /dev/ttyUSB0: an A1M8 speaks 115200, set [lidar] baudrate"),
])
def test_a_wrong_serial_speed_says_which_unit_speaks_what(key: str, configured: int, message: str) -> None:
    async def run() -> None:
        line, clock = _line(key)
        lidar = RPLidar(lambda: line.connect_at(configured), clock, baudrate=configured,
                        probe_factory=line.connect_at, response_timeout_s=0.2, name="lidar on /dev/ttyUSB0")
        try:
            await lidar.get_info()
        finally:
            await lidar.close()
            await line.close()

    with pytest.raises(HardwareUnavailable) as err:
        run_virtual(run())
    assert str(err.value) == message
