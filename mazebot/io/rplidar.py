"""Asyncio driver of the Slamtec RPLidar family (A1, A2, A3, C1, S2): requests, scan modes,
scans, and surviving a flaky USB link.

Why one module of ~960 lines: :class:`RPLidar` is one device's life cycle (start, scan modes,
scanning, a silent or vanished port, reconnecting) whose states interleave in one reader loop;
the helpers below it (:class:`_ArrivalLog`, :class:`_RevolutionBuilder`) only time-stamp and
gather its samples. The byte protocol is apart already (:mod:`mazebot.io.rplidar_protocol`).

The driver only buffers bytes and hands them to the pure decoders of
``mazebot.io.rplidar_protocol``; what it adds is the device's life cycle:

* start: motor on (DTR cleared), STOP, wait, flush, GET_HEALTH (on an error: RESET
  and ask again), the scan mode (``[lidar] scan_mode``; ``auto`` asks GET_LIDAR_CONF
  for the unit's typical mode), let the motor spin up, SCAN or EXPRESS_SCAN in that
  mode, decoded by the capsule kind its answer type names;
* a silent port: GET_INFO at the family's other serial speeds, to say which unit
  speaks what (``no answer at 115200 baud on /dev/ttyUSB0: a C1M1 speaks 460800, set
  [lidar] baudrate``);
* run: decode, stamp each sample with a clock time (from the arrival time of the bytes
  that completed it, not the later decode time), cut the stream into revolutions
  (``mazebot.io.scan.Scan``, one per turn, in the robot's angle convention);
* trouble: no sample for ``no_data_timeout_s`` -> STOP and restart the scan; the port
  vanishes (EOF, OSError) or the device stays unhealthy -> close it and reopen with an
  exponential backoff; while the port cannot even be opened (the cable is out) it is
  looked for every ``backoff_min_s``. ``scans()`` never ends for a device fault, only when cancelled;
  ``stats`` tells what happened.

Example::

    async with RPLidar.from_config(cfg.lidar, RealClock()) as lidar:
        print(await lidar.get_info())
        async for scan in lidar.scans():
            ...
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections import deque
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np

from mazebot.clock import Clock, RealClock
from mazebot.config import LidarConfig
from mazebot.cpu_budget import PartMeter
from mazebot.errors import ConfigError, HardwareUnavailable, MazebotError, ProtocolError
from mazebot.io import rplidar_protocol as proto
from mazebot.io.rplidar_models import BAUDRATES, model_name
from mazebot.io.rplidar_protocol import DecodedSamples, DeviceHealth, DeviceInfo, SampleRate, ScanModeInfo
from mazebot.io.scan import Scan
from mazebot.io.serial_link import ByteLink, SerialLink

log = logging.getLogger(__name__)

ScanMode = Literal["auto", "standard", "express", "boost", "sensitivity", "stability", "denseboost"]
SCAN_MODES: tuple[str, ...] = ("auto", "standard", "express", "boost", "sensitivity", "stability", "denseboost")
LinkFactory = Callable[[], Awaitable[ByteLink]]
#: Opens the same port at another serial speed (to tell a silent port from a wrong speed).
ProbeFactory = Callable[[int], Awaitable[ByteLink]]

#: Nominal time per sample (A1M8 datasheet: ~2000 samples/s standard, ~4000 express),
#: until the device's own figure for the mode is known.
NOMINAL_SAMPLE_PERIOD_S = {"standard": 1 / 2000, "express": 1 / 4000}
#: The two scan modes every unit has, with or without GET_LIDAR_CONF (the SDK's fallback
#: for old firmware, sl_lidar_driver.cpp getTypicalScanMode: express).
LEGACY_MODES = (
    ScanModeInfo(proto.SCAN_MODE_ID_STANDARD, "Standard", 1e6 * NOMINAL_SAMPLE_PERIOD_S["standard"], 12.0,
                 proto.TYPE_SCAN),
    ScanModeInfo(proto.SCAN_MODE_ID_EXPRESS, "Express", 1e6 * NOMINAL_SAMPLE_PERIOD_S["express"], 12.0,
                 proto.TYPE_EXPRESS),
)
#: Datasheet: wait at least 1 ms after STOP before the next request; 10 ms also lets
#: the bytes already on the wire arrive, so the flush removes them.
STOP_SETTLE_S = 0.010
#: Scan restarts in a row without a single sample before the port is reopened.
MAX_RESTARTS_WITHOUT_DATA = 3
#: Decode at most this often. A decoder call has a fixed cost (~0.1-0.2 ms quiet, about
#: three times that in the daemon under a Pi's share of CPU, where a call's caches are
#: cold): at 80 ms the ~2 000 samples a second are decoded in ~12 calls instead of ~25.
#: Time stamps come from the bytes' arrival, not the decode (and a batch's samples are
#: spaced by its own measured period: ``MEASURED_PERIOD_BAND``); a revolution is handed
#: to SLAM at most this long after its last byte (~180 ms a revolution at 5.5 rev/s).
DECODE_INTERVAL_S = 0.08
#: Samples stamped in one batch are spaced by the batch's own period (the time from the
#: previous batch's newest sample to this one's, over the samples) when that is within this
#: fraction of the nominal period, else at most the nominal one.
MEASURED_PERIOD_BAND = 0.1
#: A revolution longer than this many samples is cut (the start flag never came).
MAX_SAMPLES_PER_REVOLUTION = 8192


#: Every descriptor the A1 sends; a5 5a followed by anything else is stray data.
_KNOWN_DESCRIPTORS = frozenset(
    d.encode()
    for d in (
        proto.INFO_DESCRIPTOR,
        proto.HEALTH_DESCRIPTOR,
        proto.SAMPLERATE_DESCRIPTOR,
        proto.SCAN_DESCRIPTOR,
        proto.EXPRESS_DESCRIPTOR,
        proto.ULTRA_DESCRIPTOR,
        proto.DENSE_DESCRIPTOR,
        proto.ULTRA_DENSE_DESCRIPTOR,
    )
)
_SCAN_DESCRIPTORS = {
    d.dtype: d
    for d in (proto.SCAN_DESCRIPTOR, proto.EXPRESS_DESCRIPTOR, proto.ULTRA_DESCRIPTOR, proto.DENSE_DESCRIPTOR,
              proto.ULTRA_DENSE_DESCRIPTOR)
}


class _LinkLost(OSError):
    """The link reported end of file: the port or the emulator went away."""


@dataclass
class LidarStats:
    """Counters of what the driver went through; read them, never reset them."""

    bytes_dropped: int = 0  # bytes the decoders skipped to resynchronise
    reconnects: int = 0  # times the link was reopened after a fault
    scan_restarts: int = 0  # scans restarted because no sample came in time
    health_errors: int = 0  # GET_HEALTH answers with status "error"
    revolutions: int = 0  # scans yielded
    samples: int = 0  # samples decoded
    bytes_received: int = 0  # scan bytes read from the link
    last_receive_s: float | None = None  # clock time of the last scan bytes read
    last_error: str = ""  # the last fault, one line
    connected: bool = False  # a link is open


class RPLidar:
    """An RPLidar (A1, A2, A3, C1, S2) behind a ByteLink (serial port, pseudo-terminal or memory pipe).

    Nothing is opened by the constructor: the link is made by ``link_factory`` on first
    use, and again after a fault. Use it as an async context manager, or call
    ``close()`` (idempotent), which stops the scan and the motor.

    Example::

        lidar = RPLidar(lambda: SerialLink.open("/dev/ttyUSB0", 115200), RealClock())
        async with lidar:
            health = await lidar.get_health()
            async for scan in lidar.scans():
                print(len(scan), lidar.stats.bytes_dropped)
    """

    def __init__(
        self,
        link_factory: LinkFactory,
        clock: Clock,
        *,
        scan_mode: ScanMode = "standard",
        motor_control: bool = True,
        spin_up_s: float = 0.5,
        no_data_timeout_s: float = 1.0,
        backoff_min_s: float = 0.5,
        backoff_max_s: float = 8.0,
        min_range_m: float = 0.15,
        max_range_m: float = 12.0,
        mount_yaw_deg: float = 0.0,
        response_timeout_s: float = 1.0,
        reset_settle_s: float = 0.5,
        sample_period_s: float | None = None,
        name: str = "lidar",
        baudrate: int | None = None,
        probe_factory: ProbeFactory | None = None,
    ) -> None:
        if scan_mode not in SCAN_MODES:
            raise ValueError(f"scan_mode must be one of {', '.join(SCAN_MODES)}, got {scan_mode!r}")
        if not 0 < backoff_min_s <= backoff_max_s:
            raise ValueError(f"need 0 < backoff_min_s ({backoff_min_s}) <= backoff_max_s ({backoff_max_s})")
        self._factory = link_factory
        self._clock = clock
        self.scan_mode: ScanMode = scan_mode
        self._motor_control = motor_control
        self._spin_up_s = spin_up_s
        self._no_data_timeout_s = no_data_timeout_s
        self._backoff_min_s = backoff_min_s
        self._backoff_max_s = backoff_max_s
        self._min_range_m = min_range_m
        self._max_range_m = max_range_m
        self._mount_yaw_rad = math.radians(mount_yaw_deg)
        self._response_timeout_s = response_timeout_s
        self._reset_settle_s = reset_settle_s
        self._sample_period_s = sample_period_s
        self.name = name
        self.stats = LidarStats()
        #: CPU time the decoders take (the daemon's budget: :mod:`mazebot.cpu_budget`)
        self.decode_meter = PartMeter("lidar decoding")
        self._link: ByteLink | None = None
        self._rx = bytearray()  # received, not yet consumed by a response
        self._reader: asyncio.Future[bytes] | None = None  # the pending read of the link
        self._read_at_s: float | None = None  # when the last byte of the latest read arrived
        self._motor_on = False
        self._scanning = False
        self._closed = False
        self._last_time_s = -math.inf  # time stamp of the last sample
        self._dropped_before = 0  # bytes dropped by decoders of earlier scans
        self._decoder: proto.StandardScanDecoder | proto.ExpressScanDecoder | None = None
        self._revolutions_cut = 0  # numbers the revolutions (Scan.revolution)
        self._undecoded = 0  # scan bytes read and not yet decoded (the session's batch)
        self._pending_conf_length = 0
        self._baudrate = baudrate
        self._probe_factory = probe_factory
        self._heard = False  # the open link ever brought a byte
        #: the scan mode streaming (or last started): its answer type picks the decoder
        self.active_mode: ScanModeInfo = LEGACY_MODES[1] if scan_mode == "express" else LEGACY_MODES[0]

    @classmethod
    def from_config(
        cls, cfg: LidarConfig, clock: Clock, link_factory: LinkFactory | None = None,
        probe_factory: ProbeFactory | None = None,
    ) -> RPLidar:
        """The lidar of the ``[lidar]`` config section (default link: its serial port;
        ``probe_factory`` opens the same line at another speed, default: the port)."""
        async def open_serial() -> ByteLink:
            return await SerialLink.open(cfg.port, cfg.baudrate)

        async def open_at(baudrate: int) -> ByteLink:
            return await SerialLink.open(cfg.port, baudrate)

        return cls(
            link_factory or open_serial,
            clock,
            scan_mode=cfg.scan_mode,
            motor_control=cfg.motor_control == "dtr",
            spin_up_s=cfg.spin_up_s,
            no_data_timeout_s=cfg.no_data_timeout_s,
            backoff_min_s=cfg.reconnect_backoff_min_s,
            backoff_max_s=cfg.reconnect_backoff_max_s,
            min_range_m=cfg.min_range_m,
            max_range_m=cfg.max_range_m,
            mount_yaw_deg=cfg.mount_yaw_deg,
            name=f"lidar on {cfg.port}",
            baudrate=cfg.baudrate,
            probe_factory=probe_factory or (None if link_factory is not None else open_at),
        )

    async def __aenter__(self) -> RPLidar:
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.close()

    # -- link ------------------------------------------------------------------------

    async def open(self) -> ByteLink:
        """The open link, opening it if needed (HardwareUnavailable if it cannot be)."""
        if self._closed:
            raise RuntimeError(f"{self.name} is closed")
        if self._link is None:
            self._link = await self._factory()
            self._heard = False
            self._rx.clear()
            self._motor_on = False
            self._scanning = False
            self.stats.connected = True
        return self._link

    async def close(self) -> None:
        """Stop the scan and the motor and close the link; harmless when repeated."""
        self._closed = True
        await self._drop_link(stop=True)

    async def _drop_link(self, *, stop: bool) -> None:
        link, self._link = self._link, None
        self.stats.connected = False
        self._cancel_read()
        self._rx.clear()
        self._undecoded = 0  # the session's batch went with the link
        if link is None:
            return
        try:
            if stop:
                await link.write(proto.build_request(proto.CMD_STOP))
                if self._motor_control:
                    link.set_motor(False)
        except OSError as exc:  # the port may be gone already
            log.debug("%s: cannot stop before closing: %s", self.name, exc)
        finally:
            self._scanning = False
            self._motor_on = False
            await link.close()

    async def _read(self, timeout_s: float) -> bytes:
        """Some bytes within ``timeout_s`` (TimeoutError), or _LinkLost at end of file.

        The read of the link outlives a timeout: the next call waits on the same read
        instead of cancelling it and starting another. The scan loop times out about
        as often as it receives (it wakes up to decode), and a task per read was a
        visible share of a simulated run's event-loop work.
        """
        link = await self.open()
        reader = self._reader
        if reader is None:
            reader = self._reader = asyncio.ensure_future(self._timed_read(link))
        if not reader.done():
            await self._wait_done(reader, max(0.0, timeout_s))
            if not reader.done():
                raise TimeoutError(f"{self.name}: no answer within {timeout_s:.3g} s")
        self._reader = None
        data = reader.result()
        if not data:
            raise _LinkLost(f"{self.name}: the port closed (end of file)")
        self._heard = True
        return data

    async def _timed_read(self, link: ByteLink) -> bytes:
        """``link.read()``, noting when its last byte arrived in ``_read_at_s``.

        The time is taken in the reader itself, as the read returns: the scan loop may
        resume much later (the event loop was busy), and stamping the bytes then would
        make them look younger than they are. When more bytes wait behind the ones read
        (a backlog after a stall: the serial transport reads 1 KiB at a time), the last
        byte read came that many bytes before the newest one, at the device's data rate.
        """
        data = await link.read()
        pending = getattr(link, "pending_bytes", None)
        behind = int(pending()) if pending is not None else 0
        self._read_at_s = self._clock.now_s() - behind * self._byte_period_s()
        return data

    def _byte_period_s(self) -> float:
        """Time the device takes to send one byte of a scan: 5-byte samples, or the active mode's capsules."""
        fmt = proto.CAPSULE_FORMATS.get(self.active_mode.answer_type)
        if fmt is not None:
            return self._period_s() * fmt.samples / fmt.length
        return self._period_s() / proto.STANDARD_SAMPLE_LEN

    def _cancel_read(self) -> None:
        """Forget the pending read (the input is flushed or the link dropped)."""
        reader, self._reader = self._reader, None
        if reader is None:
            return
        if not reader.done():
            reader.cancel()
        elif not reader.cancelled():
            reader.exception()  # its bytes (or failure) go with the rest; mark it retrieved

    async def _wait_done(self, future: asyncio.Future[bytes], timeout_s: float) -> None:
        """Return once ``future`` is done or ``timeout_s`` of the clock has passed.

        On the daemon's clock (``RealClock``: the running loop's own time) the timeout is
        one loop timer and the wait one future woken by whichever comes first. The
        general way, a sleeping task raced against the read with ``asyncio.wait``, costs
        a task, two of its steps and the wait's callbacks per call, and the scan loop
        waits ~75 times a second: on virtual time it was the largest share of the event
        loop's work. Any other clock gets the general way.
        """
        if not isinstance(self._clock, RealClock):
            timer_task = asyncio.ensure_future(self._clock.sleep(timeout_s))
            try:
                waiters: set[asyncio.Future[Any]] = {future, timer_task}
                await asyncio.wait(waiters, return_when=asyncio.FIRST_COMPLETED)
            finally:
                timer_task.cancel()
            return
        loop = asyncio.get_running_loop()
        waiter = loop.create_future()

        def wake(_: object = None) -> None:
            if not waiter.done():
                waiter.set_result(None)

        future.add_done_callback(wake)
        timer = loop.call_later(timeout_s, wake)
        try:
            await waiter
        finally:
            timer.cancel()
            future.remove_done_callback(wake)

    async def _send(self, cmd: int, payload: bytes = b"") -> None:
        link = await self.open()
        await link.write(proto.build_request(cmd, payload))

    async def _flush(self) -> None:
        link = await self.open()
        self._cancel_read()
        link.reset_input_buffer()
        self._rx.clear()

    async def _descriptor(self, expected: proto.Descriptor, what: str) -> None:
        """Read up to and including the descriptor that answers ``what``."""
        deadline = self._clock.now_s() + self._response_timeout_s
        while True:
            at = self._rx.find(b"\xa5\x5a")
            if at < 0:  # nothing yet; keep a last 0xA5, it may begin the descriptor
                keep = 1 if self._rx[-1:] == b"\xa5" else 0
                del self._rx[: len(self._rx) - keep]
            else:
                del self._rx[:at]
                if len(self._rx) >= proto.DESCRIPTOR_LEN:
                    head = bytes(self._rx[: proto.DESCRIPTOR_LEN])
                    if head == expected.encode():
                        del self._rx[: proto.DESCRIPTOR_LEN]
                        return
                    if head in _KNOWN_DESCRIPTORS:  # the device answered something else
                        try:
                            proto.parse_descriptor(head, expected)
                        except ProtocolError as exc:
                            raise ProtocolError(f"{self.name}, answer to {what}: {exc}") from None
                    del self._rx[:1]  # a5 5a by chance in stale bytes: look further
                    continue
            await self._receive(deadline, what)

    async def _receive(self, deadline_s: float, what: str) -> None:
        remaining = deadline_s - self._clock.now_s()
        try:
            if remaining <= 0:
                raise TimeoutError
            self._rx += await self._read(remaining)
        except TimeoutError:
            if not self._heard and self._probe_factory is not None and self._baudrate is not None:
                wrong_speed = await self._diagnose_baudrate()
                if wrong_speed:
                    raise HardwareUnavailable(wrong_speed) from None
            raise HardwareUnavailable(
                f"{self.name} did not answer {what} within {self._response_timeout_s:g} s; "
                "check that the lidar is powered and that this is its port"
            ) from None

    async def _diagnose_baudrate(self) -> str | None:
        """A silent port: is it a unit of the family at another serial speed?

        Asks GET_INFO at each speed the family speaks (``rplidar_models.BAUDRATES``) on
        the same port; when one answers, says which model speaks what. The link is
        closed (the next use reopens it at the configured speed).
        """
        assert self._probe_factory is not None
        port = self.name.removeprefix("lidar on ")
        await self._drop_link(stop=False)
        for baud in BAUDRATES:
            if baud == self._baudrate:
                continue
            try:
                link = await self._probe_factory(baud)
            except (OSError, MazebotError):
                return None
            try:
                await link.write(proto.build_request(proto.CMD_GET_INFO))
                info = await self._probe_info(link)
            finally:
                await link.close()
            if info is not None:
                name = model_name(info.model)
                article = "an" if name[:1] in "AEFHILMNORSX" else "a"
                return (f"no answer at {self._baudrate} baud on {port}: {article} {name} speaks {baud}, "
                        "set [lidar] baudrate")
        return None

    async def _probe_info(self, link: ByteLink) -> DeviceInfo | None:
        """The GET_INFO answer on a probing link, or None within the response timeout."""
        deadline_s = self._clock.now_s() + self._response_timeout_s
        buf = bytearray()
        want = proto.INFO_DESCRIPTOR.encode()
        reader = asyncio.ensure_future(link.read())
        try:
            while (remaining := deadline_s - self._clock.now_s()) > 0:
                await self._wait_done(reader, remaining)
                if not reader.done():
                    return None
                data = reader.result()
                if not data:
                    return None
                buf += data
                at = buf.find(want)
                if at >= 0 and len(buf) >= at + len(want) + proto.INFO_DESCRIPTOR.length:
                    begin = at + len(want)
                    return proto.parse_info(bytes(buf[begin : begin + proto.INFO_DESCRIPTOR.length]))
                reader = asyncio.ensure_future(link.read())
            return None
        finally:
            if not reader.done():
                reader.cancel()

    async def _request(self, cmd: int, expected: proto.Descriptor) -> bytes:
        """Send a single-response request and return its payload."""
        if self._scanning:
            await self.stop()
        what = proto.COMMAND_NAMES[cmd]
        await self._send(cmd)
        await self._descriptor(expected, what)
        deadline = self._clock.now_s() + self._response_timeout_s
        while len(self._rx) < expected.length:
            await self._receive(deadline, what)
        payload = bytes(self._rx[: expected.length])
        del self._rx[: expected.length]
        return payload

    # -- requests --------------------------------------------------------------------

    async def get_info(self) -> DeviceInfo:
        """Model, firmware, hardware and serial number (stops a running scan)."""
        return proto.parse_info(await self._request(proto.CMD_GET_INFO, proto.INFO_DESCRIPTOR))

    async def get_health(self) -> DeviceHealth:
        """Health status (good / warning / error) and error code (stops a running scan)."""
        return proto.parse_health(await self._request(proto.CMD_GET_HEALTH, proto.HEALTH_DESCRIPTOR))

    async def get_samplerate(self) -> SampleRate:
        """Time per sample of each scan mode, in microseconds (stops a running scan)."""
        payload = await self._request(proto.CMD_GET_SAMPLERATE, proto.SAMPLERATE_DESCRIPTOR)
        return proto.parse_samplerate(payload)

    async def get_lidar_conf(self, conf_type: int, mode_id: int | None = None) -> bytes:
        """The payload of one GET_LIDAR_CONF answer (stops a running scan)."""
        if self._scanning:
            await self.stop()
        await self._send_raw(proto.build_conf_request(conf_type, mode_id))
        deadline = self._clock.now_s() + self._response_timeout_s
        await self._conf_descriptor(deadline)
        length = self._pending_conf_length
        while len(self._rx) < length:
            await self._receive(deadline, "GET_LIDAR_CONF")
        data = bytes(self._rx[:length])
        del self._rx[:length]
        return proto.parse_conf_answer(data, conf_type)

    async def _conf_descriptor(self, deadline_s: float) -> None:
        """Read up to and including a GET_LIDAR_CONF descriptor (its length varies)."""
        while True:
            at = self._rx.find(b"\xa5\x5a")
            if at >= 0 and len(self._rx) >= at + proto.DESCRIPTOR_LEN:
                head = bytes(self._rx[at : at + proto.DESCRIPTOR_LEN])
                del self._rx[: at + proto.DESCRIPTOR_LEN]
                found = proto.parse_descriptor(head)
                if found.dtype != proto.TYPE_LIDAR_CONF:
                    raise ProtocolError(f"{self.name}, answer to GET_LIDAR_CONF: expected type 0x20, found ({found})")
                self._pending_conf_length = found.length
                return
            await self._receive(deadline_s, "GET_LIDAR_CONF")

    async def get_scan_modes(self) -> tuple[list[ScanModeInfo], int]:
        """The scan modes the device offers and the id of its typical one.

        As the SDK's ``getAllSupportedScanModes``: the mode count, then per mode its
        sample period, maximum distance, answer type and name. A device without
        GET_LIDAR_CONF (firmware before 1.24) does not answer: it has Standard and
        Express, and Express is its typical mode, as the SDK assumes.
        """
        try:
            count = await self._conf_value(proto.CONF_SCAN_MODE_COUNT)
        except (HardwareUnavailable, ProtocolError) as exc:
            log.info("%s has no GET_LIDAR_CONF (%s): standard and express only", self.name, _one_line(exc))
            await self._flush()
            return list(LEGACY_MODES), proto.SCAN_MODE_ID_EXPRESS
        modes = []
        for mode_id in range(int(count)):
            values = [
                await self._conf_value(t, mode_id)
                for t in (proto.CONF_SCAN_MODE_US_PER_SAMPLE, proto.CONF_SCAN_MODE_MAX_DISTANCE,
                          proto.CONF_SCAN_MODE_ANS_TYPE, proto.CONF_SCAN_MODE_NAME)
            ]
            us, max_m, answer, name = values
            modes.append(ScanModeInfo(mode_id, str(name), float(us), float(max_m), int(answer)))
        typical = await self._conf_value(proto.CONF_SCAN_MODE_TYPICAL)
        return modes, int(typical)

    async def _conf_value(self, conf_type: int, mode_id: int | None = None) -> float | int | str:
        return proto.decode_mode_conf(conf_type, await self.get_lidar_conf(conf_type, mode_id))

    async def resolve_scan_mode(self, mode: str) -> ScanModeInfo:
        """The device's scan mode for a ``[lidar] scan_mode`` value.

        ``standard`` and ``express`` are the SCAN and legacy EXPRESS_SCAN commands every
        unit knows (asked without GET_LIDAR_CONF); ``auto`` is the mode the unit calls
        typical (what the SDK's ``startScan(useTypicalScan)`` picks: its best); any
        other is the device mode of that name, a ConfigError when there is none.
        """
        if mode in ("standard", "express"):
            # GET_SAMPLERATE (firmware 1.17 on) gives both legacy modes' sample periods
            legacy = LEGACY_MODES[0] if mode == "standard" else LEGACY_MODES[1]
            try:
                rate = await self.get_samplerate()
            except (HardwareUnavailable, ProtocolError):
                await self._flush()
                return legacy
            us = rate.standard_us if mode == "standard" else rate.express_us
            return replace(legacy, us_per_sample=float(us)) if us > 0 else legacy
        modes, typical = await self.get_scan_modes()
        if mode == "auto":
            chosen = [m for m in modes if m.id == typical] or [modes[-1]]
            return chosen[0]
        named = [m for m in modes if m.name.lower() == mode]
        if not named:
            offered = ", ".join(m.name for m in modes)
            raise ConfigError(f"[lidar] scan_mode {mode!r}: the {self.name} offers no such mode; it has {offered}")
        return named[0]

    async def _send_raw(self, request: bytes) -> None:
        link = await self.open()
        await link.write(request)

    async def stop(self) -> None:
        """Stop scanning (the motor keeps spinning) and discard what was in flight."""
        await self._send(proto.CMD_STOP)
        self._scanning = False
        await self._clock.sleep(STOP_SETTLE_S)
        await self._flush()

    async def reset(self) -> None:
        """Reboot the device's core (as after power-up) and discard its boot message."""
        await self._send(proto.CMD_RESET)
        self._scanning = False
        await self._clock.sleep(self._reset_settle_s)
        await self._flush()

    async def start_scan(self, mode: str | None = None) -> bytes:
        """Bring the device up and start scanning; returns the raw bytes received so far.

        Motor on, STOP, flush, health check (RESET once on an error; HardwareUnavailable
        if the error stays), spin-up wait if the motor was off, then SCAN or
        EXPRESS_SCAN. The returned bytes are the scan's descriptor followed by any scan
        data that came with it; read the rest with ``read_raw``.
        """
        mode = mode or self.scan_mode
        link = await self.open()
        spin_up = False
        if self._motor_control and not self._motor_on:
            link.set_motor(True)
            self._motor_on = True
            spin_up = True
        await self.stop()
        health = await self.get_health()
        if health.status == proto.HEALTH_ERROR:
            self.stats.health_errors += 1
            log.warning("%s reports error %#06x; resetting it", self.name, health.error_code)
            await self.reset()
            health = await self.get_health()
            if health.status == proto.HEALTH_ERROR:
                self.stats.health_errors += 1
                raise HardwareUnavailable(
                    f"{self.name} reports a hardware error (code {health.error_code:#06x}) "
                    "even after a reset; power-cycle it"
                )
        elif health.status == proto.HEALTH_WARNING:
            log.warning("%s reports warning %#06x", self.name, health.error_code)
        chosen = await self.resolve_scan_mode(mode)
        if spin_up:
            await self._clock.sleep(self._spin_up_s)
        expected = _SCAN_DESCRIPTORS.get(chosen.answer_type)
        if expected is None:
            raise HardwareUnavailable(
                f"{self.name}: scan mode {chosen.name} answers with type {chosen.answer_type:#04x}, "
                "which this driver cannot decode; set [lidar] scan_mode to another mode"
            )
        if chosen.answer_type == proto.TYPE_SCAN:
            await self._send(proto.CMD_SCAN)
            what = "SCAN"
        else:
            # the legacy express scan as the protocol document has it (working mode 0),
            # any other mode by its id, as the SDK's startScanExpress sends it
            legacy = chosen.id == proto.SCAN_MODE_ID_EXPRESS and chosen.name == LEGACY_MODES[1].name
            payload = proto.EXPRESS_SCAN_PAYLOAD if legacy else proto.express_scan_payload(chosen.id)
            await self._send(proto.CMD_EXPRESS_SCAN, payload)
            what = f"EXPRESS_SCAN ({chosen.name})"
        await self._descriptor(expected, what)
        self.active_mode = chosen
        self._scanning = True
        data = expected.encode() + bytes(self._rx)
        self._rx.clear()
        return data

    async def read_raw(self, timeout_s: float) -> bytes:
        """Bytes received within ``timeout_s`` (b"" if none); HardwareUnavailable at EOF."""
        try:
            return await self._read(timeout_s)
        except TimeoutError:
            return b""
        except _LinkLost as exc:
            raise HardwareUnavailable(str(exc)) from None

    # -- scanning --------------------------------------------------------------------

    def bytes_waiting(self) -> int:
        """Bytes from the device not yet decoded: in the link, in a finished read, in the batch.

        Non-zero means the lidar is talking and the loop has not caught up with it yet
        (it was blocked, or the reader has not had its turn): whoever judges the lidar
        silent must wait for the reader instead (the health monitor does).
        """
        waiting = self._undecoded
        reader = self._reader
        if reader is not None and reader.done() and not reader.cancelled() and reader.exception() is None:
            waiting += len(reader.result())
        pending = getattr(self._link, "pending_bytes", None)
        if pending is not None:
            waiting += int(pending())
        return waiting

    async def scans(self) -> AsyncIterator[Scan]:
        """One Scan per revolution, for ever: device faults are survived, not raised.

        Ends only when cancelled (or after ``close()``). The first, partial revolution
        after each (re)start is dropped.
        """
        backoff_s = self._backoff_min_s
        recovering = False
        while not self._closed:
            try:
                leftover = await self.start_scan()
                if recovering:
                    self.stats.reconnects += 1
                    recovering = False
                    log.info("%s: scanning again", self.name)
                async for scan in self._session(leftover[proto.DESCRIPTOR_LEN :]):
                    backoff_s = self._backoff_min_s
                    yield scan
            except ConfigError:
                raise  # a scan mode the unit does not have: no retry will find it
            except (OSError, TimeoutError, MazebotError) as exc:
                if self._closed:
                    return
                error = _one_line(exc)
                absent = self._link is None  # the port itself could not be opened: the cable is out
                if absent and recovering:
                    # Opening a missing port costs nothing, so look for the replugged adapter
                    # every backoff_min_s rather than backing off: scanning again within
                    # about a second of the cable going back in. Said once per outage.
                    if error != self.stats.last_error:
                        log.warning("%s: %s; trying again every %.3g s", self.name, error, self._backoff_min_s)
                    self.stats.last_error = error
                    await self._clock.sleep(self._backoff_min_s)
                    continue
                self.stats.last_error = error
                log.warning("%s: %s; reconnecting in %.3g s", self.name, error, backoff_s)
                await self._drop_link(stop=False)
                recovering = True
                await self._clock.sleep(backoff_s)
                backoff_s = min(2 * backoff_s, self._backoff_max_s)

    async def _session(self, leftover: bytes) -> AsyncIterator[Scan]:
        """Revolutions of one open link; raises on a link fault, restarts stalled scans.

        A scan is stalled when no sample came for ``no_data_timeout_s`` and no byte is
        waiting to be read (:meth:`_heard_after_all`): a loop that could not run is no
        silent device.
        """
        self._undecoded = 0
        decoder = self._new_decoder()
        revolution = _RevolutionBuilder(self)
        restarts_without_data = 0
        reprieved = False  # a stall was forgiven because bytes were waiting; no sample since
        last_data_s = batch_since_s = stamped_until_s = self._clock.now_s()
        batch = bytearray(leftover)
        arrivals = _ArrivalLog()
        arrivals.add(len(batch), last_data_s)
        rhythm = SampleRhythm()
        decoded = 0  # samples decoded since the scan (re)started
        while True:
            now_s = self._clock.now_s()
            stalled = now_s - last_data_s >= self._no_data_timeout_s
            if batch and (stalled or now_s - batch_since_s >= DECODE_INTERVAL_S):
                dropped_before = decoder.bytes_dropped
                with self.decode_meter.measure():
                    samples = decoder.feed(bytes(batch))
                batch.clear()
                if decoder.bytes_dropped != dropped_before:  # samples lost: their count no longer keeps time
                    rhythm.reset()
                self.stats.bytes_dropped = self._dropped_before + decoder.bytes_dropped
                if len(samples):
                    last_data_s = now_s
                    stalled = reprieved = False
                    restarts_without_data = 0
                    self.stats.samples += len(samples)
                    latest_s = self._latest_sample_s(arrivals, arrivals.received - decoder.pending_bytes)
                    decoded += len(samples)
                    latest_s = rhythm.latest(latest_s, decoded, self._period_s())  # not later than the rhythm says
                    times = self._stamp(len(samples), latest_s, stamped_until_s)
                    stamped_until_s = max(stamped_until_s, latest_s)
                    for scan in revolution.add(samples, times):
                        self.stats.revolutions += 1
                        yield scan
            if not batch:
                batch_since_s = now_s
            self._undecoded = len(batch)
            if stalled and not batch and not reprieved and await self._heard_after_all():
                # bytes wait: one decode interval to read and decode them before judging
                # again (once: bytes that never decode into a sample are no data either)
                stalled, reprieved = False, True
                last_data_s = self._clock.now_s() - self._no_data_timeout_s + DECODE_INTERVAL_S
            if stalled:
                self.stats.scan_restarts += 1
                restarts_without_data += 1
                if restarts_without_data > MAX_RESTARTS_WITHOUT_DATA:
                    raise _LinkLost(f"{self.name}: no data after {MAX_RESTARTS_WITHOUT_DATA} scan restarts")
                log.warning("%s: no data for %.3g s; restarting the scan", self.name, self._no_data_timeout_s)
                batch = bytearray((await self.start_scan())[proto.DESCRIPTOR_LEN :])
                decoder = self._new_decoder()
                revolution = _RevolutionBuilder(self)
                last_data_s = batch_since_s = stamped_until_s = self._clock.now_s()
                arrivals = _ArrivalLog()
                arrivals.add(len(batch), last_data_s)
                rhythm.reset()
                continue
            wait_s = last_data_s + self._no_data_timeout_s - now_s
            # come back when the batch is due, even one whose first byte has not come yet: on a link
            # that notes its chunks' arrival the first chunk needs no wake-up of its own either
            due_s = min(wait_s, DECODE_INTERVAL_S - (now_s - batch_since_s))
            if await self._take_when_due(due_s, batch, arrivals):
                continue
            if batch:  # a read instead: back when the batch is due at the latest
                wait_s = due_s
            try:
                data = await self._read(max(wait_s, 0.0))
            except TimeoutError:
                continue
            batch += data
            self._undecoded = len(batch)
            now_s = self._clock.now_s()
            received_s = now_s if self._read_at_s is None else min(now_s, self._read_at_s)
            received_s = max(received_s, arrivals.last_s)  # the estimate never runs backwards
            self.stats.bytes_received += len(data)
            self.stats.last_receive_s = received_s
            arrivals.add(len(data), received_s)

    async def _take_when_due(self, wait_s: float, batch: bytearray, arrivals: _ArrivalLog) -> bool:
        """Sleep until the batch is due, then add every byte that came meanwhile; False: read instead.

        On a link that notes when its chunks came (:meth:`SerialLink.take_arrived`) and on the
        daemon's clock (the link's times are the loop's), a batch needs no wake-up per chunk,
        its first one included: its bytes are taken at once when it is due (a decode interval
        after the last decode), each chunk stamped with its own arrival, as a read per chunk
        stamped them. One timer a decode interval instead of a read, a timer and a task for each
        chunk (~50 a second from the simulator's pty, one every few milliseconds from a USB
        serial adapter), and no read to wake the task for a batch's first chunk. Not while a read
        is outstanding (it would miss the bytes taken), nor on a failed link (the read says how
        it failed).
        """
        take = getattr(self._link, "take_arrived", None)
        if take is None or self._reader is not None or not isinstance(self._clock, RealClock):
            return False
        await self._clock.sleep(max(wait_s, 0.0))
        taken = take(self._byte_period_s) if self._reader is None else None
        if taken is None:
            return False
        data, chunks = taken
        if not data:
            return True
        self._heard = True
        now_s = self._clock.now_s()
        noted = sum(count for count, _ in chunks)
        if noted < len(data):  # bytes without a note (none on a SerialLink): they came by now
            chunks.append((len(data) - noted, now_s))
        for count, arrived_s in chunks:
            received_s = max(min(arrived_s, now_s), arrivals.last_s)  # the estimate never runs backwards
            self.stats.bytes_received += count
            self.stats.last_receive_s = received_s
            arrivals.add(count, received_s)
        batch += data
        self._undecoded = len(batch)
        return True

    async def _heard_after_all(self) -> bool:
        """True when bytes wait although no sample came for ``no_data_timeout_s``.

        After a stall of the event loop (heavy work, a slow core) the time-out expires
        with the device's bytes still in the link, unread: the reader never had its
        turn. It gets one pass of the loop first (the link's own callbacks run then),
        and only a link with nothing waiting after it is silent.
        """
        if self.bytes_waiting() > 0:
            return True
        await asyncio.sleep(0)
        return self.bytes_waiting() > 0

    def _latest_sample_s(self, arrivals: _ArrivalLog, decided_end: int) -> float:
        """Clock time at which the last sample decoded so far was taken.

        Not the time of decoding (up to ``DECODE_INTERVAL_S`` after the bytes came, so
        ~10-20 ms late on average), but the arrival of the byte that completed it
        (``decided_end`` is the stream offset just after the bytes the decoder has
        decided). In express mode a capsule's samples come out only when the next
        capsule has arrived, and the device sends a capsule once it has measured it, so
        the last sample of the capsule decoded was taken one capsule (32 samples)
        before the byte that released it.
        """
        arrived_s = arrivals.time_of(decided_end - 1)
        fmt = proto.CAPSULE_FORMATS.get(self.active_mode.answer_type)
        if fmt is not None:
            arrived_s -= fmt.samples * self._period_s()
        return arrived_s

    def _period_s(self) -> float:
        """Time per sample: configured, else the active mode's (the device's own figure)."""
        if self._sample_period_s:
            return self._sample_period_s
        return self.active_mode.us_per_sample * 1e-6

    def _new_decoder(self) -> proto.StandardScanDecoder | proto.ExpressScanDecoder:
        """A decoder for a scan that just started (its bytes follow the descriptor)."""
        if self._decoder is not None:  # keep counting what the previous one dropped
            self._dropped_before += self._decoder.bytes_dropped
        decoder = proto.scan_decoder(self.active_mode.answer_type)
        decoder.reset(synced=True)
        self._decoder = decoder
        return decoder

    def _stamp(self, count: int, received_s: float, since_s: float) -> np.ndarray:
        """Clock times of ``count`` samples taken in (``since_s``, ``received_s``].

        The last one is taken at ``received_s`` (see ``_latest_sample_s``) and the others one sample
        period apart before it: the interval's own (its length over ``count``) when that is
        within ``MEASURED_PERIOD_BAND`` of the nominal period, which keeps a long batch's
        early samples where the device took them (a head 1 % slower than nominal puts the
        first of 160 samples 0.8 ms early at the nominal period); otherwise the nominal
        period, or the interval's when more samples came than fit in it at that period (a
        backlog, a device faster than nominal). Stamps are strictly increasing across calls.
        """
        if count <= 0:
            return np.empty(0)
        period_s = self._period_s()
        if received_s > since_s:  # no interval (the first capsules of a scan): nominal spacing
            measured_s = (received_s - since_s) / count
            if abs(measured_s - period_s) <= MEASURED_PERIOD_BAND * period_s:
                period_s = measured_s
            period_s = min(period_s, measured_s)
        i = np.arange(count)
        ideal = received_s - period_s * (count - 1 - i)
        floor = self._last_time_s + 1e-6 * (i + 1)
        times = np.maximum(ideal, floor)
        self._last_time_s = float(times[-1])
        return times

    def to_scan(self, samples: DecodedSamples, time_s: np.ndarray, revolution: int) -> Scan:
        """Device samples -> Scan: robot angles, metres, validity by distance and quality."""
        angle = -np.deg2rad(samples.angle_deg) + self._mount_yaw_rad
        angle_rad = (angle + math.pi) % math.tau - math.pi
        range_m = samples.dist_mm / 1000.0
        valid = (
            (samples.dist_mm > 0)
            & (samples.quality > 0)
            & (range_m >= self._min_range_m)
            & (range_m <= self._max_range_m)
        )
        return Scan(
            angle_rad=angle_rad,
            range_m=range_m,
            quality=samples.quality.astype(np.uint8),
            time_s=np.asarray(time_s, dtype=np.float64),
            valid=valid,
            revolution=revolution,
        )


