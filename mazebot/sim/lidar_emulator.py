"""An RPLidar that answers the real serial protocol from a simulated world.

The emulator is the device end of the serial line: it reads request bytes, answers
GET_INFO, GET_HEALTH, GET_SAMPLERATE and GET_LIDAR_CONF (the scan modes of its model,
``mazebot.io.rplidar_models``), SCAN / FORCE_SCAN (5-byte samples), EXPRESS_SCAN in
each mode the model offers (legacy, ultra, dense or ultra-dense capsules at that
mode's sample rate), STOP and RESET (with the boot banner the device prints), ignores
the A2's SET_PWM like an A1 does, and streams the samples of the spinning head
(``lidar_samples.SpinningLidar``) while its motor turns. The motor follows the DTR
line as on the A1's USB adapter: DTR cleared = spinning.

It is no easier than the device: a triangulation head (A series) measures along a
direction that lies behind its raw angle by an offset that grows with the range (up
to 8°), and reports it as the real one does (standard: the angle with the offset
taken off, so angles step irregularly, even backwards; legacy capsules: the 6-bit
field, 0..63 eighths of a degree; ultra: left to the decoder, which derives it from
the range as Slamtec's SDK does).

Because it speaks bytes, anything that talks to a real unit can talk to it: the
daemon's own driver over an in-memory stream pair, or a third-party client over a
pseudo-terminal (``mazebot sim lidar``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import struct
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mazebot.clock import Clock
from mazebot.io import rplidar_protocol as proto
from mazebot.io.rplidar_models import MODELS, LidarModel
from mazebot.sim.lidar_samples import DeviceSamples, PoseHistory, SpinningLidar, concat, tail

log = logging.getLogger(__name__)

#: A2/A3 motor speed command (payload: u16 PWM); an A1 ignores it, so do we.
CMD_SET_PWM = 0xF0


def boot_banner(model: LidarModel) -> bytes:
    """What the unit prints on its serial line after a RESET (the driver must skip it);
    an A1M8 prints "RP LIDAR System. / Firmware Ver 1.29 - rtm, HW Ver 7 / Model: 18"."""
    major, minor = model.firmware
    return (f"RP LIDAR System.\r\nFirmware Ver {major}.{minor:02d} - rtm, HW Ver {model.hardware}\r\n"
            f"Model: {model.model_id:X}\r\n").encode()


#: Capsule kinds the emulator writes, by answer type.
_CAPSULE_WRITERS: dict[int, tuple[int, Callable[..., bytes]]] = {
    proto.TYPE_EXPRESS: (proto.CAPSULE_SAMPLES, proto.encode_express_capsule),
    proto.TYPE_ULTRA: (96, proto.encode_ultra_capsule),
    proto.TYPE_DENSE: (40, proto.encode_dense_capsule),
    proto.TYPE_ULTRA_DENSE: (64, proto.encode_ultra_dense_capsule),
}
_DESCRIPTORS = {
    proto.TYPE_SCAN: proto.SCAN_DESCRIPTOR,
    proto.TYPE_EXPRESS: proto.EXPRESS_DESCRIPTOR,
    proto.TYPE_ULTRA: proto.ULTRA_DESCRIPTOR,
    proto.TYPE_DENSE: proto.DENSE_DESCRIPTOR,
    proto.TYPE_ULTRA_DENSE: proto.ULTRA_DENSE_DESCRIPTOR,
}


def legacy_offset_deg(dist_mm: np.ndarray) -> np.ndarray:
    """The offset a triangulation head reports in a legacy capsule: the geometry's angle
    (the formula Slamtec's SDK applies to ultra capsules, ``ultra_angle_offset_q16``;
    8° far away, about 5-6.5° at 0.5-1 m, what real A1 units send) in eighths of a
    degree, 0..63. No return: the far value."""
    d_q2 = np.where(dist_mm > 0, np.asarray(dist_mm) * 4, 1 << 30).astype(np.int64)
    q3 = np.rint(proto.ultra_angle_offset_q16(d_q2) / 65536 * 8)
    return np.clip(q3, 0, 63) / 8


def standard_offset_deg(dist_mm: np.ndarray) -> np.ndarray:
    """The offset a triangulation head has already taken off a standard sample's angle:
    the geometry's (as ``legacy_offset_deg``) to the standard format's 1/64°, none
    where there is no return (a real A1 reports those at their raw angle)."""
    d_q2 = np.rint(np.asarray(dist_mm) * 4).astype(np.int64)
    q6 = np.clip(np.rint(proto.ultra_angle_offset_q16(d_q2) / 1024), 0, 8 * 64)
    return np.where(np.asarray(dist_mm) > 0, q6 / 64, 0.0)


def ultra_offset_deg(dist_mm: np.ndarray) -> np.ndarray:
    """The offset the SDK derives from an ultra capsule sample's range, in degrees."""
    d_q2 = np.rint(np.asarray(dist_mm) * 4).astype(np.int64)
    return proto.ultra_angle_offset_q16(d_q2) / 65536


