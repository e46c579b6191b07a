"""Byte links to the lidar: the real serial port, and in-memory streams for tests and the simulator.

The RPLidar driver needs very little from its transport: read what has arrived, write
a request, switch the motor, throw away stale input, close. ``ByteLink`` is exactly
that, so the same driver code runs on the USB serial adapter, on a pseudo-terminal
served by the emulator, and on an in-memory pipe in tests.

On the A1's USB adapter the motor is driven from the DTR line, inverted: the motor
spins while DTR is *cleared*. The port is therefore opened with DTR already cleared;
opening it the default way (DTR set) would stop the motor for a moment on every start.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import os
from collections import deque
from collections.abc import Callable
from typing import Any, Protocol

import serial
import serial_asyncio

from mazebot.errors import HardwareUnavailable, serial_port_hint

log = logging.getLogger(__name__)

#: Default size of one read; the serial transport itself reads at most 1024 bytes.
READ_SIZE = 4096
#: What pyserial-asyncio's transport reads at most per readable event (``_max_read_size``).
TRANSPORT_READ_SIZE = 1024
#: Input kept when the consumer falls behind; older bytes are dropped (a lidar's old
#: samples are worth less than new ones, and memory must stay bounded).
MAX_BUFFERED_BYTES = 1 << 20
#: How long ``close`` lets buffered output drain before it drops it.
CLOSE_TIMEOUT_S = 0.5


class ByteLink(Protocol):
    """What the lidar driver needs from a byte transport."""

    async def read(self, max_bytes: int = READ_SIZE) -> bytes:
        """Wait for at least one byte and return what has arrived (up to ``max_bytes``).

        Returns b"" when the link is closed or the other end went away (end of file).
        May raise OSError when the port fails (e.g. the USB adapter was unplugged).
        """
        ...

    async def write(self, data: bytes) -> None:
        """Send ``data`` (waits while the output buffer is full)."""
        ...

    def set_motor(self, on: bool) -> None:
        """Spin (True) or stop (False) the lidar's motor."""
        ...

    def reset_input_buffer(self) -> None:
        """Throw away every byte received and not yet read."""
        ...

    async def close(self) -> None:
        """Close the link; closing twice is harmless."""
        ...


class _BufferedProtocol(asyncio.Protocol):
    """An asyncio protocol that keeps received bytes until ``read`` takes them.

    It also notes when each chunk arrived (``now``: the loop's clock, read in
    ``data_received``, which the transport calls as the bytes come), so a reader that
    takes the bytes later, in one go (:meth:`take_arrived`), still knows their arrival
    times. A full chunk (the transport reads at most ``full_read`` bytes a time: a backlog
    after a stall) has more waiting behind it in the kernel (``kernel_waiting``): its last
    byte came that many bytes' time (``byte_period_s``) before it was read.
    """

    def __init__(self, now: Callable[[], float] | None = None) -> None:
        self._buffer = bytearray()
        self._waiter: asyncio.Future[None] | None = None
        self._eof = False
        self._error: BaseException | None = None
        self.bytes_overflowed = 0
        self.lost = asyncio.Event()  # connection_lost was called
        self._now = now
        #: (bytes, arrival time of the chunk's last byte) of the bytes in the buffer, oldest first
        self._arrivals: deque[list[float]] = deque()
        self.kernel_waiting: Callable[[], int] | None = None
        self.byte_period_s: Callable[[], float] | None = None
        self.full_read = TRANSPORT_READ_SIZE

    def data_received(self, data: bytes) -> None:
        self._buffer += data
        if self._now is not None:
            arrived_s = self._now()
            if len(data) >= self.full_read and self.kernel_waiting is not None and self.byte_period_s is not None:
                with contextlib.suppress(OSError, serial.SerialException):
                    arrived_s -= int(self.kernel_waiting()) * self.byte_period_s()
            self._arrivals.append([float(len(data)), arrived_s])
        excess = len(self._buffer) - MAX_BUFFERED_BYTES
        if excess > 0:
            del self._buffer[:excess]
            self._forget_arrivals(excess)
            self.bytes_overflowed += excess
        self._wake()

    def _forget_arrivals(self, count: int) -> None:
        """The arrival notes of the ``count`` oldest buffered bytes, which were taken or dropped."""
        arrivals = self._arrivals
        while count > 0 and arrivals:
            first = arrivals[0]
            if first[0] <= count:
                count -= int(first[0])
                arrivals.popleft()
            else:
                first[0] -= count
                count = 0

    def eof_received(self) -> bool:
        self._eof = True
        self._wake()
        return False

    def connection_lost(self, exc: Exception | None) -> None:
        self._eof = True
        self._error = exc
        self.lost.set()
        self._wake()

    def _wake(self) -> None:
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(None)

    async def read(self, max_bytes: int) -> bytes:
        while not self._buffer:
            if self._error is not None:
                raise OSError(f"serial link failed: {self._error}") from self._error
            if self._eof:
                return b""
            self._waiter = asyncio.get_running_loop().create_future()
            try:
                await self._waiter
            finally:
                self._waiter = None
        data = bytes(self._buffer[:max_bytes])
        del self._buffer[:max_bytes]
        self._forget_arrivals(len(data))
        return data

    def take_arrived(self) -> tuple[bytes, list[tuple[int, float]]]:
        """Every byte buffered, at once, and its chunks: (bytes, arrival time) each, oldest first."""
        data = bytes(self._buffer)
        self._buffer.clear()
        chunks = [(int(count), time_s) for count, time_s in self._arrivals]
        self._arrivals.clear()
        return data, chunks

    def clear(self) -> None:
        self._buffer.clear()
        self._arrivals.clear()

    @property
    def buffered(self) -> int:
        """Bytes received and not yet read."""
        return len(self._buffer)

    @property
    def failed(self) -> bool:
        """The port failed or closed: ``read`` says so (an error or end of file), ``take_arrived`` cannot."""
        return self._eof or self._error is not None