class SampleRhythm:
    """When the newest sample was taken, by the device's steady sample rate as well as by its bytes' arrival.

    A byte's arrival time is what the host reads it at, corrected for the bytes still
    waiting (``_timed_read``); a process that was not running (a CPU quota's throttle, a
    busy core) reads them late, and every sample it stamps from them is late by as much:
    45 ms at worst in a 16x16 maze at 25 % of a core, 3° of a turn. The device samples at a
    steady rate, though: its n-th sample comes ``period`` after the one before. So the
    newest sample is at most where the rhythm of an earlier, better-timed stamp puts it,
    and an arrival later than that was a late read (the lower envelope of the arrivals, as
    in clock synchronisation). The rhythm may run slow against the host clock by up to
    ``slip`` (the nominal period is not exact: an A1's rotation, and so its rate in the
    simulator, varies 3 % between turns), so the bound moves on by ``(1 + slip)`` periods
    per sample; an arrival earlier than the bound is taken as it is.

    Example::

        rhythm = SampleRhythm()
        rhythm.latest(arrival_s=10.000, samples=100, period_s=0.0005)   # 10.000
        rhythm.latest(arrival_s=10.080, samples=200, period_s=0.0005)   # 10.0525: read 27 ms late
    """

    #: How much slower than its nominal period the device may sample (relative).
    SLIP = 0.05

    def __init__(self) -> None:
        self._anchor: tuple[float, int] | None = None  # (time of the newest sample, samples so far)

    def reset(self) -> None:
        """Forget the rhythm (a new scan, lost bytes: the sample count no longer follows the device's)."""
        self._anchor = None

    def latest(self, arrival_s: float, samples: int, period_s: float) -> float:
        """The time of sample number ``samples`` (counted since the scan began), its bytes' arrival ``arrival_s``."""
        anchor = self._anchor
        if anchor is not None and samples > anchor[1]:
            bound_s = anchor[0] + (samples - anchor[1]) * period_s * (1.0 + self.SLIP)
            arrival_s = min(arrival_s, bound_s)
        self._anchor = (arrival_s, samples)
        return arrival_s


