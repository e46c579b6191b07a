"""The emulated lidar on a pseudo-terminal, so any RPLidar client can open it like a port.

A pseudo-terminal has no modem lines, so the host cannot clear DTR to start the motor:
on a pty the emulated motor simply spins from the start. (Clients that set DTR, like
the ``rplidar`` package's ``start_motor``, get "Inappropriate ioctl for device" from the
kernel on a pty; they must skip that call.)
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import tty
from collections.abc import AsyncIterator

from mazebot.sim.lidar_emulator import RPLidarEmulator


@contextlib.asynccontextmanager
async def pty_device(emulator: RPLidarEmulator) -> AsyncIterator[str]:
    """Serve ``emulator`` on a new pty; yields the device path (e.g. ``/dev/pts/3``)."""
    master_fd, slave_fd = os.openpty()
    # Raw mode: no echo, no CR/LF translation, bytes pass unchanged both ways.
    tty.setraw(slave_fd)
    path = os.ttyname(slave_fd)
    loop = asyncio.get_running_loop()
    reader = asyncio.StreamReader()
    read_transport, _ = await loop.connect_read_pipe(
        lambda: asyncio.StreamReaderProtocol(reader), os.fdopen(master_fd, "rb", buffering=0)
    )
    write_transport, write_protocol = await loop.connect_write_pipe(
        asyncio.streams.FlowControlMixin, os.fdopen(os.dup(master_fd), "wb", buffering=0)
    )
    writer = asyncio.StreamWriter(write_transport, write_protocol, reader, loop)
    emulator.set_dtr(False)  # no modem lines on a pty: the motor spins from the start
    server = asyncio.create_task(emulator.serve(reader, writer), name="pty-lidar")
    try:
        yield path
    finally:
        server.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await server
        write_transport.close()
        read_transport.close()
        # Our own slave fd kept the master readable while clients came and went.
        os.close(slave_fd)
