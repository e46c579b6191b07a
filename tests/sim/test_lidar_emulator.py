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


#: how far a decoded bearing may lie from the one the emulated A1 cast its ray along: the
#: angle field's 1/64° and the 0.024–0.031° the triangulation offsets leave between the
#: decoded bearing and the lit spot (``test_the_decoded_bearing_is_the_spots_at_every_range``)
BEARING_SLACK_DEG = 0.05


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
    # noise is off: only the protocol's quantisation (1/4 mm standard, 1 mm express) remains,
    # and the decoded bearing's own: 1/64° of the angle field, and up to 0.031° between the
    # decoded bearing and the spot the A1's laser lit (measured below). On a wall seen at a
    # steep angle that bearing moves the range by more than a millimetre, and how many such
    # samples the collection holds depends on how long the loop let it run, so the truth is
    # the range anywhere within that bearing's slack.
    quantum_mm = 0.25 if mode == "standard" else 1.0
    bracket = np.stack([_true_ranges_mm(load_maze(MAZE).start_pose, samples.angle_deg + d)
                        for d in (-BEARING_SLACK_DEG, 0.0, BEARING_SLACK_DEG)])
    dist = samples.dist_mm[in_range]
    assert np.all(dist >= bracket.min(axis=0)[in_range] - quantum_mm - 0.3)
    assert np.all(dist <= bracket.max(axis=0)[in_range] + quantum_mm + 0.3)
    np.testing.assert_allclose(np.median(np.abs(dist - truth[in_range])), 0.0, atol=quantum_mm)


def test_lidar_params_follow_the_config() -> None:
    config = Config()
    config.lidar.scan_mode = "express"
    config.lidar.mount_yaw_deg = 90.0
    params = lidar_params(config)
    # the A1's standard mode (508 us a sample) at 5.5 rev/s; a scan mode sets its own
    assert params.samples_per_rev == 358 and params.rev_per_s == 5.5
    assert params.mount_yaw_rad == pytest.approx(np.pi / 2)
    assert Path(MAZE).is_file()


def _decoded_against_the_laser_spot(range_m: float, mode: str) -> tuple[np.ndarray, np.ndarray]:
    """A flat wall ``range_m`` ahead of the emulated A1 (noise off), through the bytes and the decoder:
    per sample within 40° of the wall's normal, the decoded bearing minus the bearing of the spot the
    laser line lit (degrees), and the decoded point's distance from the wall's face (metres)."""
    from mazebot.clock import RealClock
    from mazebot.io.rplidar_models import MODELS
    from mazebot.sim.lidar_emulator import legacy_offset_deg, standard_offset_deg
    from mazebot.sim.lidar_samples import BEAM_AHEAD_RAD, BEAM_SIDE_M
    from mazebot.sim.raycast import RayCaster
    from mazebot.sim.world import World, rectangles_outline

    wall = rectangles_outline(np.array([[range_m, -4.0, range_m + 0.02, 4.0]]))
    world = World("wall", wall, np.zeros((0, 3)), (0.0, 0.0, 0.0), (-1.0, -5.0, range_m + 1.0, 5.0))
    poses = PoseHistory()
    poses.append(0.0, 0.0, 0.0, 0.0)
    poses.append(10.0, 0.0, 0.0, 0.0)
    model = MODELS["a1"]
    head = SpinningLidar(world, LidarParams(rev_jitter=0.0, range_noise=0.0, dropout=0.0), np.random.default_rng(1))
    emulator = RPLidarEmulator(head, poses, RealClock(), model=model)
    answer = proto.TYPE_SCAN if mode == "standard" else proto.TYPE_EXPRESS
    emulator.mode = next(m for m in model.modes if m.answer_type == answer)
    head.angle_offset = standard_offset_deg if mode == "standard" else legacy_offset_deg
    head.set_samples_per_rev(round(emulator.mode.samples_per_s / model.rev_per_s))
    head.restart(0.0)
    sent = head.advance(0.4, poses)
    decoder = proto.scan_decoder(answer)
    out = proto.DecodedSamples.concat([decoder.feed(emulator.encode(sent)), decoder.flush()])
    n = len(out)  # in order; the capsules' last ones wait for a successor
    assert n > 0.9 * len(sent)
    np.testing.assert_allclose(out.dist_mm, np.rint(sent.dist_mm[:n]) if mode != "standard" else sent.dist_mm[:n])
    # the spot: the laser line (BEAM_SIDE_M right of the centre, BEAM_AHEAD_RAD ahead of the raw angle) meets the wall
    beam = -np.deg2rad(sent.angle_deg[:n]) + BEAM_AHEAD_RAD
    ox, oy = BEAM_SIDE_M * np.sin(beam), -BEAM_SIDE_M * np.cos(beam)
    along = RayCaster.for_world(world).cast_xy(ox, oy, beam, 12.0)
    spot = np.arctan2(oy + along * np.sin(beam), ox + along * np.cos(beam))
    bearing = -np.deg2rad(out.angle_deg)
    err_deg = np.degrees((bearing - spot + np.pi) % (2 * np.pi) - np.pi)
    face_m = out.dist_mm / 1000.0 * np.cos(bearing) - range_m
    near_normal = (np.abs(spot) < np.radians(40)) & (out.dist_mm > 0)
    return err_deg[near_normal], face_m[near_normal]


@pytest.mark.parametrize("mode", ["standard", "express"])
@pytest.mark.parametrize("range_m", [0.2, 0.35, 0.6, 1.0, 2.0])
def test_the_decoded_bearing_is_the_spots_at_every_range(range_m: float, mode: str) -> None:
    # Emulator -> bytes -> decoder against the geometry: what the A1's angle offsets put
    # between a sample's raw angle and its direction (0-8° by range) must come back out of
    # the decoder as the bearing of the spot the laser lit, on average and sample by sample,
    # to what the formats carry: the SDK's offset (integer k = 98361 / dist_q2, one step
    # 64 / 65536 rad = 0.056°, truncated: +0.026-0.031° on average against the exact
    # geometry in standard mode), the angles' 1/64° (standard), and in express the offset's
    # 1/8° (one rounding for a whole wall at one range: up to 1/16° more on average) and the
    # SDK's floor. Every decoded point lies on the wall's face.
    err_deg, face_m = _decoded_against_the_laser_spot(range_m, mode)
    assert err_deg.size > 20
    k_step_deg = np.degrees(64 / 65536)
    assert abs(float(np.mean(err_deg))) < k_step_deg + (0.0 if mode == "standard" else 1 / 16)
    assert float(np.std(err_deg)) < (0.03 if mode == "standard" else 0.06)
    assert float(np.max(np.abs(err_deg))) < (0.1 if mode == "standard" else 0.2)
    assert float(np.max(np.abs(face_m))) < (0.0003 if mode == "standard" else 0.001) * max(1.0, range_m)