class _ArrivalLog:
    """When the bytes of a scan stream arrived: the clock time of every chunk read.

    ``add`` records a chunk as it is read; ``time_of(offset)`` is the arrival time of
    the chunk holding the byte at that stream offset (chunks wholly before it are
    forgotten: offsets asked for only grow).
    """

    def __init__(self) -> None:
        self._chunks: deque[tuple[int, float]] = deque()  # (stream offset after the chunk, time)
        self.received = 0  # bytes recorded so far
        self.last_s = -math.inf  # the latest arrival time recorded

    def add(self, count: int, time_s: float) -> None:
        if count > 0:
            self.received += count
            self._chunks.append((self.received, time_s))
            self.last_s = max(self.last_s, time_s)

    def time_of(self, offset: int) -> float:
        chunks = self._chunks
        while len(chunks) > 1 and chunks[0][0] <= offset:
            chunks.popleft()
        return chunks[0][1]


class _RevolutionBuilder:
    """Collects samples and cuts them into revolutions at the start flags."""

    def __init__(self, lidar: RPLidar) -> None:
        self._lidar = lidar
        self._samples: list[DecodedSamples] = []
        self._times: list[np.ndarray] = []
        self._count = 0
        self._synced = False  # a start flag was seen: what is collected is a revolution

    def add(self, samples: DecodedSamples, time_s: np.ndarray) -> list[Scan]:
        scans: list[Scan] = []
        starts = np.flatnonzero(samples.start)
        begin = 0
        for s in (int(i) for i in starts):
            if self._synced and (s > begin or self._count):
                self._append(samples.slice(begin, s), time_s[begin:s])
                scans.append(self._emit())
            elif not self._synced:
                self._discard()
            self._synced = True
            begin = s
        if self._synced:
            self._append(samples.slice(begin), time_s[begin:])
        if self._count > MAX_SAMPLES_PER_REVOLUTION:
            log.warning("%s: no start flag in %d samples; cutting the revolution", self._lidar.name, self._count)
            scans.append(self._emit())
        return scans

    def _append(self, samples: DecodedSamples, time_s: np.ndarray) -> None:
        if len(samples):
            self._samples.append(samples)
            self._times.append(time_s)
            self._count += len(samples)

    def _discard(self) -> None:
        self._samples, self._times, self._count = [], [], 0

    def _emit(self) -> Scan:
        samples = DecodedSamples.concat(self._samples)
        times = np.concatenate(self._times) if self._times else np.empty(0)
        self._discard()
        number = self._lidar._revolutions_cut
        self._lidar._revolutions_cut += 1
        return self._lidar.to_scan(samples, times, number)


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__
