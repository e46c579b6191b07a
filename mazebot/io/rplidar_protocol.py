"""The Slamtec RPLidar serial protocol (A1, A2, A3, C1, S2) as pure functions: bytes in, values out.

Why one module of ~1800 lines: it is the whole wire format of one device family, and each
format's encoder and decoder must stay side by side: the emulator writes with the functions the
driver reads with, so a byte layout changed on one side is changed on the other in the same
view. Most of the length is the standard-scan decoder's resynchronisation and the
express-capsule decoders, which share the descriptor, checksum and field helpers above them. If
it grows further, the seam is by answer kind (requests and descriptors; standard samples;
express capsules); it stays whole while the decoders are being tuned for speed.

No port, no asyncio, no clock: the driver (``mazebot.io.rplidar``), the emulator in
``mazebot.sim`` and the ``mazebot lidar decode`` command all share these functions, so
what the emulator writes is byte for byte what the decoder reads, and both follow the
real device (Slamtec "RPLIDAR Interface Protocol and Application Notes", and the
decoders of Slamtec's SDK 2.x: sdk/src/dataunpacker/unpacker/handler_capsules.cpp;
sdk/src/sl_lidar_driver.cpp _waitNode, getLidarConf; layouts in sdk/include/sl_lidar_cmd.h).

Wire formats, in one place::

    request          A5 cmd                                  (cmd < 0x80)
                     A5 cmd size payload... checksum         (cmd >= 0x80; XOR of all before)
    descriptor       A5 5A  u32le(length | mode << 30)  dtype
    standard sample  [q<<2 | !S<<1 | S] [angle_q6 low7 <<1 | C=1] [angle_q6 >> 7] [dist_q2 u16le]
    express capsule  [0xA<<4 | cs&0xF] [0x5<<4 | cs>>4] [start_q6 | S<<15 u16le] 16 x cabin   (0x82)
    cabin            [d1 u16le = dist_mm<<2 | dθ1 bits 4-5] [d2 u16le likewise]
                     [dθ1 bits 0-3 | dθ2 bits 0-3 << 4]
    ultra capsule    sync/checksum, start angle, 32 x u32le [major 12 | predict1 10 | predict2 10]  (0x84)
    dense capsule    sync/checksum, start angle, 40 x u16le distance mm                       (0x85)
    ultra-dense      sync/checksum, u32 time stamp, u16 status, start angle,
                     32 x [2 x u16 quality/distance/scale, u8 quality high nibbles]           (0x86)
    GET_LIDAR_CONF   A5 84 size [u32 type, u16 mode id, reserved] checksum -> type 0x20 answer

Angles are the device's: degrees, clockwise seen from above, 0 at the front mark.
The scan decoders never raise on bad bytes: a serial line that drops or corrupts bytes
is normal life for a lidar, so they resynchronise byte by byte and count what they drop.
"""

from __future__ import annotations

import enum
import struct
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mazebot.errors import ProtocolError as ProtocolError  # re-exported: the emulator catches it from here

# --- requests ------------------------------------------------------------------------

SYNC_BYTE = 0xA5
SYNC_BYTE2 = 0x5A

CMD_STOP = 0x25
CMD_RESET = 0x40
CMD_SCAN = 0x20
CMD_FORCE_SCAN = 0x21
CMD_GET_INFO = 0x50
CMD_GET_HEALTH = 0x52
CMD_GET_SAMPLERATE = 0x59
CMD_EXPRESS_SCAN = 0x82

#: Commands with this bit set carry ``size payload checksum`` after the command byte.
CMD_FLAG_HAS_PAYLOAD = 0x80

#: EXPRESS_SCAN payload for the legacy capsule format: working mode 0, 4 reserved bytes.
EXPRESS_SCAN_PAYLOAD = bytes(5)

COMMAND_NAMES = {
    CMD_STOP: "STOP",
    CMD_RESET: "RESET",
    CMD_SCAN: "SCAN",
    CMD_FORCE_SCAN: "FORCE_SCAN",
    CMD_GET_INFO: "GET_INFO",
    CMD_GET_HEALTH: "GET_HEALTH",
    CMD_GET_SAMPLERATE: "GET_SAMPLERATE",
    CMD_EXPRESS_SCAN: "EXPRESS_SCAN",
}


def _xor(data: bytes | bytearray) -> int:
    return int(np.bitwise_xor.reduce(np.frombuffer(bytes(data), dtype=np.uint8))) if data else 0


def build_request(cmd: int, payload: bytes = b"") -> bytes:
    """The bytes of one request: ``A5 cmd`` or ``A5 cmd size payload checksum``.

    The device tells the two forms apart by bit 7 of ``cmd``, so a payload on a command
    without that bit (or a payload command without payload) could never be understood.
    """
    if not 0 <= cmd <= 0xFF:
        raise ValueError(f"command must be one byte, got {cmd:#x}")
    if not cmd & CMD_FLAG_HAS_PAYLOAD:
        if payload:
            raise ValueError(f"command {cmd:#04x} takes no payload (bit 7 clear), got {len(payload)} bytes")
        return bytes((SYNC_BYTE, cmd))
    if not 0 < len(payload) <= 0xFF:
        raise ValueError(f"command {cmd:#04x} needs a payload of 1..255 bytes, got {len(payload)}")
    head = bytes((SYNC_BYTE, cmd, len(payload))) + payload
    return head + bytes((_xor(head),))


def parse_request(buf: bytes | bytearray) -> tuple[int, bytes, int] | None:
    """Parse the request at the start of ``buf``: ``(cmd, payload, bytes consumed)``.

    Returns None while ``buf`` holds only the beginning of a request (read more and call
    again). Raises ProtocolError when ``buf`` does not start with a request or the
    checksum is wrong; the caller (the emulator) then drops one byte and tries again.
    """
    if not buf:
        return None
    if buf[0] != SYNC_BYTE:
        raise ProtocolError(f"request: expected sync byte 0xa5, found {buf[0]:#04x}")
    if len(buf) < 2:
        return None
    cmd = buf[1]
    if not cmd & CMD_FLAG_HAS_PAYLOAD:
        return cmd, b"", 2
    if len(buf) < 3:
        return None
    size = buf[2]
    end = 3 + size + 1
    if len(buf) < end:
        return None
    expected = _xor(buf[: end - 1])
    if buf[end - 1] != expected:
        raise ProtocolError(
            f"request {cmd:#04x}: expected checksum {expected:#04x}, found {buf[end - 1]:#04x}"
        )
    return cmd, bytes(buf[3 : end - 1]), end


# --- response descriptors ------------------------------------------------------------

DESCRIPTOR_LEN = 7

TYPE_INFO = 0x04
TYPE_HEALTH = 0x06
TYPE_SAMPLERATE = 0x15
TYPE_SCAN = 0x81
TYPE_EXPRESS = 0x82


class SendMode(enum.IntEnum):
    """How many responses follow one descriptor."""

    SINGLE = 0
    MULTIPLE = 1


@dataclass(frozen=True)
class Descriptor:
    """A response descriptor: the 7 bytes the device sends before any response data.

    ``length`` is the size in bytes of one response (of each one, for MULTIPLE mode).
    """

    length: int
    mode: SendMode
    dtype: int

    def __str__(self) -> str:
        return f"length {self.length}, {self.mode.name.lower()}, type {self.dtype:#04x}"

    def encode(self) -> bytes:
        return encode_descriptor(self.length, self.mode, self.dtype)


INFO_DESCRIPTOR = Descriptor(20, SendMode.SINGLE, TYPE_INFO)
HEALTH_DESCRIPTOR = Descriptor(3, SendMode.SINGLE, TYPE_HEALTH)
SAMPLERATE_DESCRIPTOR = Descriptor(4, SendMode.SINGLE, TYPE_SAMPLERATE)
SCAN_DESCRIPTOR = Descriptor(5, SendMode.MULTIPLE, TYPE_SCAN)
EXPRESS_DESCRIPTOR = Descriptor(84, SendMode.MULTIPLE, TYPE_EXPRESS)


def encode_descriptor(length: int, mode: int, dtype: int) -> bytes:
    """``A5 5A`` + 30-bit length and 2-bit send mode in one u32le + data type."""
    if not 0 <= length < 1 << 30:
        raise ValueError(f"descriptor length must fit 30 bits, got {length}")
    if not 0 <= mode <= 3:
        raise ValueError(f"send mode must fit 2 bits, got {mode}")
    if not 0 <= dtype <= 0xFF:
        raise ValueError(f"data type must be one byte, got {dtype:#x}")
    return struct.pack("<BBIB", SYNC_BYTE, SYNC_BYTE2, length | (mode << 30), dtype)


def parse_descriptor(data: bytes | bytearray, expected: Descriptor | None = None) -> Descriptor:
    """Parse the 7 descriptor bytes; with ``expected``, insist on that exact descriptor.

    Raises ProtocolError naming what was expected and what was found, because a wrong
    descriptor means the device answered something else than what was asked (or the
    line is out of step) and no byte after it can be trusted.
    """
    what = f"descriptor ({expected})" if expected is not None else "descriptor"
    if len(data) < DESCRIPTOR_LEN:
        raise ProtocolError(f"expected a 7-byte {what}, found {len(data)} bytes: {bytes(data).hex(' ')}")
    if data[0] != SYNC_BYTE or data[1] != SYNC_BYTE2:
        raise ProtocolError(f"expected {what} starting a5 5a, found {bytes(data[:7]).hex(' ')}")
    (word,) = struct.unpack_from("<I", data, 2)
    mode_bits = word >> 30
    if mode_bits > SendMode.MULTIPLE:
        raise ProtocolError(f"expected {what} with send mode 0 or 1, found mode {mode_bits}")
    found = Descriptor(word & 0x3FFFFFFF, SendMode(mode_bits), data[6])
    if expected is not None and found != expected:
        raise ProtocolError(f"expected descriptor ({expected}), found ({found})")
    return found


# --- single responses ----------------------------------------------------------------

HEALTH_STATUS_NAMES = {0: "good", 1: "warning", 2: "error"}
HEALTH_GOOD = 0
HEALTH_WARNING = 1
HEALTH_ERROR = 2

#: GET_INFO model byte of the A1M8 (high nibble: series A1, low nibble: M8).
MODEL_A1M8 = 0x18


@dataclass(frozen=True)
class DeviceInfo:
    """GET_INFO answer: model, firmware and hardware versions, 16-byte serial number."""

    model: int
    firmware_minor: int
    firmware_major: int
    hardware: int
    serial_number: bytes

    @property
    def model_name(self) -> str:
        """``A1M8`` for model 0x18: series in the high nibble, sub-model in the low one."""
        return f"A{self.model >> 4}M{self.model & 0x0F}"

    @property
    def firmware_version(self) -> str:
        return f"{self.firmware_major}.{self.firmware_minor:02d}"

    @property
    def serial_hex(self) -> str:
        return self.serial_number.hex().upper()


@dataclass(frozen=True)
class DeviceHealth:
    """GET_HEALTH answer: 0 good, 1 warning, 2 error (protection stop) and a code."""

    status: int
    error_code: int

    @property
    def status_name(self) -> str:
        return HEALTH_STATUS_NAMES.get(self.status, f"unknown({self.status})")


@dataclass(frozen=True)
class SampleRate:
    """GET_SAMPLERATE answer: time per sample in microseconds, per scan mode."""

    standard_us: int
    express_us: int


def _need(data: bytes | bytearray, n: int, what: str) -> None:
    if len(data) != n:
        raise ProtocolError(f"{what}: expected {n} bytes, found {len(data)}")


