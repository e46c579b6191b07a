"""The lidar emulator is the RPLidar protocol: a third-party client reads it like a device."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mazebot.config import Config
from mazebot.io import rplidar_protocol as proto
from mazebot.sim.lidar_emulator import RPLidarEmulator
from mazebot.sim.lidar_samples import LidarParams, PoseHistory, SpinningLidar
from mazebot.sim.maze_file import load_maze, packaged_maze_path
from mazebot.sim.raycast import cast_rays
from mazebot.sim.robot import lidar_params

MAZE = packaged_maze_path("default_6x6.txt")


def _true_ranges_mm(pose: tuple[float, float, float], angles_deg: np.ndarray) -> np.ndarray:
    world = load_maze(MAZE)
    # device angles are clockwise from the lidar's front; the world is counter-clockwise
    world_rad = pose[2] - np.deg2rad(angles_deg)
    return cast_rays(np.array(pose[:2]), world_rad, world.segments, world.circles, 12.0) * 1000.0


@pytest.fixture
def sim_lidar_pty() -> tuple[str, subprocess.Popen[str]]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "mazebot", "sim", "lidar", "--maze", str(MAZE)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        path = proc.stdout.readline().strip()  # the contract: the device path comes first
        assert path.startswith("/dev/"), proc.stderr.read()
        yield path, proc
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        proc.stdout.close()
        proc.stderr.close()


@pytest.mark.slow
def test_third_party_client_reads_info_health_and_scans(sim_lidar_pty: tuple[str, subprocess.Popen[str]]) -> None:
    rplidar = pytest.importorskip("rplidar", reason="the test extra rplidar-roboticia is not installed")
    path, _proc = sim_lidar_pty
    client = rplidar.RPLidar(path, timeout=3)
    # A pty has no modem lines: the client's DTR motor control raises ENOTTY there, and
    # the emulated motor spins from the start, so that one call is skipped.
    client.start_motor = lambda: None
    try:
        info = client.get_info()
        assert info["model"] == 0x18
        assert info["firmware"] == (1, 29)
        assert client.get_health() == ("Good", 0)
        scans = []
        for scan in client.iter_scans():
            scans.append(scan)
            if len(scans) == 21:
                break
        client.stop()
    finally:
        client.disconnect()
    scans = scans[1:]  # the first may be partial
    assert len(scans) == 20
    world = load_maze(MAZE)
    for scan in scans:
        quality, angle_deg, dist_mm = (np.array(v, dtype=float) for v in zip(*scan, strict=True))
        # 360 samples a revolution; the client drops invalid ones: a few percent of
        # dropouts, and the side walls of a 1 ft cell, which at 0.146 m from its centre
        # are inside the A1's 0.15 m minimum range.
        assert len(scan) > 250
        assert np.all((angle_deg >= 0) & (angle_deg < 360))
        truth = _true_ranges_mm(world.start_pose, angle_deg)
        rel = np.abs(dist_mm - truth) / truth
        # ~1% range noise: nearly every sample within 5%, the median well under 2%
        assert np.median(rel) < 0.02
        assert np.mean(rel < 0.05) > 0.97
        assert np.all(quality == 47)


async def _collect(mode: str, seconds: float) -> tuple[bytes, RPLidarEmulator]:
    import asyncio

    from mazebot.clock import RealClock

    world = load_maze(MAZE)
    clock = RealClock()
    poses = PoseHistory()
    poses.append(clock.now_s(), *world.start_pose)
    params = LidarParams(dropout=0.0, range_noise=0.0, rev_jitter=0.0)
    emulator = RPLidarEmulator(SpinningLidar(world, params, np.random.default_rng(3)), poses, clock)
    host_to_dev = asyncio.StreamReader()
    dev_to_host = bytearray()

    class Sink:
        def write(self, data: bytes) -> None:
            dev_to_host.extend(data)

        async def drain(self) -> None:
            return None

        def is_closing(self) -> bool:
            return False

    emulator.set_dtr(False)
    server = asyncio.create_task(emulator.serve(host_to_dev, Sink()))  # type: ignore[arg-type]
    cmd = proto.CMD_SCAN if mode == "standard" else proto.CMD_EXPRESS_SCAN
    payload = b"" if mode == "standard" else proto.EXPRESS_SCAN_PAYLOAD
    host_to_dev.feed_data(proto.build_request(cmd, payload))
    await asyncio.sleep(seconds)
    host_to_dev.feed_eof()
    await server
    return bytes(dev_to_host), emulator


@pytest.mark.parametrize("mode", ["standard", "express"])
async def test_our_decoder_reads_the_emulator_byte_exactly(mode: str) -> None:
    data, emulator = await _collect(mode, 0.5)
    descriptor = proto.SCAN_DESCRIPTOR if mode == "standard" else proto.EXPRESS_DESCRIPTOR
    assert data[:7] == descriptor.encode()
    decoder = proto.StandardScanDecoder() if mode == "standard" else proto.ExpressScanDecoder()
    samples = decoder.feed(data[7:])
    assert decoder.bytes_dropped == 0
    assert len(samples) > 0.8 * emulator.stats.samples_sent - 32
    truth = _true_ranges_mm(load_maze(MAZE).start_pose, samples.angle_deg)
    # the decoded angle is the cast one to 1/64°: a wall exactly at the minimum range
    # may fall either side of it
    in_range = truth >= 150.01
    assert in_range.mean() > 0.6
    np.testing.assert_array_equal(samples.dist_mm[truth < 149.99], 0.0)  # too close: reported as no return
    if mode == "express":
        # the capsules carry the triangulation offsets of the real unit, beyond 4°
        caps = np.frombuffer(data[7 : 7 + 84 * (len(data[7:]) // 84)], np.uint8).reshape(-1, 84)
        cab = caps[:, 4:].reshape(-1, 16, 5).astype(int)
        comp = np.concatenate([(cab[:, :, 4] & 0xF) | (cab[:, :, 0] & 3) << 4,
                               (cab[:, :, 4] >> 4) | (cab[:, :, 2] & 3) << 4])
        assert comp.max() >= 45 and np.mean(comp > 31) > 0.1  # 5.6° and more: walls beyond 0.6 m
    # noise is off: only the protocol's quantisation (1/4 mm standard, 1 mm express) remains
    quantum_mm = 0.25 if mode == "standard" else 1.0
    np.testing.assert_allclose(samples.dist_mm[in_range], truth[in_range], rtol=0, atol=quantum_mm + 0.3)


def test_lidar_params_follow_the_config() -> None:
    config = Config()
    config.lidar.scan_mode = "express"
    config.lidar.mount_yaw_deg = 90.0
    params = lidar_params(config)
    # the A1's standard mode (508 us a sample) at 5.5 rev/s; a scan mode sets its own
    assert params.samples_per_rev == 358 and params.rev_per_s == 5.5
    assert params.mount_yaw_rad == pytest.approx(np.pi / 2)
    assert Path(MAZE).is_file()
