"""The asyncio RPLidar driver against a scripted fake device on an in-memory link."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import math
from collections.abc import AsyncIterator
from typing import TYPE_CHECKING

import numpy as np
import pytest

from mazebot.clock import RealClock
from mazebot.config import LidarConfig
from mazebot.errors import HardwareUnavailable, ProtocolError
from mazebot.io import rplidar_protocol as proto
from mazebot.io.rplidar import RPLidar
from mazebot.io.scan import Scan
from mazebot.io.serial_link import memory_link_pair

if TYPE_CHECKING:
    from conftest import FakeLidarLine

SAMPLES_PER_REV = 360  # what the fake device sends (tests/io/conftest.py)

FAST = {
    "spin_up_s": 0.01,
    "no_data_timeout_s": 0.15,
    "backoff_min_s": 0.01,
    "backoff_max_s": 0.04,
    "response_timeout_s": 0.2,
    "reset_settle_s": 0.01,
}


def make_lidar(lidar_line: FakeLidarLine, **options: object) -> RPLidar:
    return RPLidar(lidar_line, RealClock(), **{**FAST, **options})  # type: ignore[arg-type]


async def take(scans: AsyncIterator[Scan], count: int, timeout_s: float = 5.0) -> list[Scan]:
    async def collect() -> list[Scan]:
        out = []
        async with contextlib.aclosing(scans):  # type: ignore[type-var]
            async for scan in scans:
                out.append(scan)
                if len(out) == count:
                    break
        return out

    return await asyncio.wait_for(collect(), timeout_s)


async def test_constructor_opens_nothing(lidar_line: FakeLidarLine) -> None:
    lidar = make_lidar(lidar_line)
    await asyncio.sleep(0)
    assert lidar_line.calls == 0
    assert not lidar.stats.connected
    await lidar.close()
    assert lidar_line.calls == 0


async def test_requests_parse_the_device_answers(lidar_line: FakeLidarLine) -> None:
    async with make_lidar(lidar_line) as lidar:
        info = await lidar.get_info()
        assert (info.model_name, info.firmware_version, info.hardware) == ("A1M8", "1.29", 7)
        assert info.serial_number == bytes(range(16))
        health = await lidar.get_health()
        assert (health.status_name, health.error_code) == ("good", 0)
        rate = await lidar.get_samplerate()
        assert (rate.standard_us, rate.express_us) == (508, 254)
        assert lidar.stats.connected
    await asyncio.sleep(0.01)  # let the device read the last request
    assert lidar_line.device.requests == [
        proto.CMD_GET_INFO,
        proto.CMD_GET_HEALTH,
        proto.CMD_GET_SAMPLERATE,
        proto.CMD_STOP,
    ]
    assert not lidar.stats.connected


async def test_stray_bytes_before_an_answer_are_skipped(lidar_line: FakeLidarLine) -> None:
    # a boot message, a lone sync byte, and a5 5a followed by no known descriptor
    lidar_line.device_options["junk_before_answers"] = b"RP LIDAR System.\r\n\xa5\xa5\x5a\x01\x02\x03\x04\x05"
    async with make_lidar(lidar_line) as lidar:
        assert (await lidar.get_info()).model == proto.MODEL_A1M8
        assert (await lidar.get_health()).status == proto.HEALTH_GOOD


async def test_wrong_descriptor_is_a_protocol_error(lidar_line: FakeLidarLine) -> None:
    lidar_line.device_options["info_descriptor"] = proto.HEALTH_DESCRIPTOR
    async with make_lidar(lidar_line) as lidar:
        with pytest.raises(ProtocolError) as err:
            await lidar.get_info()
    assert "answer to GET_INFO" in str(err.value)
    assert "expected descriptor (length 20, single, type 0x04)" in str(err.value)
    assert "found (length 3, single, type 0x06)" in str(err.value)


async def test_silent_device_times_out_as_unavailable(lidar_line: FakeLidarLine) -> None:
    lidar_line.device_options["answer_info"] = False
    async with make_lidar(lidar_line) as lidar:
        with pytest.raises(HardwareUnavailable, match=r"did not answer GET_INFO within 0\.2 s"):
            await lidar.get_info()


async def test_scans_one_per_revolution_in_robot_convention(lidar_line: FakeLidarLine) -> None:
    async with make_lidar(lidar_line, mount_yaw_deg=90.0) as lidar:
        scans = await take(lidar.scans(), 3)
        # start-up: motor on, STOP, health check, the mode's sample period, spin-up, SCAN
        assert lidar_line.motor == [True]
        assert lidar_line.device.requests[:4] == [
            proto.CMD_STOP, proto.CMD_GET_HEALTH, proto.CMD_GET_SAMPLERATE, proto.CMD_SCAN
        ]
        assert lidar.stats.connected
    await asyncio.sleep(0.01)  # let the device read the last request
    assert lidar_line.device.requests[-1] == proto.CMD_STOP  # close() stops the scan
    assert lidar_line.motor == [True, False]  # ... and the motor
    angle, dist, quality, _ = lidar_line.revolution(0)
    for scan in scans:
        assert len(scan) == SAMPLES_PER_REV
        # device: clockwise from the front mark; robot: counter-clockwise from ahead,
        # here with the lidar's 0° mark turned 90° to the left
        expected = (np.deg2rad(90.0 - angle) + math.pi) % math.tau - math.pi
        np.testing.assert_allclose(scan.angle_rad, expected, atol=1e-12)
        assert np.all((scan.angle_rad >= -math.pi) & (scan.angle_rad < math.pi))
        np.testing.assert_array_equal(scan.quality, quality)
        # distance 0, quality 0 and closer than 0.15 m are invalid, but kept
        assert np.flatnonzero(~scan.valid).tolist() == [10, 20, 30]
        # the fake's distances: 1000 mm + 10 mm per degree + the revolution number
        offset_mm = scan.range_m[scan.valid] * 1000 - dist[scan.valid]
        np.testing.assert_allclose(offset_mm, round(offset_mm[0]), atol=1e-6)
    # the first, partial revolution is dropped; revolutions count on from there
    assert [s.revolution for s in scans] == [0, 1, 2]
    assert lidar.stats.revolutions == 3
    assert lidar.stats.bytes_dropped == 0


async def test_sample_times_are_increasing_and_plausible(lidar_line: FakeLidarLine) -> None:
    clock = RealClock()
    async with make_lidar(lidar_line) as lidar:
        t0 = clock.now_s()
        scans = await take(lidar.scans(), 4)
        t1 = clock.now_s()
    times = np.concatenate([s.time_s for s in scans])
    assert np.all(np.diff(times) > 0)
    assert t0 < times[0] and times[-1] <= t1
    for scan in scans:
        # the fake sends a revolution in ~20 ms; stamps spread at ~0.5 ms per sample
        # never make a revolution longer than it took to arrive, nor overlap the next
        assert scan.end_time_s - scan.start_time_s < 0.5
    assert all(a.end_time_s < b.start_time_s for a, b in itertools.pairwise(scans))


async def test_health_error_is_reset_then_scanning_works(lidar_line: FakeLidarLine) -> None:
    lidar_line.device_options["health_status"] = proto.HEALTH_ERROR
    async with make_lidar(lidar_line) as lidar:
        scans = await take(lidar.scans(), 2)
        assert lidar.stats.health_errors == 1
        assert lidar.stats.reconnects == 0
    assert lidar_line.device.requests[:6] == [
        proto.CMD_STOP,
        proto.CMD_GET_HEALTH,
        proto.CMD_RESET,
        proto.CMD_GET_HEALTH,
        proto.CMD_GET_SAMPLERATE,
        proto.CMD_SCAN,
    ]
    assert len(scans[0]) == SAMPLES_PER_REV


async def test_persistent_health_error_is_reported_and_retried(lidar_line: FakeLidarLine) -> None:
    lidar_line.device_options["health_status"] = proto.HEALTH_ERROR
    lidar_line.device_options["reset_heals"] = False
    async with make_lidar(lidar_line) as lidar:
        with pytest.raises(TimeoutError):
            await take(lidar.scans(), 1, timeout_s=0.5)
        assert lidar.stats.health_errors >= 4  # two per attempt, several attempts
        assert lidar_line.calls >= 2  # each attempt reopens the port, after a backoff
        assert "hardware error (code 0x8001) even after a reset" in lidar.stats.last_error
        assert lidar.stats.reconnects == 0  # never got back to scanning


async def test_stalled_scan_is_restarted(lidar_line: FakeLidarLine) -> None:
    lidar_line.device_options["stall_after_revs"] = 2
    async with make_lidar(lidar_line) as lidar:
        scans = await take(lidar.scans(), 4)
        assert lidar.stats.scan_restarts == 1
        assert lidar.stats.reconnects == 0
    assert lidar_line.calls == 1
    assert lidar_line.device.requests.count(proto.CMD_SCAN) == 2
    assert all(len(s) == SAMPLES_PER_REV for s in scans)


async def test_vanished_port_is_reopened_with_backoff(lidar_line: FakeLidarLine) -> None:
    # the link closes once, after three revolutions (closing every link after two was a race:
    # whether a link gave the driver a whole revolution before closing depended on timing)
    lidar_line.first_device_options["close_after_revs"] = 3
    async with make_lidar(lidar_line) as lidar:
        scans = await take(lidar.scans(), 4)
        assert lidar.stats.reconnects >= 1
        assert "end of file" in lidar.stats.last_error
        assert lidar.stats.connected
    assert lidar_line.calls >= 2
    assert all(len(s) == SAMPLES_PER_REV for s in scans)


async def test_missing_port_is_retried_until_it_appears(lidar_line: FakeLidarLine) -> None:
    lidar_line.fail_first = 2
    async with make_lidar(lidar_line) as lidar:
        scans = await take(lidar.scans(), 1)
        assert lidar.stats.reconnects == 1
        assert "/dev/fake cannot be opened" in lidar.stats.last_error
    assert lidar_line.calls == 3
    assert len(scans) == 1


async def test_scans_end_only_by_cancellation(lidar_line: FakeLidarLine) -> None:
    lidar_line.fail_first = 10**6  # the port never appears
    lidar = make_lidar(lidar_line)
    task = asyncio.create_task(take(lidar.scans(), 1, timeout_s=60))
    await asyncio.sleep(0.2)
    assert not task.done()
    assert lidar_line.calls > 3
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    await lidar.close()


async def test_express_mode_scans(lidar_line: FakeLidarLine) -> None:
    async with make_lidar(lidar_line, scan_mode="express") as lidar:
        scans = await take(lidar.scans(), 3)
    assert proto.CMD_EXPRESS_SCAN in lidar_line.device.requests
    for scan in scans:
        # 720 samples a turn (0.5° apart). As in Slamtec's SDK, a capsule revolution
        # starts with the last sample before the sweep passes 0° (here 359.5°).
        assert len(scan) == 2 * SAMPLES_PER_REV
        device_deg = np.rad2deg(-scan.angle_rad) % 360
        assert device_deg[0] == pytest.approx(359.5, abs=1 / 64)
        np.testing.assert_allclose((np.diff(device_deg) + 180) % 360 - 180, 0.5, atol=1 / 64)
        assert np.all(scan.valid)
        np.testing.assert_array_equal(scan.range_m, 2.0)


async def test_close_is_idempotent_and_final(lidar_line: FakeLidarLine) -> None:
    lidar = make_lidar(lidar_line)
    await lidar.get_health()
    await lidar.close()
    await lidar.close()
    with pytest.raises(RuntimeError, match="closed"):
        await lidar.get_health()


async def test_from_config_takes_the_plain_values() -> None:
    cfg = LidarConfig(scan_mode="express", mount_yaw_deg=-30.0, no_data_timeout_s=2.5)
    lidar = RPLidar.from_config(cfg, RealClock())
    assert lidar.scan_mode == "express"
    assert lidar.name == "lidar on /dev/ttyUSB0"
    await lidar.close()


async def test_from_config_missing_port_is_hardware_unavailable() -> None:
    lidar = RPLidar.from_config(LidarConfig(port="/dev/ttyNOPE_mazebot"), RealClock())
    with pytest.raises(HardwareUnavailable) as err:
        await lidar.get_info()
    assert err.value.exit_code == 69
    assert "/dev/ttyNOPE_mazebot" in str(err.value)
    await lidar.close()


async def test_memory_link_eof_and_motor_callback() -> None:
    switches: list[bool] = []
    link, (reader, writer) = memory_link_pair(on_motor=switches.append)
    link.set_motor(True)
    link.set_motor(False)
    assert switches == [True, False]
    await link.write(b"\xa5\x25")
    assert await reader.readexactly(2) == b"\xa5\x25"
    writer.write(b"abc")
    await writer.drain()
    assert await link.read() == b"abc"
    writer.write(b"stale")
    await asyncio.sleep(0)
    link.reset_input_buffer()
    writer.close()
    assert await link.read() == b""  # the device went away: end of file
    await link.close()
    await link.close()


async def test_bytes_waiting_in_the_link_are_no_silence() -> None:
    # the no-data time-out judged after a blocked loop: bytes that arrived meanwhile and wait
    # unread (in the link's buffers) mean the device talks; only an empty link is silent
    class Link:
        waiting = 0

        def pending_bytes(self) -> int:
            return self.waiting

    lidar = RPLidar(lambda: None, RealClock())  # type: ignore[arg-type, return-value]
    link = Link()
    lidar._link = link  # type: ignore[assignment]
    assert lidar.bytes_waiting() == 0 and not await lidar._heard_after_all()
    link.waiting = 1200
    assert lidar.bytes_waiting() == 1200 and await lidar._heard_after_all()


async def test_a_lost_link_leaves_no_bytes_waiting(lidar_line: FakeLidarLine) -> None:
    async with make_lidar(lidar_line) as lidar:
        await take(lidar.scans(), 1)
        lidar._undecoded = 100  # a batch in hand when the link went away
        await lidar._drop_link(stop=False)
        assert lidar.bytes_waiting() == 0