def encode_info(info: DeviceInfo) -> bytes:
    if len(info.serial_number) != 16:
        raise ValueError(f"serial number must be 16 bytes, got {len(info.serial_number)}")
    return (
        bytes((info.model, info.firmware_minor, info.firmware_major, info.hardware))
        + info.serial_number
    )


def parse_info(data: bytes | bytearray) -> DeviceInfo:
    _need(data, INFO_DESCRIPTOR.length, "GET_INFO response")
    return DeviceInfo(data[0], data[1], data[2], data[3], bytes(data[4:20]))


def encode_health(health: DeviceHealth) -> bytes:
    return struct.pack("<BH", health.status, health.error_code)


def parse_health(data: bytes | bytearray) -> DeviceHealth:
    _need(data, HEALTH_DESCRIPTOR.length, "GET_HEALTH response")
    status, code = struct.unpack("<BH", data)
    if status not in HEALTH_STATUS_NAMES:
        raise ProtocolError(f"GET_HEALTH response: expected status 0, 1 or 2, found {status}")
    return DeviceHealth(status, code)


def encode_samplerate(rate: SampleRate) -> bytes:
    return struct.pack("<HH", rate.standard_us, rate.express_us)


def parse_samplerate(data: bytes | bytearray) -> SampleRate:
    _need(data, SAMPLERATE_DESCRIPTOR.length, "GET_SAMPLERATE response")
    std, exp = struct.unpack("<HH", data)
    return SampleRate(std, exp)


# --- decoded samples -----------------------------------------------------------------


@dataclass(frozen=True)
class DecodedSamples:
    """Samples decoded from a scan stream, in device terms (see the module docstring).

    ``dist_mm`` is 0 where the device had no valid return. ``quality`` is 0..63 in
    standard mode; express capsules carry no quality, so it is 1 where the distance is
    valid and 0 where not. ``start`` marks the first sample of a new revolution.
    """

    angle_deg: np.ndarray  # float64, clockwise, [0, 360)
    dist_mm: np.ndarray  # float64
    quality: np.ndarray  # uint8
    start: np.ndarray  # bool

    def __len__(self) -> int:
        return int(self.angle_deg.shape[0])

    @classmethod
    def empty(cls) -> DecodedSamples:
        return cls(
            np.empty(0, np.float64), np.empty(0, np.float64), np.empty(0, np.uint8), np.empty(0, bool)
        )

    @classmethod
    def concat(cls, parts: list[DecodedSamples]) -> DecodedSamples:
        parts = [p for p in parts if len(p)]
        if not parts:
            return cls.empty()
        if len(parts) == 1:
            return parts[0]
        return cls(
            np.concatenate([p.angle_deg for p in parts]),
            np.concatenate([p.dist_mm for p in parts]),
            np.concatenate([p.quality for p in parts]),
            np.concatenate([p.start for p in parts]),
        )

    def slice(self, begin: int, end: int | None = None) -> DecodedSamples:
        s = slice(begin, end)
        return DecodedSamples(self.angle_deg[s], self.dist_mm[s], self.quality[s], self.start[s])


# --- standard scan: 5-byte samples ---------------------------------------------------

STANDARD_SAMPLE_LEN = 5
_FULL_TURN_Q6 = 360 * 64


def encode_standard_samples(
    angle_deg: np.ndarray | list[float],
    dist_mm: np.ndarray | list[float],
    quality: np.ndarray | list[int],
    start: np.ndarray | list[bool],
) -> bytes:
    """Many standard samples at once (the emulator sends ~2000 a second)."""
    angle = np.asarray(angle_deg, dtype=np.float64)
    dist = np.asarray(dist_mm, dtype=np.float64)
    qual = np.asarray(quality, dtype=np.int64)
    flag = np.asarray(start, dtype=bool)
    n = angle.shape[0]
    if not dist.shape[0] == qual.shape[0] == flag.shape[0] == n:
        raise ValueError("angle_deg, dist_mm, quality and start must have the same length")
    if n == 0:
        return b""
    # min/max instead of elementwise masks: the same verdict (NaN passes both ways)
    if qual.min() < 0 or qual.max() > 63:
        raise ValueError("quality must be in 0..63")
    if dist.min() < 0 or dist.max() * 4 > 0xFFFF:
        raise ValueError("dist_mm must be in 0..16383.75")
    angle_q6 = np.rint(angle * 64).astype(np.int64) % _FULL_TURN_Q6
    # Bytes 1-2 are the little-endian u16 (angle_q6 << 1) | check bit, bytes 3-4 the
    # little-endian u16 distance in quarter millimetres: each written as one u16 column.
    out = np.empty((n, STANDARD_SAMPLE_LEN), dtype=np.uint8)
    out[:, 0] = (qual << 2) | np.where(flag, 0b01, 0b10)  # S and its complement in bits 0-1
    out[:, 1:3] = ((angle_q6 << 1) | 1).astype("<u2").view(np.uint8).reshape(n, 2)
    out[:, 3:5] = np.rint(dist * 4).astype("<u2").view(np.uint8).reshape(n, 2)
    return out.tobytes()


def encode_standard_sample(angle_deg: float, dist_mm: float, quality: int, start: bool) -> bytes:
    """One 5-byte standard sample (angle rounded to 1/64°, distance to 1/4 mm)."""
    return encode_standard_samples([angle_deg], [dist_mm], [quality], [start])


def _wrap_deg(x: np.ndarray | float) -> np.ndarray:
    """Angle difference folded into [-180, 180)."""
    return (np.asarray(x) + 180.0) % 360.0 - 180.0


_Rhythm = tuple[float, float, float, float]  # rhythm, loose, gap, exact tolerance (deg)