class NonBlockingSerial(serial.Serial):  # type: ignore[misc]  # pyserial has no type information
    """pyserial's POSIX port whose non-blocking read (``timeout=0``) is one ``os.read``.

    pyserial-asyncio's transport calls ``read`` each time the event loop finds the port
    readable (every chunk the USB adapter delivers: ~40 a second from the simulator's
    pseudo-terminal, one every few milliseconds from a CP2102). pyserial's read, written for
    every timeout, makes a ``Timeout`` object, asks ``select`` again whether the port (and
    its cancel pipe) is readable, then reads: ~25 µs of Python and a second system call per
    chunk on this machine. With ``timeout=0`` on a port opened ``O_NONBLOCK`` (as pyserial
    opens it) a single ``os.read`` gives the same bytes when there are some, and a failure
    the same :class:`serial.SerialException`. A read of no bytes is ambiguous on a raw tty
    (nothing waiting, or a disconnected device that stays readable): pyserial's own read
    tells them apart (``b""``, or its exception), as before. The cancel pipe serves blocking
    reads from another thread, which this link never makes. Any other timeout reads the
    pyserial way.
    """

    def read(self, size: int = 1) -> bytes:
        if self._timeout != 0 or not self.is_open or size <= 0:
            return bytes(super().read(size))
        try:
            data = os.read(self.fd, size)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as exc:
            raise serial.SerialException(f"read failed: {exc}") from exc
        if not data:  # nothing waiting (a raw tty's read returns 0 then) or a device gone: pyserial tells them apart
            return bytes(super().read(size))
        return data


def _serial_port(port: str, baudrate: int) -> serial.SerialBase:
    """The port, not yet open, non-blocking: a device path as :class:`NonBlockingSerial`, a pyserial
    URL (``loop://``, ``socket://``...) the way :func:`serial.serial_for_url` makes it."""
    if "://" in port or os.name != "posix":
        return serial.serial_for_url(port, baudrate=baudrate, timeout=0, do_not_open=True)
    ser = NonBlockingSerial(None, baudrate=baudrate, timeout=0)
    ser.port = port
    return ser


