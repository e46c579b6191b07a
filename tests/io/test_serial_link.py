"""The serial link's arrival notes, and the lidar driver taking a batch's bytes at once with them."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import os
import pty
import time
from collections.abc import Callable

import numpy as np
import serial

from mazebot.clock import RealClock
from mazebot.io.rplidar import RPLidar
from mazebot.io.serial_link import TRANSPORT_READ_SIZE, NonBlockingSerial, SerialLink, _BufferedProtocol

from .conftest import PtyLidar


class _Now:
    def __init__(self) -> None:
        self.s = 0.0

    def __call__(self) -> float:
        return self.s


def test_the_protocol_notes_when_each_chunk_came_and_hands_them_over_with_the_bytes() -> None:
    now = _Now()
    protocol = _BufferedProtocol(now)
    now.s = 1.00
    protocol.data_received(b"a" * 100)
    now.s = 1.01
    protocol.data_received(b"b" * 50)

    async def read() -> bytes:
        return await protocol.read(120)

    assert asyncio.run(read()) == b"a" * 100 + b"b" * 20  # the old way: a read takes the oldest bytes
    now.s = 1.02
    protocol.data_received(b"c" * 20)
    data, chunks = protocol.take_arrived()
    assert data == b"b" * 30 + b"c" * 20
    assert chunks == [(30, 1.01), (20, 1.02)]  # the read's bytes took their notes with them
    assert protocol.take_arrived() == (b"", [])


def test_a_full_chunk_came_as_long_before_as_the_bytes_still_waiting_behind_it_take() -> None:
    # the transport reads at most TRANSPORT_READ_SIZE bytes a time: after a stall the backlog comes in
    # full chunks, and the last byte of one was sent before the bytes still in the kernel
    now = _Now()
    protocol = _BufferedProtocol(now)
    protocol.kernel_waiting = lambda: 500
    protocol.byte_period_s = lambda: 1e-4
    now.s = 2.0
    protocol.data_received(b"x" * TRANSPORT_READ_SIZE)
    protocol.data_received(b"y" * 10)  # a short chunk: nothing was waiting behind it
    _, chunks = protocol.take_arrived()
    assert chunks[0] == (TRANSPORT_READ_SIZE, 2.0 - 500 * 1e-4)
    assert chunks[1] == (10, 2.0)


def test_the_driver_wakes_once_a_decode_interval_not_once_a_chunk(pty_lidar: PtyLidar) -> None:
    """A pseudo-terminal lidar sending a chunk every 10 ms, on the real clock: between two decodes
    the driver reads nothing, not even a batch's first chunk; the bytes of a batch are taken at once
    when it is due, each chunk with the time it came (the revolutions' stamps run forward)."""
    clock = RealClock()
    reads, taken = [0], [0, 0]  # reads; chunks and bytes taken

    async def run() -> tuple[RPLidar, list[np.ndarray]]:
        lidar = RPLidar(lambda: SerialLink.open(pty_lidar.path), clock, spin_up_s=0.0, sample_period_s=1 / 4000)
        read, stamps = lidar._read, []

        async def counted_read(timeout_s: float) -> bytes:
            reads[0] += 1
            return await read(timeout_s)

        lidar._read = counted_read  # type: ignore[method-assign]
        async with lidar:
            link = await lidar.open()
            take = link.take_arrived  # type: ignore[attr-defined]

            def counted_take(byte_period_s: Callable[[], float]) -> tuple[bytes, list[tuple[int, float]]] | None:
                result = take(byte_period_s)
                if result is not None:
                    taken[0] += len(result[1])
                    taken[1] += len(result[0])
                return result

            link.take_arrived = counted_take  # type: ignore[attr-defined]
            scans = lidar.scans()
            async with contextlib.aclosing(scans):  # type: ignore[type-var]
                async for scan in scans:
                    stamps.append(scan.time_s)
                    if len(stamps) == 8:
                        break
        return lidar, stamps

    lidar, stamps = asyncio.run(asyncio.wait_for(run(), 30.0))
    decodes = lidar.decode_meter.calls
    assert taken[1] > 0 and taken[0] > 0
    # no read starts a batch either: only the scan's start-up requests' answers are read
    assert decodes >= 8 and reads[0] <= 3, (reads[0], decodes, taken)
    for s in stamps:
        assert np.all(np.diff(s) > 0)
    assert all(b[0] > a[-1] for a, b in itertools.pairwise(stamps))


def _pty_port(cls: type) -> tuple[int, serial.SerialBase]:
    """A pseudo-terminal's master fd and its slave opened as ``cls`` the way :class:`SerialLink` opens a port."""
    master, slave = pty.openpty()
    path = os.ttyname(slave)
    port = cls(None, baudrate=115200, timeout=0)
    port.port = path
    port.open()
    os.close(slave)
    return master, port


def _reads(cls: type) -> list[object]:
    """What ``read`` gives on each step: nothing sent, bytes sent, more than asked, the other end gone."""
    master, port = _pty_port(cls)
    out: list[object] = []
    try:
        out.append(port.read(1024))
        os.write(master, bytes(range(200)))
        time.sleep(0.05)
        out.append(port.read(1024))
        os.write(master, b"\xa5" * 300)
        time.sleep(0.05)
        out.append(port.read(100))  # a transport's read is capped: the rest stays for the next one
        out.append(port.read(1024))
        os.close(master)
        master = -1
        try:
            out.append(port.read(1024))
        except serial.SerialException as exc:
            out.append(type(exc))
    finally:
        port.close()
        if master >= 0:
            os.close(master)
    return out


def test_the_non_blocking_port_reads_what_pyserial_reads_with_one_system_call() -> None:
    expected = _reads(serial.Serial)
    assert expected[0] == b"" and expected[1] == bytes(range(200)) and expected[-1] is serial.SerialException
    assert _reads(NonBlockingSerial) == expected