class StandardScanDecoder:
    """Streaming decoder of a standard (SCAN) response stream into samples.

    Feed it whatever the port delivers; it keeps a partial sample for the next call.
    A sample is well-formed when S != !S, the check bit C is 1 and the angle is below
    360°; where the stream is not, one byte is dropped and the next offset tried.

    Well-formedness alone is weak (about one offset in six of random bytes passes), so
    the decoder also uses what a spinning head guarantees: consecutive samples step by
    a nearly constant angle (the "rhythm": the median of the recent steps). Once there
    is a rhythm, a sample is believed when its step fits the rhythm and the next sample
    confirms it (its step fits too, and the two steps make two rhythm steps). After
    dropped bytes, decoding resumes on a sample that continues the rhythm (inserted
    bytes lose no sample) or on a fresh run of four samples keeping the rhythm (lost
    bytes, a restarted scan). "Loosely" allows the 8° more or less a step takes where a
    triangulation head's range, and with it its angle offset, jumps. A lone sample
    between two stretches of noise is believed when it matches the rhythm to one angle
    unit and nothing nearby matches better.

    A stream without rhythm (synthetic test data, or a head whose angles jitter by more
    than a twentieth of a step) is decoded by form alone; after a resync a run is then
    believed only when it is eight samples long or ends the data.
    Decisions look at most ~110 bytes ahead, so call ``flush()`` at the end of a finite
    stream. Results do not depend on how the stream is cut into ``feed`` calls.

    An embedded scan descriptor (``A5 5A 05 00 00 40 81``, e.g. at the start of a
    captured file or after a restarted scan) is skipped without counting as dropped.

    Example::

        dec = StandardScanDecoder()
        samples = dec.feed(port_bytes)   # DecodedSamples, possibly empty
        dec.bytes_dropped, dec.samples_decoded
    """

    #: A resync may restart on a run of this many samples keeping one rhythm.
    REGULAR_RUN = 4
    #: Without a rhythm, a run is believed only when it is this long (or ends the data).
    LONG_RUN = 8
    #: Steps remembered to estimate the rhythm, and how many it takes at least.
    HISTORY = 8
    MIN_STEPS = 3
    #: Largest plausible step between consecutive samples, degrees.
    MAX_STEP_DEG = 90.0
    #: Steps keep a rhythm when none deviates from their median by more than this
    #: fraction of the step, or MIN_SPREAD_DEG (the angle's 1/64° quantisation).
    #: A head that jitters more is decoded by form alone: never lose real samples.
    MAX_SPREAD = 0.15
    MIN_SPREAD_DEG = 2.0 / 64.0
    #: A plausible step differs from the rhythm by at most max(this, half the rhythm).
    #: A triangulation head reports each standard sample at its raw angle minus an
    #: offset that its range sets anywhere in 0..8° (the geometry the SDK applies to
    #: ultra capsules), so where the range jumps the angle steps up to 8° more or less
    #: than the rhythm: a real A1 goes from 1234 mm at 68° to 315 mm at 72°, from "no
    #: return" at 83° to 320 mm at 79° (tests/io/data/a1_standard_ev3dev_issue85.csv).
    LOOSE_TOLERANCE_DEG = 8.5
    #: Confirmation and resumption after dropped bytes: max(this, a tenth of the rhythm,
    #: four times the spread of the recent steps), degrees.
    GAP_TOLERANCE_DEG = 0.3
    #: A lone sample must match the rhythm to one angle unit (1/64°) or twice the spread.
    EXACT_TOLERANCE_DEG = 1.0 / 64.0 + 1e-9
    #: How far a lone sample looks for a better continuation, bytes.
    LOOKAHEAD_BYTES = 48
    #: Take ``_steady_run``'s shortcut on clean stretches (tests switch it off to compare).
    FAST_PATH = True

    _ACCEPT_CONTINUE, _ACCEPT_FRESH, _AFTER_DESCRIPTOR, _REJECT, _WAIT = range(5)

    def __init__(self) -> None:
        self._tail = b""
        self._synced = False  # the tail starts at a sample boundary (no resync needed)
        self._approved = False  # the judge already accepted the sample at the boundary
        self._adjacent_at = -1  # buffer offset just after the last accepted sample
        self._clean = False  # the last run of samples ended only with the data
        self._last_angle: float | None = None
        self._steps: list[float] = []  # recent steps (deg) of accepted samples
        self._rhythm_cache: _Rhythm | bool | None = False  # False: to be computed
        self._descriptor = SCAN_DESCRIPTOR.encode()
        self._descriptors_at: list[int] = []  # descriptor offsets in the buffer decoded
        self.bytes_dropped = 0
        self.samples_decoded = 0
        self.descriptors_skipped = 0

    def reset(self, *, synced: bool = False) -> None:
        """Forget the stream; ``synced``: the next byte starts a sample (after a descriptor)."""
        self._tail = b""
        self._synced = synced
        self._approved = False
        self._adjacent_at = -1
        self._forget_rhythm()

    def feed(self, data: bytes) -> DecodedSamples:
        """Decode what can be decided now; keep the rest for the next call."""
        return self._decode(self._tail + bytes(data), final=False)

    def flush(self) -> DecodedSamples:
        """End of stream: decide on the kept bytes; an incomplete sample counts as dropped."""
        return self._decode(self._tail, final=True)

    @property
    def pending_bytes(self) -> int:
        """Bytes fed but not decided yet (kept for the next call); the driver's time stamps
        need where in the stream the last decoded sample ended."""
        return len(self._tail)

    # -- the rhythm of the head ------------------------------------------------------

    def _forget_rhythm(self) -> None:
        self._last_angle = None
        self._steps = []
        self._rhythm_cache = False

    def _remember(self, angle: np.ndarray) -> None:
        if self._last_angle is not None:
            angle = np.concatenate([[self._last_angle], angle])
        steps = _wrap_deg(np.diff(angle))[-self.HISTORY :]
        self._steps = (self._steps + [float(s) for s in steps])[-self.HISTORY :]
        self._last_angle = float(angle[-1])
        self._rhythm_cache = False

    def _tolerances(self, m: np.ndarray, spread: np.ndarray) -> tuple[np.ndarray, ...]:
        """(loose, gap, exact) tolerances in degrees for a rhythm and its step spread.

        Gap and exact widen with the spread of the recent steps, so a head that
        jitters more is judged by its own jitter.
        """
        loose = np.maximum(self.LOOSE_TOLERANCE_DEG, 0.5 * np.abs(m))
        gap = np.minimum(loose, np.maximum(np.maximum(self.GAP_TOLERANCE_DEG, 0.1 * m), 4 * spread))
        exact = np.minimum(gap, np.maximum(self.EXACT_TOLERANCE_DEG, 2 * spread))
        return loose, gap, exact

    def _window_rhythm(self, win: np.ndarray) -> tuple[np.ndarray, ...] | None:
        """Per row of recent steps (NaN = none): has a rhythm, rhythm, loose, gap, exact.

        A row has a rhythm when it holds at least MIN_STEPS steps, their median is a
        plausible step and every one of them is close to it. None when no row has
        enough steps.
        """
        count = np.sum(~np.isnan(win), axis=1)
        need = count >= self.MIN_STEPS
        if not np.any(need):
            return None
        m = _row_median(win, count)
        deviation = np.abs(win - m[:, None])
        spread = _row_median(deviation, count)
        loose, gap, exact = self._tolerances(m, spread)
        with np.errstate(invalid="ignore"):
            has = need & (m > 0) & (m <= self.MAX_STEP_DEG)
            # every remembered step close to the median, not just most of them
            worst = np.max(np.where(np.isnan(deviation), 0.0, deviation), axis=1)
            has &= worst <= np.maximum(self.MAX_SPREAD * m, self.MIN_SPREAD_DEG)
        return has, m, loose, gap, exact

    def _full_window_rhythm(self, win: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`_window_rhythm`'s has, rhythm and loose tolerance for rows of ``HISTORY`` steps, none NaN.

        The same arithmetic without what NaN needs (counts, masks): each row's median from
        its sorted steps, the largest deviation the last of the sorted deviations. A read
        of a realistic A1 stream fits ~100 such rows; this is most of its decoding.
        """
        width = win.shape[1]
        lo, hi = (width - 1) // 2, width // 2
        srt = np.sort(win, axis=1)
        m = 0.5 * (srt[:, lo] + srt[:, hi])
        deviation = np.sort(np.abs(win - m[:, None]), axis=1)
        loose = np.maximum(self.LOOSE_TOLERANCE_DEG, 0.5 * np.abs(m))
        has = (m > 0) & (m <= self.MAX_STEP_DEG)
        # every remembered step close to the median, not just most of them
        has &= deviation[:, -1] <= np.maximum(self.MAX_SPREAD * m, self.MIN_SPREAD_DEG)
        return has, m, loose

    def _rhythm(self) -> _Rhythm | None:
        """(rhythm, loose, gap, exact) from the recent accepted steps, if they keep one."""
        if self._rhythm_cache is False:
            fit = self._window_rhythm(np.array([self._steps[-self.HISTORY :]], dtype=np.float64))
            if fit is None or not fit[0][0]:
                self._rhythm_cache = None
            else:
                _, m, loose, gap, exact = fit
                self._rhythm_cache = (float(m[0]), float(loose[0]), float(gap[0]), float(exact[0]))
        return self._rhythm_cache  # type: ignore[return-value]

    def _rhythm_fit(self, angle: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per candidate at consecutive sample boundaries: (plausible, believed).

        Plausible: its step fits the rhythm loosely. Believed: plausible, and the next
        candidate (well-formed per ``ok``) confirms it: its step fits loosely too, and
        the two steps together make two rhythm steps (to half a step, or the gap
        tolerance for a jittery head: noise between two real samples makes one step
        out of two). Without a rhythm everything is both.

        Each candidate is judged against the rhythm of the samples before it as if
        every earlier candidate were accepted; that is exactly the situation of the
        first failing one (the run stops there), so the outcome does not depend on how
        the stream was cut into reads.
        """
        k = angle.shape[0]
        prev = np.empty(k)
        prev[0] = np.nan if self._last_angle is None else self._last_angle
        prev[1:] = angle[:-1]
        step = _wrap_deg(angle - prev)  # step[0] is nan without a previous sample
        h = self.HISTORY
        known = np.array(self._steps[-h:], dtype=np.float64)
        hist = np.concatenate([np.full(h - known.size, np.nan), known, step])
        # window j holds the (up to h) steps accepted before candidate j: the rows of
        # sliding_window_view(hist, h)[:k], gathered (a copy of ~100 x 8 values costs less
        # than the strided view's construction, which dominated a short read's decoding)
        win = hist[np.arange(k)[:, None] + np.arange(h)]
        if known.size == h and self._last_angle is not None:  # every window full: the usual case
            has, m, loose = self._full_window_rhythm(win)
        else:
            fit = self._window_rhythm(win)
            if fit is None:
                everything = np.ones(k, dtype=bool)
                return everything, everything
            has, m, loose, _, _ = fit
        with np.errstate(invalid="ignore"):
            plausible = np.abs(step - m) <= loose
            nxt_step = np.full(k, np.nan)  # the next candidate's step, and the two steps
            nxt_step[:-1] = step[1:]
            two = np.full(k, np.nan)
            two[:-1] = _wrap_deg(angle[1:] - prev[:-1])
            confirmed = (np.abs(nxt_step - m) <= loose) & (np.abs(two - 2 * m) <= np.maximum(0.5 * m, loose))
        confirmed[:-1] &= ok[1:]
        return ~has | plausible, ~has | (plausible & confirmed)

    @classmethod
    def _regular(cls, angles: np.ndarray) -> bool:
        """Do these consecutive angles step with one plausible rhythm (loosely)?"""
        steps = _wrap_deg(np.diff(angles))
        m = float(np.median(steps))
        if not 0.0 < m <= cls.MAX_STEP_DEG:
            return False
        return bool(np.all(np.abs(steps - m) <= max(cls.LOOSE_TOLERANCE_DEG, 0.5 * m)))

    @classmethod
    def _has_regular_window(cls, angles: np.ndarray) -> bool:
        w = cls.REGULAR_RUN
        return any(cls._regular(angles[j : j + w]) for j in range(angles.size - w + 1))

    # -- decoding --------------------------------------------------------------------

    def _decode(self, buf: bytes, final: bool) -> DecodedSamples:
        arr = np.frombuffer(buf, dtype=np.uint8)
        n = len(buf)
        parts: list[DecodedSamples] = []
        pos = 0
        self._descriptors_at = _find_all(buf, self._descriptor)
        fields = _Fields(arr, self._descriptors_at)  # per-offset form, angle and successor
        while True:
            if self._synced:
                taken, end, waiting = self._take_locked(arr, fields, pos, final)
                parts.append(taken)
                if len(taken):
                    pos = end
                    self._adjacent_at = pos
                if waiting or n - pos < STANDARD_SAMPLE_LEN:
                    break
                self._synced = False  # the sample at pos is not believed: resync here
            pos, verdict = self._hunt(buf, fields, pos, final)
            if verdict is None or verdict == self._WAIT:
                break
            self._synced = True
            self._approved = verdict != self._AFTER_DESCRIPTOR
        if final:
            self.bytes_dropped += n - pos
            pos = n
            self._synced = False
        self._adjacent_at = self._adjacent_at - pos if self._adjacent_at >= pos else -1
        self._tail = buf[pos:]
        out = DecodedSamples.concat(parts)
        self.samples_decoded += len(out)
        return out

    def _take_locked(
        self, arr: np.ndarray, fields: _Fields, pos: int, final: bool
    ) -> tuple[DecodedSamples, int, bool]:
        """Accept the run of believed samples at sample boundaries from ``pos``.

        The boundaries are where the device's own reader (the SDK's ``_waitNode``)
        would look for the next sample: right after the previous one, past any bytes
        that cannot start a sample (S == !S). Such bytes may have been inserted by the
        line, but they cannot hide a sample, so skipping them keeps the lock and the
        sample before them is confirmed by the one after them.

        Vectorized: in one block while the stream runs clean (each numpy call has a
        fixed cost), in growing blocks after a break, so that a short run in a long
        buffer costs little. Returns the samples, the offset just after the last one
        taken, and whether the run stopped only for want of the sample that would
        confirm the last one.
        """
        offsets, total = fields.boundaries(pos)
        parts: list[DecodedSamples] = []
        done = 0
        end = pos
        block = total if self._clean else 32
        while done < total:
            size = min(block, total - done)
            look = min(size + 1, offsets.size - done)  # one more, to confirm the block's last
            at = offsets[done : done + look]
            rows = arr[at[:, None] + np.arange(STANDARD_SAMPLE_LEN)]
            ok = fields.ok[at]
            taken, stopped, waiting = self._take_rows(rows, ok, size, done + look == offsets.size and not final)
            parts.append(taken)
            if len(taken):
                end = int(at[len(taken) - 1]) + STANDARD_SAMPLE_LEN
            done += len(taken)
            if stopped:
                self._clean = waiting
                return DecodedSamples.concat(parts), end, waiting
            block = min(block * 4, 4096)
        self._clean = total == offsets.size
        return DecodedSamples.concat(parts), end, False

    def _take_rows(
        self, rows: np.ndarray, ok: np.ndarray, size: int, may_wait: bool
    ) -> tuple[DecodedSamples, bool, bool]:
        """Accept the leading believed samples among the first ``size`` of ``rows``.

        ``ok``: which rows are well-formed (a sample a descriptor cuts short is not).
        Returns (samples, stopped before ``size``, stopped only to await the sample that
        would confirm the last row; only when ``may_wait``).
        """
        k = rows.shape[0]
        angle_q6 = (rows[:, 1].astype(np.int32) >> 1) | (rows[:, 2].astype(np.int32) << 7)
        angle = angle_q6 / 64.0
        fast = None if self._approved or not self.FAST_PATH else self._steady_run(angle, ok, size)
        if fast is not None:
            r = fast
            waiting = may_wait and r == k - 1
        else:
            plausible, believed = self._rhythm_fit(angle, ok)
            if self._approved:  # the judge looked further than this block can
                believed[0] = True
                self._approved = False
            good = ok & believed
            bad = np.flatnonzero(~good[:size])
            r = int(bad[0]) if bad.size else size
            waiting = may_wait and r == k - 1 and bool(ok[r] and plausible[r])
        if r == 0:
            return DecodedSamples.empty(), True, waiting
        rows = rows[:r]
        angle = angle[:r]
        self._remember(angle)
        samples = DecodedSamples(
            angle,
            (rows[:, 3].astype(np.int32) | (rows[:, 4].astype(np.int32) << 8)) / 4.0,
            (rows[:, 0] >> 2).astype(np.uint8),
            (rows[:, 0] & 1).astype(bool),
        )
        return samples, r < size, waiting

    def _steady_run(self, angle: np.ndarray, ok: np.ndarray, size: int) -> int | None:
        """How many leading rows ``_rhythm_fit`` would accept, when that is obvious; else None.

        The common case on a healthy line: every row well-formed and every step, the
        remembered ones included, inside one narrow band ``[lo, hi]``. Then each
        window's median lies in the band and deviates from its steps by at most
        ``hi - lo``, so with ``hi - lo`` within the rhythm's own spread limit
        (``max(MAX_SPREAD * lo, MIN_SPREAD_DEG)``), within ``LOOSE_TOLERANCE_DEG`` and
        within a quarter of ``lo`` (two steps then make two rhythm steps to half a
        step), every window has a rhythm, every step is plausible and every row with
        a successor is confirmed. Only a row without a successor is left out, and only
        when its window already holds ``MIN_STEPS`` steps (otherwise it has no rhythm
        and is believed as it stands). ``_rhythm_fit`` gives the same answer at many
        times the cost (a sorted window per row); tests compare the two on noisy streams.
        """
        if self._last_angle is None or not ok.all():
            return None
        k = angle.shape[0]
        steps = np.empty(k)
        steps[0] = angle[0] - self._last_angle
        steps[1:] = angle[1:] - angle[:-1]
        steps = (steps + 180.0) % 360.0 - 180.0  # _wrap_deg, inlined
        lo, hi = float(steps.min()), float(steps.max())
        if self._steps:
            known = self._steps[-self.HISTORY :]
            lo, hi = min(lo, min(known)), max(hi, max(known))
        band = hi - lo
        if not (lo > 0.0 and hi <= self.MAX_STEP_DEG / 2 and band <= self.LOOSE_TOLERANCE_DEG
                and band <= max(self.MAX_SPREAD * lo, self.MIN_SPREAD_DEG) and 4.0 * band <= lo):
            return None
        if size < k:  # every row up to ``size`` has its confirming successor
            return size
        steps_before_last = min(self.HISTORY, len(self._steps[-self.HISTORY :]) + k - 1)
        return size - 1 if steps_before_last >= self.MIN_STEPS else size

    def _hunt(self, buf: bytes, fields: _Fields, pos: int, final: bool) -> tuple[int, int | None]:
        """Find where samples resume at or after ``pos``; drop the bytes before it.

        Returns (new position, verdict): ACCEPT_* (decode from the new position on),
        AFTER_DESCRIPTOR (a descriptor was skipped), WAIT (more bytes are needed to
        decide at the new position) or None (fewer than 5 bytes left).
        """
        n = len(buf)
        desc = self._descriptor
        cands = fields.candidates
        for q in (int(c) for c in cands[int(np.searchsorted(cands, pos)) :]):
            if buf[q] == SYNC_BYTE and (q + 1 == n or buf[q + 1] == SYNC_BYTE2):
                head = buf[q : q + DESCRIPTOR_LEN]
                if head == desc:
                    self.bytes_dropped += q - pos
                    self.descriptors_skipped += 1
                    self._forget_rhythm()
                    return q + DESCRIPTOR_LEN, self._AFTER_DESCRIPTOR
                if len(head) < DESCRIPTOR_LEN and desc.startswith(head) and not final:
                    # maybe a descriptor: wait for the rest, keeping the bytes before it
                    # that are too few yet to tell whether a sample starts there
                    keep_from = min(q, max(pos, n - (STANDARD_SAMPLE_LEN - 1)))
                    self.bytes_dropped += keep_from - pos
                    return keep_from, self._WAIT
            if fields.ok[q]:
                verdict = self._judge(fields, q, n, final)
                if verdict == self._REJECT:
                    continue
                self.bytes_dropped += q - pos
                if verdict == self._ACCEPT_FRESH:
                    self._forget_rhythm()
                return q, verdict
        # no sample can start before the last 4 bytes: keep those for the next read
        keep_from = max(pos, n - (STANDARD_SAMPLE_LEN - 1))
        self.bytes_dropped += keep_from - pos
        return keep_from, None

    def _judge(self, fields: _Fields, q: int, n: int, final: bool) -> int:
        """Should decoding resume with the well-formed sample at ``q``?"""
        rhythm = self._rhythm()
        if rhythm is not None:
            # does q continue the rhythm across the dropped bytes? (inserted bytes
            # lose no sample, so it is one ordinary step from the last sample)
            _, _, gap, exact = rhythm
            off = self._offset(fields, q, rhythm)
            if off <= gap:
                confirmed = self._confirmed(fields, q, n, rhythm)
                if confirmed is None:  # its confirmation has not arrived yet
                    return self._ACCEPT_CONTINUE if final else self._WAIT
                if confirmed:
                    if self._outdone_by_overlap(fields, q, n, off, rhythm):
                        return self._REJECT
                    return self._ACCEPT_CONTINUE
                if off <= exact:  # a lone sample between stretches of noise?
                    return self._lone_sample(fields, q, n, final, off, rhythm)
        chain, cut = self._chain(fields, q, n, self.LONG_RUN)
        if cut and not final:
            return self._WAIT
        fresh = chain.size >= self.REGULAR_RUN and self._fresh_run(chain[: self.REGULAR_RUN], rhythm)
        # a long run, regular enough: the rhythm changed
        fresh = fresh or (
            chain.size >= self.LONG_RUN and self._regular(chain) and not self._continues(chain[1], rhythm)
        )
        if fresh:
            if rhythm is not None:
                resumed = self._continuation_ahead(fields, q, n, final, rhythm)
                if resumed is None:
                    return self._WAIT
                if resumed:
                    # a fresh run that merges into the old stream a little later is a
                    # stretch of noise that the old stream's tail bytes happen to continue
                    return self._REJECT
            return self._ACCEPT_FRESH
        if self._has_regular_window(chain[1:]):
            return self._REJECT  # regular only after its head: the head is noise
        other_lengths = []
        for p in range(q + 1, q + STANDARD_SAMPLE_LEN):
            if not fields.ok[p]:
                other_lengths.append(0)
                continue
            other, other_cut = self._chain(fields, p, n, self.LONG_RUN)
            if other_cut and not final:
                return self._WAIT
            if self._has_regular_window(other):
                return self._REJECT  # a regular run is nearby at another offset: q is noise
            other_lengths.append(other.size)
        if rhythm is not None:
            return self._REJECT  # a regular stream does not turn irregular
        long_enough = chain.size >= self.LONG_RUN or (final and cut)
        if long_enough and chain.size >= max(other_lengths):
            return self._ACCEPT_FRESH  # an irregular stream: believe the form
        return self._REJECT

    def _outdone_by_overlap(self, fields: _Fields, q: int, n: int, off: float, rhythm: _Rhythm) -> bool:
        """Does a sample overlapping ``q`` continue the rhythm better than ``q`` does?

        Only asked when ``q`` is confirmed across skipped bytes: the last bytes of a
        real sample (distance bits) often cannot start a sample, so a well-formed
        impostor that ends inside the real sample just after it is "confirmed" by the
        real stream too. The real sample matches the rhythm more closely (to its own
        jitter); on a tie the first one wins.
        """
        if fields.next_start[q + STANDARD_SAMPLE_LEN] == q + STANDARD_SAMPLE_LEN:
            return False  # confirmed by the very next bytes: the usual, strong case
        for p in range(q + 1, q + STANDARD_SAMPLE_LEN):
            if fields.ok[p] and self._offset(fields, p, rhythm) < off and self._confirmed(fields, p, n, rhythm):
                return True
        return False

    def _continuation_ahead(self, fields: _Fields, q: int, n: int, final: bool, rhythm: _Rhythm) -> bool | None:
        """Is there, within the lookahead after ``q``, a confirmed continuation of the
        rhythm (what the resync would accept as resumed samples)? None: not known yet."""
        gap = rhythm[2]
        look = self.LOOKAHEAD_BYTES
        if not final and q + look + 2 * STANDARD_SAMPLE_LEN > n:
            return None
        for p in range(q + 1, min(q + look, n - STANDARD_SAMPLE_LEN) + 1):
            if fields.ok[p] and self._offset(fields, p, rhythm) <= gap and self._confirmed(fields, p, n, rhythm):
                return True
        return False

    def _offset(self, fields: _Fields, q: int, rhythm: _Rhythm) -> float:
        """How far the step from the last accepted sample to ``q`` is from the rhythm."""
        assert self._last_angle is not None
        return abs(float(_wrap_deg(fields.angle[q] - self._last_angle)) - rhythm[0])

    def _confirmed(self, fields: _Fields, q: int, n: int, rhythm: _Rhythm) -> bool | None:
        """Does the sample after ``q`` confirm it as the next one? None: not received."""
        assert self._last_angle is not None
        m, loose, _, _ = rhythm
        nxt = int(fields.next_start[q + STANDARD_SAMPLE_LEN])
        if nxt + STANDARD_SAMPLE_LEN > n:
            return None
        step = float(_wrap_deg(fields.angle[nxt] - fields.angle[q]))
        two = float(_wrap_deg(fields.angle[nxt] - self._last_angle))
        return bool(fields.ok[nxt]) and abs(step - m) <= loose and abs(two - 2 * m) <= max(0.5 * m, loose)

    def _lone_sample(self, fields: _Fields, q: int, n: int, final: bool, off: float, rhythm: _Rhythm) -> int:
        """Believe an unconfirmed exact continuation unless a better one follows soon.

        Noise matches the rhythm to one unit now and then, so every candidate within
        ``LOOKAHEAD_BYTES`` that matches as exactly competes with ``q``. Each scores a
        point for: directly following the last accepted sample (no byte dropped in
        between); being confirmed by the sample right after it; being confirmed by a
        sample a little later (noise in between). The most points win, then the
        closest match, then the first.
        """
        look = self.LOOKAHEAD_BYTES
        if not final and q + 2 * look + 2 * STANDARD_SAMPLE_LEN > n:
            return self._WAIT
        exact = rhythm[3]

        def rank(c: int, c_off: float) -> tuple[int, float]:
            points = (
                int(self._adjacent_at >= 0 and c == fields.next_start[self._adjacent_at])
                + int(bool(self._confirmed(fields, c, n, rhythm)))
                + int(self._confirmed_later(fields, c, n, rhythm))
            )
            return points, -c_off

        mine = rank(q, off)
        for p in range(q + 1, min(q + look, n - STANDARD_SAMPLE_LEN) + 1):
            if fields.ok[p]:
                p_off = self._offset(fields, p, rhythm)
                if p_off <= exact and rank(p, p_off) > mine:
                    return self._REJECT
        return self._ACCEPT_CONTINUE

    def _confirmed_later(self, fields: _Fields, c: int, n: int, rhythm: _Rhythm) -> bool:
        """Is there, within the lookahead after ``c``, a sample one step after it?"""
        assert self._last_angle is not None
        m, _, gap, _ = rhythm
        for s in range(c + STANDARD_SAMPLE_LEN, min(c + self.LOOKAHEAD_BYTES, n - STANDARD_SAMPLE_LEN) + 1):
            if not fields.ok[s]:
                continue
            step = float(_wrap_deg(fields.angle[s] - fields.angle[c]))
            two = float(_wrap_deg(fields.angle[s] - self._last_angle))
            if abs(step - m) <= gap and abs(two - 2 * m) <= max(0.5 * m, gap):
                return True
        return False

    def _continues(self, angle: float, rhythm: _Rhythm | None) -> bool:
        """Is ``angle`` one rhythm step after the last accepted sample?"""
        if rhythm is None or self._last_angle is None:
            return False
        return abs(float(_wrap_deg(angle - self._last_angle)) - rhythm[0]) <= rhythm[2]

    def _fresh_run(self, angles: np.ndarray, rhythm: _Rhythm | None) -> bool:
        """May decoding restart on this run of samples (after lost bytes, a restart)?

        Without a rhythm: when it is regular. With one: when it keeps that rhythm to the
        gap tolerance (the head turns as fast after lost bytes as before), and its
        second sample does not simply continue from the last accepted one (then the
        head is noise in front of resumed samples).
        """
        if rhythm is None or self._last_angle is None:
            return self._regular(angles)
        m, _, gap, _ = rhythm
        steps = _wrap_deg(np.diff(angles))
        if not np.all(np.abs(steps - m) <= gap):
            return False
        return not self._continues(float(angles[1]), rhythm)

    @staticmethod
    def _chain(fields: _Fields, q: int, n: int, limit: int) -> tuple[np.ndarray, bool]:
        """Angles of the run of well-formed samples from q, each followed by the next
        at its successor (past bytes that cannot start a sample), at most ``limit``.

        Also says whether the run was cut by the end of the buffer (so more bytes could
        make it longer) rather than by a malformed sample or the limit.
        """
        idx: list[int] = []
        p = q
        while len(idx) < limit:
            if p + STANDARD_SAMPLE_LEN > n:
                return fields.angle[idx], True
            if not fields.ok[p]:
                break
            idx.append(p)
            p = int(fields.next_start[p + STANDARD_SAMPLE_LEN])
        return fields.angle[idx], False


def _find_all(buf: bytes, pattern: bytes) -> list[int]:
    """Offsets of every occurrence of ``pattern`` in ``buf``."""
    found = []
    at = buf.find(pattern)
    while at >= 0:
        found.append(at)
        at = buf.find(pattern, at + 1)
    return found


def _row_median(rows: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Median of the non-NaN values of each row (``count`` of them; 0 where none).

    NaN sorts last, so the known values are the first ``count`` of each sorted row.
    """
    srt = np.sort(rows, axis=1)
    width = rows.shape[1]
    if np.all(count == width):  # the usual case: a full history
        return 0.5 * (srt[:, (width - 1) // 2] + srt[:, width // 2])
    r = np.arange(rows.shape[0])
    lo = srt[r, (np.maximum(count, 1) - 1) // 2]
    hi = srt[r, np.minimum(count // 2, width - 1)]
    return np.where(count > 0, 0.5 * (lo + hi), 0.0)


class _Fields:
    """For every byte offset of a buffer: is a well-formed sample there, its angle, and
    where the next sample could start.

    A sample that a descriptor (at the offsets ``descriptors``) cuts short is not
    well-formed, however good its first bytes look.

    ``next_start[i]`` is the first offset at or after ``i`` whose byte could start a
    sample (S != !S), ``n`` and beyond where none does: the successor of a sample at
    ``q`` is at ``next_start[q + 5]``, as the SDK's byte-by-byte reader (``_waitNode``
    in sl_lidar_driver.cpp) skips every byte whose two sync bits agree.

    ``candidates`` are the offsets where a resync could stop: well-formed samples and
    0xA5 bytes (a descriptor may start there).
    """

    def __init__(self, arr: np.ndarray, descriptors: list[int]) -> None:
        n = arr.shape[0]
        self.n = n
        pad = n + 2 * STANDARD_SAMPLE_LEN
        self.ok = np.zeros(pad, dtype=bool)
        self.angle = np.zeros(pad)
        b = arr.astype(np.int32)
        can = (b & 1) != ((b >> 1) & 1)
        self.can_start = np.zeros(pad, dtype=bool)
        self.can_start[:n] = can
        idx = np.full(pad, n, dtype=np.int64)
        idx[:n] = np.where(can, np.arange(n), n)
        self.next_start = np.minimum.accumulate(idx[::-1])[::-1]
        self.next_start[n:] = np.arange(n, pad)
        if n >= STANDARD_SAMPLE_LEN:
            b1 = b[1 : n - 3]
            angle_q6 = (b1 >> 1) | (b[2 : n - 2] << 7)
            ok = can[: n - 4] & ((b1 & 1) == 1) & (angle_q6 < _FULL_TURN_Q6)
            self.ok[: n - 4] = ok
            self.angle[: n - 4] = angle_q6 / 64.0
            for d in descriptors:  # a sample cut short by a descriptor is no sample
                self.ok[max(0, d - STANDARD_SAMPLE_LEN + 1) : d] = False
        self.candidates = np.flatnonzero(self.ok[:n] | (arr == SYNC_BYTE))

    def boundaries(self, pos: int) -> tuple[np.ndarray, int]:
        """Offsets of the samples a locked reader meets from ``pos``, and how many of
        them it may accept.

        The acceptable ones follow each other 5 bytes apart, all well-formed. After them
        comes the sample that judges the last one (its confirmation): the malformed one
        that ends the run, or, where the run ends at bytes that cannot start a sample,
        the sample after those bytes. The reader stops there either way: after skipped
        bytes it is the resynchronisation that decides, more strictly, whether samples
        resume (see ``StandardScanDecoder._judge``).
        """
        n = self.n
        parts = []
        p = pos
        chunk = 64
        while p + STANDARD_SAMPLE_LEN <= n:
            k = min((n - p) // STANDARD_SAMPLE_LEN, chunk)
            at = p + STANDARD_SAMPLE_LEN * np.arange(k)
            stop = np.flatnonzero(~self.ok[at])
            if stop.size:
                first = int(at[stop[0]])
                parts.append(at[: int(stop[0])])
                accept = sum(x.size for x in parts)
                judge = first if self.can_start[first] else int(self.next_start[first])
                if accept and judge + STANDARD_SAMPLE_LEN <= n:
                    parts.append(np.array([judge]))
                return np.concatenate(parts), accept
            parts.append(at)
            p += STANDARD_SAMPLE_LEN * k
            chunk = min(chunk * 4, 1 << 16)
        if not parts:
            return np.empty(0, dtype=np.int64), 0
        out = np.concatenate(parts)
        return out, out.size


# --- express scan: 84-byte capsules (legacy format) ----------------------------------

CAPSULE_LEN = 84
CAPSULE_SAMPLES = 32
_CABINS = 16
_SYNC_NIBBLE_1 = 0xA
_SYNC_NIBBLE_2 = 0x5
_START_FLAG = 0x8000
#: The compensation field is 6 bits, unsigned: 0..63 eighths of a degree (0..7.875°).
_MAX_COMPENSATION_Q3 = 63
_MAX_EXPRESS_DIST_MM = (1 << 14) - 1


def encode_express_capsule(
    start_angle_deg: float,
    dists_mm: np.ndarray | list[float],
    compensation_deg: np.ndarray | list[float] | None = None,
    *,
    start: bool = False,
) -> bytes:
    """One 84-byte express capsule of 32 samples.

    A decoder gives sample ``i`` the angle ``start + i * (next_start - start) / 32 -
    compensation[i]``, where ``next_start`` is the start angle of the *next* capsule, so
    an emulator that takes its 32 samples evenly between two capsule start angles needs
    no compensation (the default). ``start`` marks the first capsule after EXPRESS_SCAN.

    The compensation covers the field's whole range, 0..7.875° (q3 values 0..63),
    read unsigned and subtracted as Slamtec's SDK does. (The datasheet's signed
    reading and the ``rplidar`` Python package's sign-and-magnitude reading agree with
    the SDK only below 4°; a real A1 sends 5-6.5° for walls 0.5-1 m away.)
    Distances are whole millimetres, 0..16383.
    """
    dist = np.rint(np.asarray(dists_mm, dtype=np.float64)).astype(np.int64)
    if dist.shape != (CAPSULE_SAMPLES,):
        raise ValueError(f"an express capsule holds {CAPSULE_SAMPLES} distances, got {dist.shape}")
    if np.any((dist < 0) | (dist > _MAX_EXPRESS_DIST_MM)):
        raise ValueError(f"express distances must be in 0..{_MAX_EXPRESS_DIST_MM} mm")
    if compensation_deg is None:
        comp = np.zeros(CAPSULE_SAMPLES, dtype=np.int64)
    else:
        comp = np.rint(np.asarray(compensation_deg, dtype=np.float64) * 8).astype(np.int64)
        if comp.shape != (CAPSULE_SAMPLES,):
            raise ValueError(f"an express capsule holds {CAPSULE_SAMPLES} compensations, got {comp.shape}")
        if np.any((comp < 0) | (comp > _MAX_COMPENSATION_Q3)):
            raise ValueError("express angle compensation must be in 0..7.875 degrees")
    start_q6 = round(start_angle_deg * 64) % _FULL_TURN_Q6
    word = np.empty(CAPSULE_SAMPLES, dtype=np.int64)
    word[:] = (dist << 2) | ((comp >> 4) & 0x3)
    cabins = np.empty((_CABINS, 5), dtype=np.uint8)
    d1, d2 = word[0::2], word[1::2]
    cabins[:, 0] = d1 & 0xFF
    cabins[:, 1] = d1 >> 8
    cabins[:, 2] = d2 & 0xFF
    cabins[:, 3] = d2 >> 8
    cabins[:, 4] = (comp[0::2] & 0xF) | ((comp[1::2] & 0xF) << 4)
    body = struct.pack("<H", start_q6 | (_START_FLAG if start else 0)) + cabins.tobytes()
    cs = _xor(body)
    return bytes(((_SYNC_NIBBLE_1 << 4) | (cs & 0xF), (_SYNC_NIBBLE_2 << 4) | (cs >> 4))) + body


def express_compensation_deg(
    start_angle_deg: float, next_start_angle_deg: float, angles_deg: np.ndarray | list[float]
) -> np.ndarray:
    """The compensation that makes a capsule decode to ``angles_deg`` (32 values).

    Raises ValueError when an angle is not within 0..7.875° before its interpolated
    position (what the 6-bit field can carry, see ``encode_express_capsule``).
    """
    angles = np.asarray(angles_deg, dtype=np.float64)
    if angles.shape != (CAPSULE_SAMPLES,):
        raise ValueError(f"an express capsule holds {CAPSULE_SAMPLES} angles, got {angles.shape}")
    s = round(start_angle_deg * 64) % _FULL_TURN_Q6 / 64.0
    e = round(next_start_angle_deg * 64) % _FULL_TURN_Q6 / 64.0
    diff = (e - s) % 360.0
    interp = s + np.arange(CAPSULE_SAMPLES) * diff / CAPSULE_SAMPLES
    comp = np.asarray(_wrap_deg(interp - angles))
    if np.any(comp < -1e-9) or np.any(comp > _MAX_COMPENSATION_Q3 / 8 + 1e-9):
        raise ValueError("express sample angles must lie 0..7.875 degrees before their interpolated angle")
    return np.clip(comp, 0.0, _MAX_COMPENSATION_Q3 / 8)


def _sdk_sync_bits(raw_q16: np.ndarray, inc_q16: np.ndarray) -> np.ndarray:
    """The SDK's revolution flag of each capsule sample (m x n raw angles -> flat bools).

    As in ``_onScanNodeCapsuleData`` (handler_capsules.cpp): a sample is flagged when
    the raw angle of the sample after it, ``raw + inc``, has wrapped past 360°, i.e.
    ``(raw + inc) mod 360° < inc``. The flagged sample is the last one before 0° of
    the uncompensated sweep, and the SDK starts its new revolution with it.
    """
    nxt = (raw_q16 + inc_q16[:, None]) % (360 << 16)
    return (nxt < inc_q16[:, None]).reshape(-1)


def _capsules_valid(rows: np.ndarray) -> np.ndarray:
    """Per 84-byte row: both sync nibbles and the checksum of bytes 2..83 match."""
    cs = np.bitwise_xor.reduce(rows[:, 2:], axis=1)
    recv = (rows[:, 0] & 0x0F) | ((rows[:, 1] & 0x0F) << 4)
    return (rows[:, 0] >> 4 == _SYNC_NIBBLE_1) & (rows[:, 1] >> 4 == _SYNC_NIBBLE_2) & (cs == recv)


def _start_word(rows: np.ndarray, at: int = 2) -> np.ndarray:
    return rows[:, at].astype(np.int64) | (rows[:, at + 1].astype(np.int64) << 8)


def _legacy_unpack(prev: np.ndarray, cur: np.ndarray, carry: dict[str, int]) -> tuple[np.ndarray, ...]:
    """Legacy express capsules (answer type 0x82) ``prev`` interpolated up to ``cur``:
    angle_q6, dist_q2, quality (1 where a distance, as the SDK's 0x2F), SDK sync bits."""
    del carry  # nothing carries over from capsule to capsule
    angle_q6, dist_q2, raw, inc = _decode_capsule_pairs(prev, cur)
    dist = dist_q2.reshape(-1)
    return angle_q6.reshape(-1), dist, (dist > 0).astype(np.uint8), _sdk_sync_bits(raw, inc)


def _decode_capsule_pairs(prev: np.ndarray, cur: np.ndarray) -> tuple[np.ndarray, ...]:
    """Samples of the capsules ``prev`` (m x 84), each interpolated up to ``cur``'s start.

    Follows the SDK's fixed-point arithmetic (q8 start angles, q16 interpolation, q6
    result) so this decoder and the SDK agree to the last bit on the angle.
    Returns angle_q6, dist_q2, raw interpolated angle q16 (m x 32 each; not wrapped)
    and the q16 increment per sample (m).
    """
    prev_q8 = (_start_word(prev) & 0x7FFF) << 2
    cur_q8 = (_start_word(cur) & 0x7FFF) << 2
    diff_q8 = cur_q8 - prev_q8
    diff_q8 = np.where(prev_q8 > cur_q8, diff_q8 + (360 << 8), diff_q8)
    inc_q16 = diff_q8 << 3
    i = np.arange(CAPSULE_SAMPLES, dtype=np.int64)
    raw_q16 = (prev_q8 << 8)[:, None] + inc_q16[:, None] * i[None, :]
    cab = prev[:, 4:].reshape(-1, _CABINS, 5).astype(np.int64)
    word = np.empty((prev.shape[0], CAPSULE_SAMPLES), dtype=np.int64)
    word[:, 0::2] = cab[:, :, 0] | (cab[:, :, 1] << 8)
    word[:, 1::2] = cab[:, :, 2] | (cab[:, :, 3] << 8)
    low = np.empty_like(word)
    low[:, 0::2] = cab[:, :, 4] & 0xF
    low[:, 1::2] = cab[:, :, 4] >> 4
    # The 6-bit compensation is unsigned and subtracted, as in the SDK (Slamtec
    # rplidar_sdk, sdk/src/dataunpacker/unpacker/handler_capsules.cpp,
    # UnpackerHandler_CapsuleNode::_onScanNodeCapsuleData; sl_lidar_driver.cpp
    # _capsuleToNormal in SDK 2.0): a real A1 reports 40-52 (5-6.5°) for walls at
    # 0.5-1 m, which a signed reading would turn into -3..-1.5°.
    comp_q3 = low | ((word & 0x3) << 4)
    angle_q6 = ((raw_q16 - (comp_q3 << 13)) >> 10) % _FULL_TURN_Q6
    return angle_q6, word & 0xFFFC, raw_q16, inc_q16


class ExpressScanDecoder:
    """Streaming decoder of an EXPRESS_SCAN (legacy capsule) response stream.

    A capsule is believed when its sync nibbles (0xA, 0x5) and its checksum match
    (a 1 in 65536 chance for random bytes); otherwise one byte is dropped and the next
    offset tried. As on the device's SDK, a capsule's 32 samples are interpolated
    between its start angle and the next capsule's, so they come out only when the
    next valid capsule arrives; a capsule followed by dropped bytes, by a capsule with
    the start flag (a new scan), or by the end of the stream is discarded
    (``capsules_discarded``). Capsules carry no revolution flag: ``start`` is set as
    the SDK sets it, on the last sample before the uncompensated sweep passes 360°.

    Example::

        dec = ExpressScanDecoder()
        samples = dec.feed(port_bytes)
    """

    def __init__(self, capsule_format: CapsuleFormat | None = None) -> None:
        self.format = capsule_format or LEGACY_CAPSULE
        self._length = self.format.length
        self._tail = b""
        self._synced = False
        self._pending: np.ndarray | None = None  # last valid capsule, waiting for the next
        self._carry: dict[str, int] = {}  # the SDK's state carried from sample to sample
        self.bytes_dropped = 0
        self.samples_decoded = 0
        self.capsules_decoded = 0
        self.capsules_discarded = 0
        self.descriptors_skipped = 0
        self._descriptor = self.format.descriptor.encode()

    def reset(self, *, synced: bool = False) -> None:
        """Forget the stream; ``synced``: the next byte starts a capsule."""
        self._tail = b""
        self._synced = synced
        self._carry = {}
        self._break()

    def _break(self) -> None:
        if self._pending is not None:
            self.capsules_discarded += 1
        self._pending = None

    def feed(self, data: bytes) -> DecodedSamples:
        return self._decode(self._tail + bytes(data), final=False)

    def flush(self) -> DecodedSamples:
        """End of stream: the kept bytes are dropped, the last capsule discarded."""
        out = self._decode(self._tail, final=True)
        self._break()
        return out

    @property
    def pending_bytes(self) -> int:
        """Bytes fed but not decoded yet: a partial capsule, or the start of a resync.

        The capsule waiting for its successor (its samples need the next start angle)
        is not counted: its bytes were decided, its samples come out with the next one.
        """
        return len(self._tail)

    def _decode(self, buf: bytes, final: bool) -> DecodedSamples:
        arr = np.frombuffer(buf, dtype=np.uint8)
        n = len(buf)
        pos = 0
        parts: list[DecodedSamples] = []
        while True:
            if self._synced:
                size = self._length
                k = (n - pos) // size
                if k > 0:
                    rows = arr[pos : pos + k * size].reshape(k, size)
                    bad = np.flatnonzero(~_capsules_valid(rows))
                    r = int(bad[0]) if bad.size else k
                    if r:
                        parts.append(self._emit(rows[:r]))
                        pos += r * size
                    if r < k:
                        self._synced = False
                if self._synced:
                    break
            pos, found = self._hunt(buf, arr, pos, final)
            if not found:
                break
            self._synced = True
        if final:
            self.bytes_dropped += n - pos
            pos = n
            self._synced = False
        self._tail = buf[pos:]
        out = DecodedSamples.concat(parts)
        self.samples_decoded += len(out)
        return out

    def _hunt(self, buf: bytes, arr: np.ndarray, pos: int, final: bool) -> tuple[int, bool]:
        """Drop bytes up to the next valid capsule (or descriptor); True when found."""
        n = len(buf)
        desc = self._descriptor
        if n - pos >= 2:
            hi = arr[pos:] >> 4
            cands = np.flatnonzero((hi[:-1] == _SYNC_NIBBLE_1) & (hi[1:] == _SYNC_NIBBLE_2)) + pos
        else:
            cands = np.empty(0, dtype=np.int64)
        for q in (int(c) for c in cands):
            head = buf[q : q + DESCRIPTOR_LEN]
            if head == desc:
                self._drop(q - pos)
                self.descriptors_skipped += 1
                self._break()
                return q + DESCRIPTOR_LEN, True
            if q + self._length > n:
                if final:
                    continue
                self._drop(q - pos)  # maybe a capsule: wait for the rest of it
                return q, False
            if _capsules_valid(arr[q : q + self._length][None, :])[0]:
                self._drop(q - pos)
                return q, True
        # no candidate: keep a last byte that could begin a capsule
        keep = 1 if (n > pos and arr[n - 1] >> 4 == _SYNC_NIBBLE_1 and not final) else 0
        self._drop(n - keep - pos)
        return n - keep, False

    def _drop(self, count: int) -> None:
        if count > 0:
            self.bytes_dropped += count
            self._break()

    def _emit(self, rows: np.ndarray) -> DecodedSamples:
        """Samples of every capsule that now has a successor, from contiguous ``rows``."""
        if self._pending is not None:
            rows = np.concatenate([self._pending[None, :], rows])
        fmt = self.format
        opens_scan = (_start_word(rows, fmt.start_at) & _START_FLAG) != 0
        # capsule j is decoded with j+1, unless j+1 opens a new scan (then j is lost)
        idx = np.flatnonzero(~opens_scan[1:])
        self.capsules_discarded += int(np.count_nonzero(opens_scan[1:]))
        self._pending = rows[-1].copy()
        if idx.size == 0:
            return DecodedSamples.empty()
        angle_q6, dist_q2, quality, start = fmt.unpack(rows[idx], rows[idx + 1], self._carry)
        self.capsules_decoded += idx.size
        dist = dist_q2 / 4.0
        return DecodedSamples(angle_q6 / 64.0, dist, quality, start)


# --- the other capsule kinds: ultra (A2/A3/A1 boost), dense (C1/S2), ultra-dense -----
#
# Each follows one handler of Slamtec's SDK 2.x, sdk/src/dataunpacker/unpacker/
# handler_capsules.cpp (vendored in Slamtec/rplidar_ros), with the layouts of
# sdk/include/sl_lidar_cmd.h. All of them, like the legacy capsule, carry a start
# angle and are interpolated up to the next capsule's start angle, checksummed by the
# XOR of every byte after the two sync bytes, and flagged with bit 15 of the start
# angle word when they open a scan.

TYPE_ULTRA = 0x84
TYPE_DENSE = 0x85
TYPE_ULTRA_DENSE = 0x86
TYPE_LIDAR_CONF = 0x20

ULTRA_DESCRIPTOR = Descriptor(132, SendMode.MULTIPLE, TYPE_ULTRA)
DENSE_DESCRIPTOR = Descriptor(84, SendMode.MULTIPLE, TYPE_DENSE)
ULTRA_DENSE_DESCRIPTOR = Descriptor(170, SendMode.MULTIPLE, TYPE_ULTRA_DENSE)

_Unpack = Callable[[np.ndarray, np.ndarray, dict[str, int]], tuple[np.ndarray, ...]]


@dataclass(frozen=True)
class CapsuleFormat:
    """One capsule kind: its answer type, size, samples, where its start angle sits,
    and the SDK's recipe turning a capsule and its successor into samples."""

    name: str
    descriptor: Descriptor
    samples: int
    start_at: int  # byte offset of the start angle word (bit 15: opens a scan)
    unpack: _Unpack

    @property
    def length(self) -> int:
        return self.descriptor.length

    @property
    def answer_type(self) -> int:
        return self.descriptor.dtype


def _interpolated(
    prev: np.ndarray, cur: np.ndarray, start_at: int, inc_num: int, inc_den: int, n: int
) -> tuple[np.ndarray, np.ndarray]:
    """The SDK's raw angles (q16, not wrapped) of the n samples of each capsule ``prev``
    and the increment per sample: the angle from ``prev``'s start to ``cur``'s, q8,
    wrapped once, times ``inc_num`` over ``inc_den`` (C integer division)."""
    prev_q8 = (_start_word(prev, start_at) & 0x7FFF) << 2
    cur_q8 = (_start_word(cur, start_at) & 0x7FFF) << 2
    diff_q8 = cur_q8 - prev_q8
    diff_q8 = np.where(prev_q8 > cur_q8, diff_q8 + (360 << 8), diff_q8)
    inc_q16 = (diff_q8 * inc_num) // inc_den
    raw_q16 = (prev_q8 << 8)[:, None] + inc_q16[:, None] * np.arange(n, dtype=np.int64)[None, :]
    return raw_q16, inc_q16


# -- ultra capsules (answer type 0x84): 32 cabins of 3 samples, 132 bytes --------------

#: The SDK's variable bit scale (sl_lidar_cmd.h SL_LIDAR_VARBITSCALE_*): a 12-bit major
#: distance above each threshold counts 2, 4, 8, 16 mm a unit.
_VBS_SCALED_BASE = (3328, 1792, 1280, 512, 0)
_VBS_LEVEL = (4, 3, 2, 1, 0)
_VBS_TARGET_BASE = (1 << 14, 1 << 12, 1 << 11, 1 << 9, 0)


def _varbitscale_decode(scaled: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distance mm, scale level) of 12-bit scaled majors (SDK ``_varbitscale_decode``)."""
    dist = np.zeros_like(scaled)
    level = np.zeros_like(scaled)
    done = np.zeros(scaled.shape, dtype=bool)
    for base, lvl, target in zip(_VBS_SCALED_BASE, _VBS_LEVEL, _VBS_TARGET_BASE, strict=True):
        here = ~done & (scaled >= base)
        dist = np.where(here, target + ((scaled - base) << lvl), dist)
        level = np.where(here, lvl, level)
        done |= here
    return dist, level


def _varbitscale_encode(dist_mm: np.ndarray) -> np.ndarray:
    """The 12-bit scaled major that decodes closest below ``dist_mm`` (inverse of the above)."""
    d = np.asarray(dist_mm, dtype=np.int64)
    out = np.zeros_like(d)
    done = np.zeros(d.shape, dtype=bool)
    for base, lvl, target in zip(_VBS_SCALED_BASE, _VBS_LEVEL, _VBS_TARGET_BASE, strict=True):
        here = ~done & (d >= target)
        out = np.where(here, np.minimum(base + ((d - target) >> lvl), 0xFFF), out)
        done |= here
    return out


def _sign10(x: np.ndarray) -> np.ndarray:
    return np.where(x >= 512, x - 1024, x)


def ultra_angle_offset_q16(dist_q2: np.ndarray) -> np.ndarray:
    """The angle an ultra capsule sample lies behind its raw angle, degrees q16.

    The SDK (``_onScanNodeUltraCapsuleData``) derives it from the range, as the
    triangulation geometry has it: 7.5° in radians q16 below 50 mm, otherwise
    8° - (k << 6) - k³ / 98304 with k = 98361 / dist_q2 (C integer arithmetic), then
    converted to degrees q16 with the SDK's own constants.
    """
    d = np.asarray(dist_q2, dtype=np.int64)
    k = 98361 // np.maximum(d, 1)
    near = int(7.5 * 3.1415926535 * (1 << 16) / 180.0)
    far = int(8 * 3.1415926535 * (1 << 16) / 180) - (k << 6) - (k * k * k) // 98304
    rad_q16 = np.where(d >= 50 * 4, far, near)
    return np.trunc(rad_q16 * 180 / 3.14159265).astype(np.int64)


def _ultra_unpack(prev: np.ndarray, cur: np.ndarray, carry: dict[str, int]) -> tuple[np.ndarray, ...]:
    """SDK ``UnpackerHandler_UltraCapsuleNode::_onScanNodeUltraCapsuleData``."""
    del carry
    m = prev.shape[0]
    raw, inc = _interpolated(prev, cur, 2, 8, 3, 96)  # (diff << 3) / 3
    cab = prev[:, 4:].reshape(m, 32, 4).astype(np.int64)
    word = cab[:, :, 0] | (cab[:, :, 1] << 8) | (cab[:, :, 2] << 16) | (cab[:, :, 3] << 24)
    major = word & 0xFFF
    predict1 = _sign10((word >> 12) & 0x3FF)
    predict2 = _sign10((word >> 22) & 0x3FF)
    first_next = (cur[:, 4].astype(np.int64) | (cur[:, 5].astype(np.int64) << 8)) & 0xFFF
    major2 = np.concatenate([major[:, 1:], first_next[:, None]], axis=1)  # "prefetch next"
    dist1, lvl1 = _varbitscale_decode(major)
    dist2, lvl2 = _varbitscale_decode(major2)
    base1 = np.where((dist1 == 0) & (dist2 != 0), dist2, dist1)
    lvl1 = np.where((dist1 == 0) & (dist2 != 0), lvl2, lvl1)
    d = np.empty((m, 32, 3), dtype=np.int64)
    d[:, :, 0] = dist1 << 2
    invalid1 = (predict1 == -512) | (predict1 == 511)
    invalid2 = (predict2 == -512) | (predict2 == 511)
    d[:, :, 1] = np.where(invalid1, 0, ((predict1 << lvl1) + base1) << 2)
    d[:, :, 2] = np.where(invalid2, 0, ((predict2 << lvl2) + dist2) << 2)
    dist_q2 = d.reshape(m, 96)
    angle_q6 = ((raw - ultra_angle_offset_q16(dist_q2)) >> 10) % _FULL_TURN_Q6
    dist = dist_q2.reshape(-1)
    return angle_q6.reshape(-1), dist, (dist > 0).astype(np.uint8), _sdk_sync_bits(raw, inc)


def encode_ultra_capsule(start_angle_deg: float, dists_mm: np.ndarray | list[float], *, start: bool = False) -> bytes:
    """One 132-byte ultra capsule of 96 samples (32 cabins of a 12-bit major and two
    10-bit signed predictions, each relative to its own major or the next cabin's).

    The decoder puts sample ``i`` at ``start + i * (next_start - start) / 96`` minus the
    range-dependent offset of ``ultra_angle_offset_q16``. Distances are rounded to
    what the variable bit scale can carry; a prediction out of its 10 bits, or a
    sample without return, becomes 0 (no return).
    """
    dist = np.rint(np.asarray(dists_mm, dtype=np.float64)).astype(np.int64)
    if dist.shape != (96,):
        raise ValueError(f"an ultra capsule holds 96 distances, got {dist.shape}")
    if np.any((dist < 0) | (dist > 28656)):
        raise ValueError("ultra distances must be in 0..28656 mm")
    d = dist.reshape(32, 3)
    major = _varbitscale_encode(d[:, 0])
    base1, lvl1 = _varbitscale_decode(major)
    nxt = np.concatenate([major[1:], [major[0]]])  # the last cabin's is fixed up by the next capsule
    base2, lvl2 = _varbitscale_decode(nxt)
    b1 = np.where((base1 == 0) & (base2 != 0), base2, base1)
    l1 = np.where((base1 == 0) & (base2 != 0), lvl2, lvl1)

    def predict(target: np.ndarray, base: np.ndarray, lvl: np.ndarray) -> np.ndarray:
        p = np.floor_divide(target - base, 1 << lvl)
        ok = (target > 0) & (p > -512) & (p < 511)
        return np.where(ok, p, -512) & 0x3FF

    # the second prediction refers to the *next* cabin's major, which the encoder of a
    # single capsule only knows for cabins 0..30; the last one is sent as "no return"
    p1 = predict(d[:, 1], b1, l1)
    p2 = predict(d[:, 2], base2, lvl2)
    p2[-1] = (-512) & 0x3FF
    word = major | (p1 << 12) | (p2 << 22)
    body = struct.pack("<H", round(start_angle_deg * 64) % _FULL_TURN_Q6 | (_START_FLAG if start else 0))
    body += word.astype("<u4").tobytes()
    cs = _xor(body)
    return bytes(((_SYNC_NIBBLE_1 << 4) | (cs & 0xF), (_SYNC_NIBBLE_2 << 4) | (cs >> 4))) + body


# -- dense capsules (answer type 0x85): 40 distances, 84 bytes --------------------------


def _dense_sync(raw: np.ndarray, inc: np.ndarray, carry: dict[str, int], key: str) -> np.ndarray:
    """The dense handlers' revolution flag: ``(raw + inc) mod 360° < 2 inc``, and set only
    where the flag published for the sample before was not (``(syncBit ^
    lastNodeSyncBit) & syncBit``, the last flag carried across capsules)."""
    nxt = (raw + inc[:, None]) % (360 << 16)
    cond = (nxt < (inc[:, None] << 1)).reshape(-1)
    out = np.zeros_like(cond)
    for i in np.flatnonzero(cond):  # about two a revolution
        before = bool(out[i - 1]) if i > 0 else bool(carry.get(key, 0))
        out[i] = not before
    if out.size:
        carry[key] = int(out[-1])
    return out


def _dense_unpack(prev: np.ndarray, cur: np.ndarray, carry: dict[str, int]) -> tuple[np.ndarray, ...]:
    """SDK ``UnpackerHandler_DenseCapsuleNode::_onScanNodeDenseCapsuleData``: no angle
    compensation (a time-of-flight head), distances in whole millimetres."""
    m = prev.shape[0]
    raw, inc = _interpolated(prev, cur, 2, 1 << 8, 40, 40)  # (diff << 8) / 40
    cab = prev[:, 4:84].reshape(m, 40, 2).astype(np.int64)
    dist_q2 = ((cab[:, :, 0] | (cab[:, :, 1] << 8)) << 2).reshape(-1)
    angle_q6 = ((raw >> 10) % _FULL_TURN_Q6).reshape(-1)
    return angle_q6, dist_q2, (dist_q2 > 0).astype(np.uint8), _dense_sync(raw, inc, carry, "dense_sync")


def encode_dense_capsule(start_angle_deg: float, dists_mm: np.ndarray | list[float], *, start: bool = False) -> bytes:
    """One 84-byte dense capsule: start angle and 40 distances (u16, mm)."""
    dist = np.rint(np.asarray(dists_mm, dtype=np.float64)).astype(np.int64)
    if dist.shape != (40,):
        raise ValueError(f"a dense capsule holds 40 distances, got {dist.shape}")
    if np.any((dist < 0) | (dist > 0xFFFF)):
        raise ValueError("dense distances must be in 0..65535 mm")
    body = struct.pack("<H", round(start_angle_deg * 64) % _FULL_TURN_Q6 | (_START_FLAG if start else 0))
    body += dist.astype("<u2").tobytes()
    cs = _xor(body)
    return bytes(((_SYNC_NIBBLE_1 << 4) | (cs & 0xF), (_SYNC_NIBBLE_2 << 4) | (cs >> 4))) + body


# -- ultra-dense capsules (answer type 0x86): 32 cabins of 2 samples, 170 bytes ---------

_UD_THRESHOLD_MM = (0, 2046, 8187, 24567)  # SDK DISTANCE_THRESHOLD_TO_SCALE_1..3


def _ultra_dense_unpack(prev: np.ndarray, cur: np.ndarray, carry: dict[str, int]) -> tuple[np.ndarray, ...]:
    """SDK ``UnpackerHandler_UltraDenseCapsuleNode::_onScanNodeUltraDenseCapsuleData``.

    Layout (sl_lidar_cmd.h): checksum nibbles, u32 time stamp, u16 device status, u16
    start angle, then 32 cabins of two u16 "quality low, distance, scale" words and
    one byte holding both samples' high quality nibbles. Each sample's 2-bit scale
    picks the distance's unit (2, 3, 4 or 5 quarter-millimetre steps above a
    threshold); at the finest scale, a distance within 2 mm of the previous sample's
    is averaged with it (the SDK's ``_last_dist_q2``, carried across capsules).
    """
    m = prev.shape[0]
    raw, inc = _interpolated(prev, cur, 8, 1 << 8, 64, 64)  # (diff << 8) / 64
    cab = prev[:, 10:170].reshape(m, 32, 5).astype(np.int64)
    w: np.ndarray = np.empty((m, 64), dtype=np.int64)
    w[:, 0::2] = (cab[:, :, 0] | (cab[:, :, 1] << 8)) | ((cab[:, :, 4] & 0x0F) << 16)
    w[:, 1::2] = (cab[:, :, 2] | (cab[:, :, 3] << 8)) | ((cab[:, :, 4] >> 4) << 16)
    w = w.reshape(-1)
    scale = w & 0x3
    quality = np.select(
        [scale == 0, scale == 1, scale == 2], [w >> 12, (w >> 13) << 1, (w >> 14) << 2], (w >> 15) << 3
    ) & 0xFF
    dist = np.select(
        [scale == 0, scale == 1, scale == 2],
        [(w & 0xFFC) * 2, (w & 0x1FFC) * 3 + (_UD_THRESHOLD_MM[1] << 2), (w & 0x3FFC) * 4 + (_UD_THRESHOLD_MM[2] << 2)],
        (w & 0x7FFC) * 5 + (_UD_THRESHOLD_MM[3] << 2),
    )
    last = carry.get("last_dist_q2", 0)
    out = dist.copy()
    for i in range(out.size):  # a recurrence: each sample may average with the one before
        d = int(out[i])
        if scale[i] == 0 and last and abs(d - last) <= 8:
            d = (d + last) >> 1
            out[i] = d
        last = d
    carry["last_dist_q2"] = last
    angle_q6 = ((raw >> 10) % _FULL_TURN_Q6).reshape(-1)
    del quality  # like every capsule kind here: 1 where a return, 0 where none
    return angle_q6, out, (out > 0).astype(np.uint8), _dense_sync(raw, inc, carry, "ultra_dense_sync")


def encode_ultra_dense_capsule(
    start_angle_deg: float, dists_mm: np.ndarray | list[float], *, start: bool = False, time_stamp: int = 0
) -> bytes:
    """One 170-byte ultra-dense capsule of 64 samples, each at the finest scale that
    holds its distance (quality 15, i.e. a good return, where the distance is not 0)."""
    dist = np.asarray(dists_mm, dtype=np.float64)
    if dist.shape != (64,):
        raise ValueError(f"an ultra-dense capsule holds 64 distances, got {dist.shape}")
    q2 = np.rint(dist * 4).astype(np.int64)
    words = np.zeros(64, dtype=np.int64)
    fields = (0xFFC, 0x1FFC, 0x3FFC, 0x7FFC)
    for i, d in enumerate(q2.tolist()):
        if d <= 0:
            continue
        for sc, field in enumerate(fields):
            unit, base = sc + 2, _UD_THRESHOLD_MM[sc] << 2
            f = (d - base) // (4 * unit) * 4
            if f <= field or sc == 3:
                words[i] = min(f, field) | sc | (1 << (12 + sc))  # quality 1 << sc: a return
                break
    high = words >> 16
    cabins = np.empty((32, 5), dtype=np.uint8)
    cabins[:, 0] = words[0::2] & 0xFF
    cabins[:, 1] = (words[0::2] >> 8) & 0xFF
    cabins[:, 2] = words[1::2] & 0xFF
    cabins[:, 3] = (words[1::2] >> 8) & 0xFF
    cabins[:, 4] = (high[0::2] & 0xF) | ((high[1::2] & 0xF) << 4)
    body = struct.pack("<IHH", time_stamp & 0xFFFFFFFF, 0,
                       round(start_angle_deg * 64) % _FULL_TURN_Q6 | (_START_FLAG if start else 0))
    body += cabins.tobytes()
    cs = _xor(body)
    return bytes(((_SYNC_NIBBLE_1 << 4) | (cs & 0xF), (_SYNC_NIBBLE_2 << 4) | (cs >> 4))) + body


LEGACY_CAPSULE = CapsuleFormat("express", EXPRESS_DESCRIPTOR, CAPSULE_SAMPLES, 2, _legacy_unpack)
ULTRA_CAPSULE = CapsuleFormat("ultra", ULTRA_DESCRIPTOR, 96, 2, _ultra_unpack)
DENSE_CAPSULE = CapsuleFormat("dense", DENSE_DESCRIPTOR, 40, 2, _dense_unpack)
ULTRA_DENSE_CAPSULE = CapsuleFormat("ultradense", ULTRA_DENSE_DESCRIPTOR, 64, 8, _ultra_dense_unpack)

#: Capsule kinds by the answer type of their scan mode (GET_LIDAR_CONF, descriptor).
CAPSULE_FORMATS = {f.answer_type: f for f in (LEGACY_CAPSULE, ULTRA_CAPSULE, DENSE_CAPSULE, ULTRA_DENSE_CAPSULE)}
#: ... and by the name ``mazebot lidar decode --mode`` knows them by.
CAPSULE_FORMATS_BY_NAME = {f.name: f for f in CAPSULE_FORMATS.values()}


def scan_decoder(answer_type: int) -> StandardScanDecoder | ExpressScanDecoder:
    """The decoder of a scan mode's answer type (0x81 standard, 0x82/0x84/0x85/0x86 capsules)."""
    if answer_type == TYPE_SCAN:
        return StandardScanDecoder()
    if answer_type not in CAPSULE_FORMATS:
        raise ProtocolError(f"scan answer type {answer_type:#04x} is none of 0x81, 0x82, 0x84, 0x85, 0x86")
    return ExpressScanDecoder(CAPSULE_FORMATS[answer_type])


# --- GET_LIDAR_CONF: the device's scan modes --------------------------------------------
#
# Request A5 84 size [u32le type, u16le mode id, padding] checksum (the SDK sends the
# type and 32 reserved bytes, the mode id in the first two: sl_lidar_driver.cpp,
# getLidarConf). Answer: descriptor of type 0x20, single, then u32le type + payload.

CMD_GET_LIDAR_CONF = 0x84
COMMAND_NAMES[CMD_GET_LIDAR_CONF] = "GET_LIDAR_CONF"

CONF_SCAN_MODE_COUNT = 0x70  # u16
CONF_SCAN_MODE_US_PER_SAMPLE = 0x71  # u32, q8 microseconds
CONF_SCAN_MODE_MAX_DISTANCE = 0x74  # u32, q8 metres
CONF_SCAN_MODE_ANS_TYPE = 0x75  # u8
CONF_SCAN_MODE_TYPICAL = 0x7C  # u16
CONF_SCAN_MODE_NAME = 0x7F  # NUL-terminated string

#: The mode ids of the scan commands a device without GET_LIDAR_CONF knows (sl_lidar_cmd.h).
SCAN_MODE_ID_STANDARD = 0
SCAN_MODE_ID_EXPRESS = 1


@dataclass(frozen=True)
class ScanModeInfo:
    """One scan mode the device offers (GET_LIDAR_CONF)."""

    id: int
    name: str
    us_per_sample: float
    max_distance_m: float
    answer_type: int

    @property
    def samples_per_s(self) -> float:
        return 1e6 / self.us_per_sample if self.us_per_sample > 0 else 0.0

    def __str__(self) -> str:
        return (f"{self.id}: {self.name}, {self.samples_per_s:.0f} samples/s ({self.us_per_sample:g} us), "
                f"max {self.max_distance_m:g} m, answer type {self.answer_type:#04x}")


def build_conf_request(conf_type: int, mode_id: int | None = None) -> bytes:
    """A GET_LIDAR_CONF request as the SDK sends it: the type and 32 reserved bytes,
    the mode id (for the per-mode types) in the first two."""
    reserved = bytearray(32)
    if mode_id is not None:
        reserved[:2] = struct.pack("<H", mode_id)
    return build_request(CMD_GET_LIDAR_CONF, struct.pack("<I", conf_type) + bytes(reserved))


def parse_conf_request(payload: bytes) -> tuple[int, int]:
    """(type, mode id) of a GET_LIDAR_CONF request payload (mode id 0 if absent)."""
    if len(payload) < 4:
        raise ProtocolError(f"GET_LIDAR_CONF request: expected at least 4 payload bytes, found {len(payload)}")
    (conf_type,) = struct.unpack_from("<I", payload)
    mode_id = struct.unpack_from("<H", payload, 4)[0] if len(payload) >= 6 else 0
    return conf_type, mode_id


def conf_descriptor(payload_len: int) -> Descriptor:
    return Descriptor(4 + payload_len, SendMode.SINGLE, TYPE_LIDAR_CONF)


def encode_conf_answer(conf_type: int, payload: bytes) -> bytes:
    return struct.pack("<I", conf_type) + payload


def parse_conf_answer(data: bytes | bytearray, conf_type: int) -> bytes:
    """The payload of a GET_LIDAR_CONF answer, insisting it answers ``conf_type``."""
    if len(data) < 5:
        raise ProtocolError(f"GET_LIDAR_CONF answer: expected a type and a payload, found {len(data)} bytes")
    (found,) = struct.unpack_from("<I", data)
    if found != conf_type:
        raise ProtocolError(f"GET_LIDAR_CONF answer: expected type {conf_type:#x}, found {found:#x}")
    return bytes(data[4:])


def encode_mode_conf(mode: ScanModeInfo, conf_type: int) -> bytes:
    """The payload the device sends for one per-mode conf type."""
    if conf_type == CONF_SCAN_MODE_US_PER_SAMPLE:
        return struct.pack("<I", round(mode.us_per_sample * 256))
    if conf_type == CONF_SCAN_MODE_MAX_DISTANCE:
        return struct.pack("<I", round(mode.max_distance_m * 256))
    if conf_type == CONF_SCAN_MODE_ANS_TYPE:
        return bytes((mode.answer_type,))
    if conf_type == CONF_SCAN_MODE_NAME:
        return mode.name.encode("ascii") + b"\0"
    raise ValueError(f"conf type {conf_type:#x} is not a per-mode one")


def decode_mode_conf(conf_type: int, payload: bytes) -> float | int | str:
    """A per-mode conf value as the SDK reads it (q8 values shifted right by 8)."""
    if conf_type in (CONF_SCAN_MODE_US_PER_SAMPLE, CONF_SCAN_MODE_MAX_DISTANCE):
        if len(payload) < 4:
            raise ProtocolError(f"GET_LIDAR_CONF {conf_type:#x}: expected 4 bytes, found {len(payload)}")
        return float(struct.unpack_from("<I", payload)[0] >> 8)
    if conf_type == CONF_SCAN_MODE_ANS_TYPE:
        return payload[0]
    if conf_type in (CONF_SCAN_MODE_COUNT, CONF_SCAN_MODE_TYPICAL):
        if len(payload) < 2:
            raise ProtocolError(f"GET_LIDAR_CONF {conf_type:#x}: expected 2 bytes, found {len(payload)}")
        value: int = struct.unpack_from("<H", payload)[0]
        return value
    if conf_type == CONF_SCAN_MODE_NAME:
        return payload.split(b"\0", 1)[0].decode("ascii", errors="replace")
    raise ProtocolError(f"GET_LIDAR_CONF: unknown conf type {conf_type:#x}")


def express_scan_payload(mode_id: int) -> bytes:
    """EXPRESS_SCAN payload (sl_lidar_payload_express_scan_t): u8 working mode (the scan
    mode id), u16 working flags, u16 param."""
    return struct.pack("<BHH", mode_id, 0, 0)