class SerialLink:
    """The lidar's USB serial adapter, through pyserial-asyncio.

    Example::

        link = await SerialLink.open("/dev/ttyUSB0", 115200)
        await link.write(b"\\xa5\\x50")
        data = await link.read()
        await link.close()
    """

    def __init__(
        self, port: str, serial_instance: serial.SerialBase, transport: asyncio.Transport, protocol: _BufferedProtocol
    ) -> None:
        self.port = port
        self._serial = serial_instance
        self._transport = transport
        self._protocol = protocol
        self._closed = False

    @classmethod
    async def open(cls, port: str, baudrate: int = 115200) -> SerialLink:
        """Open ``port`` with DTR cleared (the A1 motor keeps spinning).

        Raises HardwareUnavailable, with a hint (cable, dialout group), when the port
        is missing or cannot be opened.
        """
        try:
            ser = _serial_port(port, baudrate)
            ser.dtr = False  # applied at open: the motor must not stop
            ser.open()
        except (serial.SerialException, OSError, ValueError) as exc:
            # pyserial wraps the OSError of open() in a long message; the original
            # one says it best ("No such file or directory", "Permission denied")
            cause = exc.__context__ if isinstance(exc.__context__, OSError) else exc
            raise HardwareUnavailable(serial_port_hint(port, cause)) from exc
        loop = asyncio.get_running_loop()
        protocol = _BufferedProtocol(loop.time)  # RealClock's time: the driver's stamps
        protocol.kernel_waiting = lambda: ser.in_waiting
        try:
            transport, _ = await serial_asyncio.connection_for_serial(loop, lambda: protocol, ser)
        except Exception:
            ser.close()
            raise
        return cls(port, ser, transport, protocol)

    async def read(self, max_bytes: int = READ_SIZE) -> bytes:
        if self._closed:
            return b""
        return await self._protocol.read(max_bytes)

    def take_arrived(self, byte_period_s: Callable[[], float]) -> tuple[bytes, list[tuple[int, float]]] | None:
        """Every byte that has arrived, without waiting, with the loop-clock time each chunk of them
        arrived (``(bytes, time_s)``, oldest first); None when the port failed or closed (``read``
        says how).

        The lidar driver takes its bytes this way between two decodes: the transport's callback
        notes each chunk as it comes, and the driver's task wakes once a decode interval instead
        of once a chunk (a USB serial adapter delivers one every few milliseconds). A full chunk's
        time is moved back by the bytes still waiting in the kernel, ``byte_period_s()`` each.
        """
        if self._closed or self._protocol.failed:
            return None
        self._protocol.byte_period_s = byte_period_s
        return self._protocol.take_arrived()

    def pending_bytes(self) -> int:
        """Bytes that arrived and wait to be read: in the protocol's buffer and in the kernel's.

        The kernel's count (``in_waiting``, the FIONREAD ioctl) holds what came while the
        event loop could not run; the watchdogs look at it before they call the lidar silent.
        """
        waiting = self._protocol.buffered
        if not self._closed:
            with contextlib.suppress(OSError, serial.SerialException):
                waiting += int(self._serial.in_waiting)
        return waiting

    async def write(self, data: bytes) -> None:
        if self._closed or self._transport.is_closing():
            raise OSError(f"lidar serial port {self.port} is closed")
        self._transport.write(data)

    def set_motor(self, on: bool) -> None:
        if self._closed:
            return
        try:
            self._serial.dtr = not on  # DTR cleared = motor spinning on the A1 adapter
        except OSError as exc:  # (SerialException is an OSError too)
            if exc.errno in (errno.ENOTTY, errno.EINVAL):  # a pseudo-terminal has no DTR
                log.debug("%s has no DTR line (%s); motor left as it is", self.port, exc)
            else:
                log.warning("cannot switch the lidar motor on %s: %s", self.port, exc)

    def reset_input_buffer(self) -> None:
        if self._closed:
            return
        try:
            self._serial.reset_input_buffer()
        except (serial.SerialException, OSError) as exc:
            log.debug("cannot flush %s: %s", self.port, exc)
        self._protocol.clear()

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._transport.close()
        # the transport sends what is buffered, then closes the port (connection_lost)
        try:
            await asyncio.wait_for(self._protocol.lost.wait(), CLOSE_TIMEOUT_S)
        except TimeoutError:
            self._transport.abort()
            await asyncio.sleep(0)
        if self._serial.is_open:
            self._serial.close()


class StreamLink:
    """A ByteLink on an asyncio StreamReader/StreamWriter pair.

    The simulator serves the emulated lidar this way (see ``memory_link_pair``);
    ``on_motor`` receives every motor switch (True = spinning), since a stream has no
    DTR line.

    Example::

        link, (dev_reader, dev_writer) = memory_link_pair()
        await link.write(b"\\xa5\\x52")
        await dev_reader.readexactly(2)   # the device side sees the request
    """

    def __init__(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        on_motor: Callable[[bool], None] | None = None,
    ) -> None:
        self._reader = reader
        self._writer = writer
        self._on_motor = on_motor
        self._closed = False

    async def read(self, max_bytes: int = READ_SIZE) -> bytes:
        if self._closed:
            return b""
        return await self._reader.read(max_bytes)

    def pending_bytes(self) -> int:
        """Bytes that arrived and wait to be read (the stream reader's buffer)."""
        # StreamReader has no public count of its buffer; ``_buffer`` is a bytearray in CPython
        return 0 if self._closed else len(getattr(self._reader, "_buffer", b""))

    async def write(self, data: bytes) -> None:
        if self._closed or self._writer.is_closing():
            raise ConnectionResetError("lidar stream is closed")
        self._writer.write(data)
        await self._writer.drain()

    def set_motor(self, on: bool) -> None:
        if self._on_motor is not None and not self._closed:
            self._on_motor(on)

    def reset_input_buffer(self) -> None:
        # StreamReader has no public way to discard buffered bytes without awaiting;
        # its buffer is a bytearray attribute in every CPython since 3.4.
        buffered = getattr(self._reader, "_buffer", None)
        if isinstance(buffered, bytearray):
            buffered.clear()

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._writer.close()
        with contextlib.suppress(OSError):  # the other end may be gone already
            await self._writer.wait_closed()