@dataclass
class EmulatorStats:
    requests: dict[str, int] = field(default_factory=dict)
    samples_sent: int = 0
    bytes_sent: int = 0
    bad_requests: int = 0
    #: when the first sample of each revolution was measured (the latest ones): the truth the
    #: quota benchmark holds the daemon's time stamps of its revolutions against
    revolution_starts_s: deque[float] = field(default_factory=lambda: deque(maxlen=20_000))


class RPLidarEmulator:
    """The device side of an RPLidar serial line (an A1M8 unless told another model).

    Example::

        emulator = RPLidarEmulator(head, poses, clock)
        await emulator.serve(device_reader, device_writer)   # until the line closes
    """

    #: How often streamed samples are written while scanning. The device sends
    #: continuously, but its USB serial adapter hands bytes to the host in packets;
    #: 20 ms batches (~40 standard samples) are what a host typically reads at once.
    SEND_PERIOD_S = 0.02

    def __init__(
        self,
        head: SpinningLidar,
        poses: PoseHistory,
        clock: Clock,
        *,
        model: LidarModel | None = None,
        info: proto.DeviceInfo | None = None,
        serial_number: bytes = bytes(range(0x30, 0x40)),
        self_paced: bool = True,
    ) -> None:
        self.head = head
        self.poses = poses
        self.clock = clock
        self.model = model or MODELS["a1"]
        major, minor = self.model.firmware
        self.info = info or proto.DeviceInfo(
            model=self.model.model_id, firmware_minor=minor, firmware_major=major, hardware=self.model.hardware,
            serial_number=serial_number,
        )
        self.health = proto.DeviceHealth(status=0, error_code=0)
        self.motor_on = False
        self.mode: proto.ScanModeInfo | None = None  # the scan mode streaming, None when idle
        self.stats = EmulatorStats()
        self._pending: list[DeviceSamples] = []  # express samples waiting to fill a capsule
        self._capsule_start = True
        self._writer: asyncio.StreamWriter | None = None
        #: True: a streaming task of its own sends the samples every SEND_PERIOD_S. False:
        #: the simulator calls ``pump`` from its own tick instead (``SimulatedRobot.attach_lidar``)
        self.self_paced = self_paced
        #: brings the simulated world up to the clock's time (the backend steps the physics):
        #: a self-paced emulator calls it before its head measures, so no sample is taken
        #: from a pose the physics has not reached. Without it, on a slowed virtual CPU the
        #: streaming timer fired after a loop stall before the simulator's tick, and held
        #: the robot's last pose for every sample of the stall (up to 0.26 s of a turn)
        self.world_catch_up: Callable[[], None] | None = None
        # --- fault injection (mazebot.sim.faults): what a sick A1 does on its serial line ---
        #: the device core hangs: it neither answers nor streams (a brown-out, a stuck firmware)
        self.frozen = False
        #: the motor does not turn whatever DTR says (a jammed or unpowered motor): no samples
        self.motor_jammed = False
        #: every byte the device sends goes through this (noise on the line, flipped bits)
        self.line_filter: Callable[[bytes], bytes] | None = None
        #: the next descriptor is cut after this many bytes (then the line carries on)
        self.truncate_next_descriptor: int | None = None

    # --- lines the host controls ----------------------------------------------------

    def set_dtr(self, dtr: bool) -> None:
        """The A1 USB adapter powers the motor while DTR is cleared."""
        on = not dtr
        if on and not self.motor_on:
            self.head.restart(self.clock.now_s())
        self.motor_on = on

    # --- serving --------------------------------------------------------------------

    async def serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Answer requests and stream samples until the host closes the line."""
        self._writer = writer
        streamer = asyncio.create_task(self._stream(writer), name="lidar-emulator-stream") if self.self_paced else None
        buf = bytearray()
        try:
            while True:
                chunk = await reader.read(256)
                if not chunk:
                    return
                if self.frozen:
                    continue  # a hung core hears nothing
                buf += chunk
                self._handle_requests(buf, writer)
                await writer.drain()
        except (ConnectionError, OSError):
            return
        finally:
            if streamer is not None:
                streamer.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await streamer
            self._writer = None

    def _handle_requests(self, buf: bytearray, writer: asyncio.StreamWriter) -> None:
        while buf:
            if buf[0] != proto.SYNC_BYTE:
                # Not a request start: the real device ignores stray bytes.
                del buf[0]
                self.stats.bad_requests += 1
                continue
            try:
                parsed = proto.parse_request(bytes(buf))
            except proto.ProtocolError:
                del buf[0]
                self.stats.bad_requests += 1
                continue
            if parsed is None:
                return  # incomplete: wait for more bytes
            cmd, payload, consumed = parsed
            del buf[:consumed]
            self._answer(cmd, payload, writer)

    def _send(self, writer: asyncio.StreamWriter, data: bytes) -> None:
        if self.line_filter is not None:
            data = self.line_filter(data)
        writer.write(data)
        self.stats.bytes_sent += len(data)

    def _answer(self, cmd: int, payload: bytes, writer: asyncio.StreamWriter) -> None:
        name = proto.COMMAND_NAMES.get(cmd, f"0x{cmd:02X}")
        self.stats.requests[name] = self.stats.requests.get(name, 0) + 1
        if cmd == proto.CMD_STOP:
            self.mode = None
        elif cmd == proto.CMD_RESET:
            self.mode = None
            self.health = proto.DeviceHealth(status=0, error_code=0)
            asyncio.get_running_loop().call_later(0.002, self._send_banner)
        elif cmd == proto.CMD_GET_INFO:
            self._send_descriptor(writer, proto.INFO_DESCRIPTOR)
            self._send(writer, proto.encode_info(self.info))
        elif cmd == proto.CMD_GET_HEALTH:
            self._send_descriptor(writer, proto.HEALTH_DESCRIPTOR)
            self._send(writer, proto.encode_health(self.health))
        elif cmd == proto.CMD_GET_SAMPLERATE:
            rate = proto.SampleRate(standard_us=round(self.model.standard_us), express_us=round(self.model.express_us))
            self._send_descriptor(writer, proto.SAMPLERATE_DESCRIPTOR)
            self._send(writer, proto.encode_samplerate(rate))
        elif cmd == proto.CMD_GET_LIDAR_CONF:
            self._answer_conf(writer, payload)
        elif cmd in (proto.CMD_SCAN, proto.CMD_FORCE_SCAN):
            self._start_scan(writer, self.model.mode(proto.SCAN_MODE_ID_STANDARD))
        elif cmd == proto.CMD_EXPRESS_SCAN:
            # working mode 0 is the legacy express scan of the protocol document (what
            # clients without GET_LIDAR_CONF send); any other is a scan mode id
            working_mode = payload[0] if payload else 0
            ids = {m.id for m in self.model.modes}
            if working_mode == 0:
                legacy = [m for m in self.model.modes if m.answer_type == proto.TYPE_EXPRESS]
                working_mode = legacy[0].id if legacy else self.model.typical_mode
            if working_mode not in ids:
                self.stats.bad_requests += 1
                return  # a mode the unit does not have: it stays silent
            self._start_scan(writer, self.model.mode(working_mode))
        elif cmd == CMD_SET_PWM:
            pass  # an A2/A3 command; the A1 has no PWM motor control
        else:
            self.stats.bad_requests += 1

    def _answer_conf(self, writer: asyncio.StreamWriter, payload: bytes) -> None:
        """GET_LIDAR_CONF: the scan modes of the model (unknown types: no answer)."""
        try:
            conf_type, mode_id = proto.parse_conf_request(payload)
        except proto.ProtocolError:
            self.stats.bad_requests += 1
            return
        if conf_type == proto.CONF_SCAN_MODE_COUNT:
            data = struct.pack("<H", len(self.model.modes))
        elif conf_type == proto.CONF_SCAN_MODE_TYPICAL:
            data = struct.pack("<H", self.model.typical_mode)
        else:
            try:
                data = proto.encode_mode_conf(self.model.mode(mode_id), conf_type)
            except (KeyError, ValueError):
                self.stats.bad_requests += 1
                return
        self._send_descriptor(writer, proto.conf_descriptor(len(data)))
        self._send(writer, proto.encode_conf_answer(conf_type, data))

    def _send_descriptor(self, writer: asyncio.StreamWriter, descriptor: proto.Descriptor) -> None:
        data = descriptor.encode()
        if self.truncate_next_descriptor is not None:
            data, self.truncate_next_descriptor = data[: self.truncate_next_descriptor], None
        self._send(writer, data)

    def protection_stop(self, error_code: int = 0x8001) -> None:
        """The device detects a fault of its own: health "error", scanning stops until RESET."""
        self.health = proto.DeviceHealth(status=proto.HEALTH_ERROR, error_code=error_code)
        self.mode = None

    def _send_banner(self) -> None:
        if self._writer is not None and not self._writer.is_closing():
            self._send(self._writer, boot_banner(self.model))

    def _start_scan(self, writer: asyncio.StreamWriter, mode: proto.ScanModeInfo) -> None:
        if self.health.status == proto.HEALTH_ERROR:
            return  # protection stop: the device refuses to scan until RESET
        self._send_descriptor(writer, _DESCRIPTORS[mode.answer_type])
        self.mode = mode
        self._pending.clear()
        self._capsule_start = True
        self.head.set_samples_per_rev(max(36, round(mode.samples_per_s / self.model.rev_per_s)))
        if not self.model.triangulation or mode.answer_type == proto.TYPE_DENSE:
            self.head.angle_offset = None
        elif mode.answer_type == proto.TYPE_SCAN:
            self.head.angle_offset = standard_offset_deg
        elif mode.answer_type == proto.TYPE_EXPRESS:
            self.head.angle_offset = legacy_offset_deg
        else:
            self.head.angle_offset = ultra_offset_deg
        self.head.restart(self.clock.now_s())

    async def _stream(self, writer: asyncio.StreamWriter) -> None:
        while True:
            await self.clock.sleep(self.SEND_PERIOD_S)
            if self._send_samples(writer):
                with contextlib.suppress(ConnectionError):
                    await writer.drain()

    def pump(self) -> None:
        """Send what the head measured since the last send (the simulator's tick calls this).

        The same step as the streaming task's, without a task and a timer of its own:
        one wake-up of the event loop serves the physics and the lidar, and the samples
        never run ahead of the poses they are measured from. While the host's end is
        full (it stopped reading) nothing is measured, as when the streaming task
        waits in ``drain()``: the head catches up on the next send.
        """
        writer = self._writer
        if writer is None or getattr(writer.transport, "peer_full", False):
            return
        self._send_samples(writer)

    def _send_samples(self, writer: asyncio.StreamWriter) -> bool:
        """One streaming step: measure since the last one and send it; True if bytes went out."""
        if self.mode is None or not self.motor_on or writer.is_closing() or self.frozen:
            return False
        if self.motor_jammed:
            self.head.restart(self.clock.now_s())  # the head stands still: nothing measured
            return False
        if self.self_paced and self.world_catch_up is not None:
            self.world_catch_up()
        samples = self.head.advance(self.clock.now_s(), self.poses)
        if samples.start.any():
            self.stats.revolution_starts_s.extend(samples.time_s[samples.start].tolist())
        data = self.encode(samples)
        if not data:
            return False
        self._send(writer, data)
        return True

    def encode(self, samples: DeviceSamples) -> bytes:
        """Protocol bytes for these samples in the current scan mode."""
        mode = self.mode
        if mode is None:
            return b""
        if mode.answer_type == proto.TYPE_SCAN:
            self.stats.samples_sent += len(samples)
            if not len(samples):
                return b""
            # the device reports the direction it measured along: raw angle minus offset
            angle = samples.angle_deg if samples.offset_deg is None else (samples.angle_deg - samples.offset_deg) % 360
            return proto.encode_standard_samples(angle, samples.dist_mm, samples.quality, samples.start)
        per_capsule, write = _CAPSULE_WRITERS[mode.answer_type]
        top_mm = 16383 if mode.answer_type == proto.TYPE_EXPRESS else 28000
        self._pending.append(samples)
        pending = concat(self._pending)
        n_caps = len(pending) // per_capsule
        out = bytearray()
        for k in range(n_caps):
            lo, hi = k * per_capsule, (k + 1) * per_capsule
            dist = np.minimum(pending.dist_mm[lo:hi], top_mm)
            start_deg = float(pending.angle_deg[lo])  # the raw angle: the decoder interpolates raw angles
            if mode.answer_type == proto.TYPE_EXPRESS:
                comp = None if pending.offset_deg is None else pending.offset_deg[lo:hi]
                out += write(start_deg, dist, comp, start=self._capsule_start)
            else:
                out += write(start_deg, dist, start=self._capsule_start)
            self._capsule_start = False
        used = n_caps * per_capsule
        self.stats.samples_sent += used
        self._pending = [tail(pending, used)]
        return bytes(out)
