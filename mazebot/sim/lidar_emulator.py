"""An RPLidar A1M8 that answers the real serial protocol from a simulated world.

The emulator is the device end of the serial line: it reads request bytes, answers
GET_INFO (model 0x18), GET_HEALTH, GET_SAMPLERATE, SCAN / FORCE_SCAN (5-byte samples),
EXPRESS_SCAN (84-byte legacy capsules), STOP and RESET (with the boot banner the
device prints), ignores the A2's SET_PWM like an A1 does, and streams the samples of
the spinning head (``lidar_samples.SpinningLidar``) while its motor turns. The motor
follows the DTR line as on the A1's USB adapter: DTR cleared = spinning.

Because it speaks bytes, anything that talks to a real A1 can talk to it: the daemon's
own driver over an in-memory stream pair, or a third-party client over a
pseudo-terminal (``mazebot sim lidar``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mazebot.clock import Clock
from mazebot.io import rplidar_protocol as proto
from mazebot.sim.lidar_samples import DeviceSamples, PoseHistory, SpinningLidar, concat

log = logging.getLogger(__name__)

#: A2/A3 motor speed command (payload: u16 PWM); an A1 ignores it, so do we.
CMD_SET_PWM = 0xF0
#: What the A1 prints on its serial line after a RESET (the driver must skip it).
BOOT_BANNER = b"RP LIDAR System.\r\nFirmware Ver 1.29 - rc9, HW Ver 7\r\nModel: 18\r\n"


@dataclass
class EmulatorStats:
    requests: dict[str, int] = field(default_factory=dict)
    samples_sent: int = 0
    bytes_sent: int = 0
    bad_requests: int = 0


class RPLidarEmulator:
    """The device side of an RPLidar A1M8 serial line.

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
        info: proto.DeviceInfo | None = None,
        serial_number: bytes = bytes(range(0x30, 0x40)),
        self_paced: bool = True,
    ) -> None:
        self.head = head
        self.poses = poses
        self.clock = clock
        self.info = info or proto.DeviceInfo(
            model=proto.MODEL_A1M8, firmware_minor=29, firmware_major=1, hardware=7, serial_number=serial_number
        )
        self.health = proto.DeviceHealth(status=0, error_code=0)
        self.motor_on = False
        self.mode: str | None = None  # None (idle), "standard" or "express"
        self.stats = EmulatorStats()
        self._pending: list[DeviceSamples] = []  # express samples waiting to fill a capsule
        self._capsule_start = True
        self._writer: asyncio.StreamWriter | None = None
        #: True: a streaming task of its own sends the samples every SEND_PERIOD_S. False:
        #: the simulator calls ``pump`` from its own tick instead (``SimulatedRobot.attach_lidar``)
        self.self_paced = self_paced
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
            per_rev = self.head.params.samples_per_rev * self.head.params.rev_per_s
            us = max(1, round(1e6 / per_rev))
            self._send_descriptor(writer, proto.SAMPLERATE_DESCRIPTOR)
            self._send(writer, proto.encode_samplerate(proto.SampleRate(standard_us=us, express_us=max(1, us // 2))))
        elif cmd in (proto.CMD_SCAN, proto.CMD_FORCE_SCAN):
            self._start_scan(writer, "standard")
        elif cmd == proto.CMD_EXPRESS_SCAN:
            self._start_scan(writer, "express")
        elif cmd == CMD_SET_PWM:
            pass  # an A2/A3 command; the A1 has no PWM motor control
        else:
            self.stats.bad_requests += 1

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
            self._send(self._writer, BOOT_BANNER)

    def _start_scan(self, writer: asyncio.StreamWriter, mode: str) -> None:
        if self.health.status == proto.HEALTH_ERROR:
            return  # protection stop: the device refuses to scan until RESET
        if mode == "standard":
            self._send_descriptor(writer, proto.SCAN_DESCRIPTOR)
        else:
            self._send_descriptor(writer, proto.EXPRESS_DESCRIPTOR)
        self.mode = mode
        self._pending.clear()
        self._capsule_start = True
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
        samples = self.head.advance(self.clock.now_s(), self.poses)
        data = self.encode(samples)
        if not data:
            return False
        self._send(writer, data)
        return True

    def encode(self, samples: DeviceSamples) -> bytes:
        """Protocol bytes for these samples in the current scan mode."""
        if self.mode == "standard":
            self.stats.samples_sent += len(samples)
            if not len(samples):
                return b""
            return proto.encode_standard_samples(samples.angle_deg, samples.dist_mm, samples.quality, samples.start)
        self._pending.append(samples)
        pending = concat(self._pending)
        n_caps = len(pending) // proto.CAPSULE_SAMPLES
        out = bytearray()
        for k in range(n_caps):
            lo = k * proto.CAPSULE_SAMPLES
            dist = np.minimum(pending.dist_mm[lo : lo + proto.CAPSULE_SAMPLES], 16383)
            out += proto.encode_express_capsule(float(pending.angle_deg[lo]), dist, start=self._capsule_start)
            self._capsule_start = False
        used = n_caps * proto.CAPSULE_SAMPLES
        self.stats.samples_sent += used
        rest = DeviceSamples(*(getattr(pending, f)[used:] for f in
                               ("time_s", "angle_deg", "dist_mm", "quality", "start")))
        self._pending = [rest]
        return bytes(out)