class _MemoryTransport(asyncio.Transport):
    """One end of an in-memory pipe: what it writes arrives at the peer's protocol.

    Flow control is passed across: when the peer's reader pauses reading (its buffer is
    full), this end's protocol is asked to pause writing, so ``drain()`` waits.
    """

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        super().__init__()
        self._loop = loop
        self.protocol: asyncio.Protocol | None = None
        self.peer: _MemoryTransport | None = None
        self._closing = False
        self._paused = False
        #: the peer's reader is full and asked this end to stop writing (drain() would wait)
        self.peer_full = False

    def get_extra_info(self, name: str, default: Any = None) -> Any:
        return {"peername": "memory", "sockname": "memory"}.get(name, default)

    def is_closing(self) -> bool:
        return self._closing

    def write(self, data: bytes | bytearray | memoryview) -> None:
        if self._closing or not data:
            return
        peer = self.peer
        if peer is not None and peer.protocol is not None and not peer._closing:
            peer.protocol.data_received(bytes(data))

    def writelines(self, list_of_data: Any) -> None:
        for data in list_of_data:
            self.write(data)

    def can_write_eof(self) -> bool:
        return True

    def write_eof(self) -> None:
        peer = self.peer
        if peer is not None and peer.protocol is not None and not peer._closing:
            peer.protocol.eof_received()

    def get_write_buffer_size(self) -> int:
        return 0

    def pause_reading(self) -> None:
        # our reader is full: the peer must stop writing
        if self.peer is not None and self.peer.protocol is not None and not self._paused:
            self._paused = True
            self.peer.peer_full = True
            self.peer.protocol.pause_writing()

    def resume_reading(self) -> None:
        if self.peer is not None and self.peer.protocol is not None and self._paused:
            self._paused = False
            self.peer.peer_full = False
            self.peer.protocol.resume_writing()

    def is_reading(self) -> bool:
        return not self._paused

    def close(self) -> None:
        if self._closing:
            return
        self._closing = True
        peer = self.peer
        if self._paused:
            self.resume_reading()
        if peer is not None and peer.protocol is not None and not peer._closing:
            peer_protocol = peer.protocol
            peer._closing = True
            self._loop.call_soon(peer_protocol.connection_lost, None)
        if self.protocol is not None:
            self._loop.call_soon(self.protocol.connection_lost, None)

    def abort(self) -> None:
        self.close()


def _stream_end(
    loop: asyncio.AbstractEventLoop, limit: int
) -> tuple[asyncio.StreamReader, asyncio.StreamWriter, _MemoryTransport]:
    reader = asyncio.StreamReader(limit=limit, loop=loop)
    protocol = asyncio.StreamReaderProtocol(reader, loop=loop)
    transport = _MemoryTransport(loop)
    transport.protocol = protocol
    protocol.connection_made(transport)
    writer = asyncio.StreamWriter(transport, protocol, reader, loop)
    return reader, writer, transport


def memory_stream_pair(
    limit: int = 1 << 16,
) -> tuple[tuple[asyncio.StreamReader, asyncio.StreamWriter], tuple[asyncio.StreamReader, asyncio.StreamWriter]]:
    """Two connected (reader, writer) pairs, without sockets: each writer feeds the other reader.

    Closing either writer ends the stream on both sides (the other reader sees EOF),
    like a USB adapter that is unplugged. Must be called with an event loop running.
    """
    loop = asyncio.get_running_loop()
    a_reader, a_writer, a_transport = _stream_end(loop, limit)
    b_reader, b_writer, b_transport = _stream_end(loop, limit)
    a_transport.peer = b_transport
    b_transport.peer = a_transport
    return (a_reader, a_writer), (b_reader, b_writer)


def memory_link_pair(
    on_motor: Callable[[bool], None] | None = None, limit: int = 1 << 16
) -> tuple[StreamLink, tuple[asyncio.StreamReader, asyncio.StreamWriter]]:
    """A driver-side StreamLink connected in memory to a device-side (reader, writer).

    The device side (the emulator, or a scripted fake in a test) reads requests from
    its reader and writes responses to its writer. Must be called with a loop running.

    Example::

        link, (dev_reader, dev_writer) = memory_link_pair()
        # serve the device side (e.g. mazebot.sim's emulator) on dev_reader/dev_writer
    """
    (drv_reader, drv_writer), device = memory_stream_pair(limit)
    return StreamLink(drv_reader, drv_writer, on_motor), device
