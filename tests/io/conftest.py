"""A scripted RPLidar A1M8 for driver and CLI tests, built on the protocol's own encoders.

``FakeLidar`` serves one link (the device side of ``memory_link_pair``): it answers
STOP, RESET, GET_INFO, GET_HEALTH, GET_SAMPLERATE, SCAN and EXPRESS_SCAN with valid
bytes, logs every request, and has controls to misbehave (report a health error, stall
mid-scan, close the link). ``FakeLidarLine`` is the link factory handed to the driver:
every call plugs in a fresh ``FakeLidar`` (as when a USB adapter is replugged).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import pty
import select
import threading
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass, field

import numpy as np
import pytest

from mazebot.errors import HardwareUnavailable
from mazebot.io import rplidar_protocol as proto
from mazebot.io.serial_link import ByteLink, memory_link_pair

INFO = proto.DeviceInfo(proto.MODEL_A1M8, 29, 1, 7, bytes(range(16)))
SAMPLES_PER_REV = 360


def revolution(rev: int, samples_per_rev: int = SAMPLES_PER_REV) -> tuple[np.ndarray, ...]:
    """Device samples of one revolution: angles, distances (mm), qualities, start flags.

    Distances follow the angle (so tests can check them); a few samples are invalid on
    purpose: distance 0, quality 0, and one closer than the A1's 0.15 m minimum.
    """
    angle = np.arange(samples_per_rev) * (360.0 / samples_per_rev)
    dist = 1000.0 + 10.0 * angle + rev
    quality = np.full(samples_per_rev, 47)
    dist[10] = 0.0
    quality[20] = 0
    dist[30] = 100.0
    start = np.zeros(samples_per_rev, dtype=bool)
    start[0] = True
    return angle, dist, quality, start



def take_requests(buf: bytearray) -> list[tuple[int, bytes]]:
    """The whole requests at the front of ``buf`` (command, payload), removed from it; bytes before
    a sync byte are dropped, a partial request stays for the next read."""
    requests = []
    while buf:
        if buf[0] != proto.SYNC_BYTE:
            del buf[0]
            continue
        parsed = proto.parse_request(bytes(buf))
        if parsed is None:
            break
        cmd, payload, used = parsed
        del buf[:used]
        requests.append((cmd, payload))
    return requests

@dataclass
class FakeLidar:
    """The device end of one link: answers requests, streams scans, misbehaves on demand."""

    reader: asyncio.StreamReader
    writer: asyncio.StreamWriter
    health_status: int = proto.HEALTH_GOOD  # status reported by GET_HEALTH
    reset_heals: bool = True  # RESET clears a health error
    stall_after_revs: int | None = None  # stop streaming (link stays up) after this many
    close_after_revs: int | None = None  # close the link after this many revolutions
    answer_info: bool = True  # False: never answer GET_INFO
    info_descriptor: proto.Descriptor = proto.INFO_DESCRIPTOR
    junk_before_answers: bytes = b""  # bytes sent before every response descriptor
    chunk_samples: int = 40  # samples per write while scanning
    chunk_period_s: float = 0.002  # pause between writes while scanning
    requests: list[int] = field(default_factory=list)
    revs_sent: int = 0
    _streamer: asyncio.Task[None] | None = None

    async def serve(self) -> None:
        buf = bytearray()
        try:
            while True:
                data = await self.reader.read(4096)
                if not data:
                    return
                buf += data
                for cmd, payload in take_requests(buf):
                    await self._answer(cmd, payload)
        except ConnectionError:
            return  # the driver closed the link
        finally:
            await self._stop_streaming()

    async def _answer(self, cmd: int, payload: bytes) -> None:
        self.requests.append(cmd)
        if cmd in (proto.CMD_STOP, proto.CMD_RESET):
            await self._stop_streaming()
            if cmd == proto.CMD_RESET and self.reset_heals:
                self.health_status = proto.HEALTH_GOOD
            if cmd == proto.CMD_RESET:
                self._write(b"RP LIDAR System.\r\nFirmware Ver 1.29 - rc9, HW Ver 7\r\nModel: 18\r\n")
        elif cmd == proto.CMD_GET_INFO:
            if self.answer_info:
                self._write(self.junk_before_answers + self.info_descriptor.encode() + proto.encode_info(INFO))
        elif cmd == proto.CMD_GET_HEALTH:
            health = proto.DeviceHealth(self.health_status, 0x8001 if self.health_status else 0)
            self._write(self.junk_before_answers + proto.HEALTH_DESCRIPTOR.encode() + proto.encode_health(health))
        elif cmd == proto.CMD_GET_SAMPLERATE:
            self._write(proto.SAMPLERATE_DESCRIPTOR.encode() + proto.encode_samplerate(proto.SampleRate(508, 254)))
        elif cmd in (proto.CMD_SCAN, proto.CMD_EXPRESS_SCAN):
            await self._stop_streaming()
            express = cmd == proto.CMD_EXPRESS_SCAN
            assert not express or payload == proto.EXPRESS_SCAN_PAYLOAD
            desc = proto.EXPRESS_DESCRIPTOR if express else proto.SCAN_DESCRIPTOR
            self._write(desc.encode())
            self._streamer = asyncio.create_task(self._stream(express))
        await self.writer.drain()

    def _write(self, data: bytes) -> None:
        if not self.writer.is_closing():
            self.writer.write(data)

    async def _stop_streaming(self) -> None:
        task, self._streamer = self._streamer, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    async def _stream(self, express: bool) -> None:
        """Revolutions of standard samples, or express capsules (0.5° apart)."""
        with contextlib.suppress(ConnectionError):  # the driver closed the link
            await self._stream_until_stopped(express)

    async def _stream_until_stopped(self, express: bool) -> None:
        first_capsule = True
        capsule_step_deg = 32 * 360.0 / (2 * SAMPLES_PER_REV)
        capsule_index = 0
        while True:
            if self.close_after_revs is not None and self.revs_sent >= self.close_after_revs:
                self.writer.close()
                return
            if self.stall_after_revs is not None and self.revs_sent >= self.stall_after_revs:
                self.stall_after_revs = None  # stall once: the next SCAN streams again
                await asyncio.Event().wait()
            if express:
                # 720 samples a turn = 22.5 capsules; angles continue across turns
                data = b""
                for _ in range(SAMPLES_PER_REV // 32 + 1):
                    start_deg = (capsule_index * capsule_step_deg) % 360.0
                    dist = np.full(32, 2000.0)
                    data += proto.encode_express_capsule(start_deg, dist, start=first_capsule)
                    first_capsule = False
                    capsule_index += 1
                chunks = [data[i : i + 84 * 2] for i in range(0, len(data), 84 * 2)]
            else:
                data = proto.encode_standard_samples(*revolution(self.revs_sent))
                step = 5 * self.chunk_samples
                chunks = [data[i : i + step] for i in range(0, len(data), step)]
            for chunk in chunks:
                self._write(chunk)
                await self.writer.drain()
                await asyncio.sleep(self.chunk_period_s)
            self.revs_sent += 1


class FakeLidarLine:
    """A link factory: each call connects a fresh FakeLidar configured by ``configure``.

    ``fail_first`` makes the first calls raise HardwareUnavailable, like a port that
    is not there yet. ``first_device_options`` apply to the first device only (a cable
    pulled once). ``devices`` holds every device plugged in so far.
    """

    def __init__(self, **device_options: object) -> None:
        self.device_options = device_options
        self.first_device_options: dict[str, object] = {}
        self.fail_first = 0
        self.calls = 0
        self.devices: list[FakeLidar] = []
        self.motor: list[bool] = []
        self._tasks: list[asyncio.Task[None]] = []

    async def __call__(self) -> ByteLink:
        self.calls += 1
        if self.calls <= self.fail_first:
            raise HardwareUnavailable("lidar serial port /dev/fake cannot be opened (No such file)")
        link, (reader, writer) = memory_link_pair(on_motor=self.motor.append)
        options = {**self.device_options, **(self.first_device_options if not self.devices else {})}
        device = FakeLidar(reader, writer, **options)  # type: ignore[arg-type]
        self.devices.append(device)
        self._tasks.append(asyncio.create_task(device.serve()))
        return link

    samples_per_rev = SAMPLES_PER_REV
    revolution = staticmethod(revolution)

    @property
    def device(self) -> FakeLidar:
        return self.devices[-1]

    async def aclose(self) -> None:
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        for device in self.devices:
            device.writer.close()


@pytest.fixture
async def lidar_line() -> AsyncIterator[FakeLidarLine]:
    fake = FakeLidarLine()
    try:
        yield fake
    finally:
        await fake.aclose()


class PtyLidar:
    """A small A1M8 on a pseudo-terminal, served from a thread (the CLI runs its own
    event loop): answers STOP, GET_INFO, GET_HEALTH and SCAN (40 samples every 10 ms)."""

    def __init__(self) -> None:
        self._master, self._slave = pty.openpty()
        self.path = os.ttyname(self._slave)
        self.requests: list[int] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._scanning = False
        self._sent = 0

    def __enter__(self) -> PtyLidar:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        os.close(self._master)
        os.close(self._slave)

    def _serve(self) -> None:
        buf = bytearray()
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], 0.01)
            if self._scanning:
                self._send_samples(40)
            if not ready:
                continue
            try:
                buf += os.read(self._master, 4096)
            except OSError:
                return
            for cmd, _ in take_requests(buf):
                self._answer(cmd)

    def _answer(self, cmd: int) -> None:
        self.requests.append(cmd)
        if cmd == proto.CMD_STOP:
            self._scanning = False
        elif cmd == proto.CMD_GET_INFO:
            os.write(self._master, proto.INFO_DESCRIPTOR.encode() + proto.encode_info(INFO))
        elif cmd == proto.CMD_GET_HEALTH:
            health = proto.DeviceHealth(proto.HEALTH_WARNING, 0x0102)
            os.write(self._master, proto.HEALTH_DESCRIPTOR.encode() + proto.encode_health(health))
        elif cmd == proto.CMD_SCAN:
            os.write(self._master, proto.SCAN_DESCRIPTOR.encode())
            self._scanning = True

    def _send_samples(self, count: int) -> None:
        i = self._sent + np.arange(count)
        angle, dist, quality, start = revolution(0)
        k = i % SAMPLES_PER_REV
        os.write(self._master, proto.encode_standard_samples(angle[k], dist[k], quality[k], start[k]))
        self._sent += count


@pytest.fixture
def pty_lidar() -> Iterator[PtyLidar]:
    with PtyLidar() as device:
        yield device
