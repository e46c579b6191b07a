"""Wheel encoders: quadrature decoding of two GPIO channels per wheel, with gpiozero.

Each drive wheel carries a quadrature encoder: two square waves, A and B, a quarter of
a cycle apart. Which one leads tells the direction; every edge is a quarter of an
encoder line. :class:`QuadratureDecoder` turns edges into signed ticks with an explicit
transition table (pure, no pins); :class:`WheelEncoder` feeds it from two gpiozero
input devices on an injected pin factory (``LGPIOFactory`` on the Pi, ``MockFactory``
in tests and in the simulator); :class:`WheelEncoders` pairs the two wheels and hands
odometry one consistent :class:`EncoderReading`.

Threading: gpiozero calls our pin callbacks on its own thread (lgpio's notification
thread on the Pi; whoever drives a mock pin in tests). Each callback only updates the
decoder's integers, under a :class:`threading.Lock` (one for both wheels of a
:class:`WheelEncoders`) that the asyncio side also takes (for a few hundred nanoseconds) to
copy the counters, so a reader can never see a count and an invalid-transition total from
different edges, nor one wheel's count from later edges than the other's.

Callback cost, measured with ``tools/measure_encoder_callback.py`` (MockFactory pins
driven through full quadrature cycles, each stage timed separately, best of 15 runs
of 80 000 edges): on this development machine our part (lock + decoder step) costs
0.36 µs per edge called directly, 0.5 µs seen through gpiozero; gpiozero's
``when_changed`` dispatch adds 0.26 µs; an emulation of lgpio's Python notification
loop (read one 16-byte report, ``struct.unpack``, scan the registered callbacks,
gpiozero's ``LGPIOPin`` wrapper) adds 0.40 µs. The mock's own bookkeeping (0.46 µs per
edge) is subtracted: it does not exist on the Pi. Total on the Pi's path: about 1.0 µs
per edge here. Estimate for a Pi 4, assumptions explicit: a core 5× slower (the
pessimistic end of docs/design.md's 3–5×) gives 5 µs per edge; the callback thread gets at
most half of the GIL while SLAM and the web server run, so it can follow about
100 000 edges/s, both wheels together. Latency does not set that limit, throughput
does: lgpio's C alert thread reads the kernel's line events (level taken from the edge
type), sorts the events of all lines by timestamp, buffers up to 2000 of them and
writes them in order to one notification pipe, which a single Python thread reads and
dispatches (joan2937/lg ``lgPthAlerts.c`` and ``PY_LGPIO/lgpio_extra.py``; the docs
corpus had no published lgpio callback rate, so these sources and the measurement
are the basis). A GIL stall of a few milliseconds only queues reports in the pipe; and
when the Python thread falls behind it reads reports in batches, so the per-report
thread wake-up (not measured here) is paid only while there is slack. Our need at
full speed with the default config (0.065 m wheels, 0.6 m/s at full throttle, 210
lines, x4 decoding) is 2.94 rev/s × 840 ticks = 2 500 edges/s per wheel, 5 000 for
both: a margin of about 20× (a 1000-line encoder in x4 would still fit, at about 4×).
Re-run the tool after touching the callback path.
"""

from __future__ import annotations

import contextlib
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final, Literal, Self

from gpiozero import InputDevice
from gpiozero.pins import Factory

from mazebot.clock import Clock
from mazebot.config import EncodersConfig
from mazebot.taps import notify

Decoding = Literal["x1", "x2", "x4"]

#: A gpiozero pin callback: ``(ticks, state)``, the event time and the pin's new level.
PinCallback = Callable[[float, int], None]

#: The oldest edge stamp taken as one: older than this, the stamp and the pin factory's clock
#: cannot be the same clock (a robot at rest has no new edge, and then the age is not needed).
MAX_EDGE_AGE_S: Final = 3600.0
#: Both wheels' counts are noted at most this often, by the edges' own stamps (:class:`EdgeSamples`).
EDGE_SAMPLE_PERIOD_S: Final = 0.01
#: Samples kept between two readings (1.3 s of driving at ``EDGE_SAMPLE_PERIOD_S``); older ones are
#: dropped: the odometry then has fewer poses inside a long gap, never wrong ones.
EDGE_SAMPLES_KEPT: Final = 128

#: Ticks per encoder line for each decoding mode.
TICKS_PER_LINE: Final[dict[Decoding, int]] = {"x1": 1, "x2": 2, "x4": 4}

#: Channel bits in the 2-bit state ``AB`` (A is the high bit).
CHANNEL_A: Final = 0b10
CHANNEL_B: Final = 0b01

#: Marker in :data:`TRANSITIONS` for a transition the encoder cannot make.
INVALID: Final = None

# The Gray-code cycle. Forward (+1) is A leading B; each step changes one bit:
#
#          +---+   +---+
#   A  ----+   +---+   +---
#            +---+   +---+
#   B  ------+   +---+   +-
#
#   AB:  00 -> 10 -> 11 -> 01 -> 00   forward, +1 per edge
#   AB:  00 -> 01 -> 11 -> 10 -> 00   backward, -1 per edge
#
# A change of both bits at once (00 <-> 11, 01 <-> 10) is impossible for a real
# encoder: an edge was lost and the direction of the missing step is unknowable.
#
# Indexed by (previous AB << 2) | new AB.
TRANSITIONS: Final[tuple[int | None, ...]] = (
    # new:  00       01       10       11          previous
    0,       -1,      +1,      INVALID,  # 00
    +1,      0,       INVALID, -1,       # 01
    -1,      INVALID, 0,       +1,       # 10
    INVALID, +1,      -1,      0,        # 11
)  # fmt: skip

# Which valid transitions each mode counts. x4 counts every edge. x2 counts A's edges.
# x1 counts only the edge where A rises while B is low (00 -> 10) and its reverse
# (10 -> 00): the same physical edge in both directions, so a wheel rocking back and
# forth across it nets zero instead of counting "A rising" once per rock.
_COUNTED: Final[dict[Decoding, frozenset[tuple[int, int]]]] = {
    "x4": frozenset(
        (p, n) for p in range(4) for n in range(4) if TRANSITIONS[(p << 2) | n]
    ),
    "x2": frozenset(
        (p, n)
        for p in range(4)
        for n in range(4)
        if TRANSITIONS[(p << 2) | n] and (p ^ n) == CHANNEL_A
    ),
    "x1": frozenset({(0b00, 0b10), (0b10, 0b00)}),
}


class QuadratureDecoder:
    """Turns successive A/B states (or single-channel edges) into signed ticks.

    Pure state machine, no pins, no threads: the caller serializes calls.

    ``count`` is the running tick total (``ticks_per_line`` per encoder line, see
    :data:`TICKS_PER_LINE`), positive forward (A leading B) unless ``invert``.
    ``invalid_transitions`` counts the events the table cannot interpret; they are
    counted, never applied to ``count``.

    Example::

        >>> d = QuadratureDecoder(initial_ab=0b00, decoding="x4")
        >>> for ab in (0b10, 0b11, 0b01, 0b00):
        ...     _ = d.update(ab)
        >>> d.count
        4
    """

    def __init__(
        self, initial_ab: int = 0b00, *, decoding: Decoding = "x4", invert: bool = False
    ) -> None:
        if decoding not in TICKS_PER_LINE:
            raise ValueError(f"decoding must be one of x1, x2, x4, got {decoding!r}")
        if not 0 <= initial_ab <= 0b11:
            raise ValueError(f"initial_ab must be a 2-bit state 0..3, got {initial_ab!r}")
        self.decoding: Decoding = decoding
        self.invert = invert
        self.count = 0
        self.invalid_transitions = 0
        self.direction = 0  # sign of the last valid movement (after inversion), 0 = none yet
        self._ab = initial_ab
        sign = -1 if invert else 1
        counted = _COUNTED[decoding]
        # Per-instance table: the step to add for each valid transition in this mode,
        # with inversion applied; 0 for transitions this mode does not count.
        self._counted_steps = tuple(
            sign * (TRANSITIONS[(p << 2) | n] or 0) if (p, n) in counted else 0
            for p in range(4)
            for n in range(4)
        )
        self._direction_steps = tuple(sign * (t or 0) for t in TRANSITIONS)

    @property
    def state(self) -> int:
        """The current 2-bit state ``AB``."""
        return self._ab

    @property
    def ticks_per_line(self) -> int:
        return TICKS_PER_LINE[self.decoding]

    def update(self, new_ab: int) -> int | None:
        """Move to state ``new_ab``; return the ticks added, or ``None`` if impossible.

        An impossible transition (both channels changed) is counted in
        ``invalid_transitions`` and not applied to ``count``; the decoder still adopts
        ``new_ab`` so that it is back in step with the pins for the next edge.
        """
        prev = self._ab
        index = (prev << 2) | new_ab
        self._ab = new_ab
        if TRANSITIONS[index] is INVALID:
            self.invalid_transitions += 1
            return None
        return self._apply(index)

    def edge(self, channel: int, level: int) -> int | None:
        """One channel (``CHANNEL_A`` or ``CHANNEL_B``) changed to ``level``.

        This is what a GPIO callback knows: which pin and its new level. The other
        channel keeps the level of its own last edge, not a fresh read of the pin:
        events arrive in order, and a fresh read could already show an edge that is
        still queued behind this one. An event that reports the level its channel
        already has means that channel's opposite edge was lost (edge-triggered
        reports can only alternate); it is counted as invalid and not applied.
        """
        prev = self._ab
        new_ab = (prev | channel) if level else (prev & ~channel)
        if new_ab == prev:
            self.invalid_transitions += 1
            return None
        self._ab = new_ab
        return self._apply((prev << 2) | new_ab)

    def _apply(self, index: int) -> int:
        direction = self._direction_steps[index]
        if direction:
            self.direction = direction
        step = self._counted_steps[index]
        self.count += step
        return step


@dataclass(frozen=True, slots=True)
class EncoderReading:
    """Both wheels' tick totals since the encoders were opened.

    Ticks grow forward for each wheel (after the configured inversion).
    ``invalid_transitions`` is the sum over both wheels of edges the decoder could not
    interpret: a growing value means lost edges and odometry that is short by a few
    ticks. ``time_s`` is the clock time of the reading, when a clock was given.
    """

    left_ticks: int
    right_ticks: int
    invalid_transitions: int
    time_s: float | None = None
    #: seconds between the newest edge counted (either wheel) and this reading, on the pin
    #: factory's own clock (the edge's stamp, lgpio's from the kernel): how old the counts are
    #: when the thread that counts edges is behind. None: no edge yet, or an unusable stamp.
    edge_age_s: float | None = None
    #: both wheels' counts at edges since the previous reading, oldest first, at most one per
    #: ``EDGE_SAMPLE_PERIOD_S`` of the edges' time: (age in seconds, as ``edge_age_s``, left
    #: ticks, right ticks). A reading that comes late (a starved process) still knows how the
    #: wheels got to its counts: a turn that began in the gap is not smeared over all of it.
    steps: tuple[tuple[float, int, int], ...] = ()


class EdgeSamples:
    """Both wheels' counts as the edges come, at most every ``period_s`` of the edges' own time.

    Called from the encoder callbacks before each edge is counted, on the one thread that
    delivers every line's edges (lgpio's; the simulator's GPIO thread). A sample is the two
    counts as they stand *before* an edge with a later stamp than the one before it, dated
    by that one: every edge up to that stamp is counted on both wheels then. (Read at the
    edge itself, the other wheel could still lack edges of the same stamp: the quota
    bench's world sends each 10 ms step's edges with the step's time, the left wheel's
    first, and samples taken there were a step behind on the right: 0.86 deg p99 of heading
    over 0.2 s in a 16x16 quota run.) The odometry task takes what gathered since its last
    reading (:meth:`take`).

    Example::

        samples = EdgeSamples(left, right, factory.ticks_diff)
        samples.note(12.50)     # in an edge callback, before counting the edge stamped 12.50
        samples.note(12.52)     # the next: (12.50, left ticks, right ticks) noted
        samples.take()          # [(12.50, ...)], and empty again
    """

    def __init__(self, left: WheelEncoder, right: WheelEncoder, ticks_diff: Callable[[float, float], float],
                 period_s: float = EDGE_SAMPLE_PERIOD_S, kept: int = EDGE_SAMPLES_KEPT) -> None:
        self._left, self._right = left._decoder, right._decoder
        self._diff = ticks_diff
        self.period_s = period_s
        self._rows: deque[tuple[float, int, int]] = deque(maxlen=kept)
        self._last: float | None = None  # the stamp of the newest sample
        self._prev: float | None = None  # the stamp of the edge before this one

    def note(self, ticks: float) -> None:
        """An edge stamped ``ticks`` is about to be counted (on the edge thread)."""
        prev, self._prev = self._prev, ticks
        if prev is None or self._diff(ticks, prev) <= 0:
            return  # the first edge, or one stamped as the edge before: the counts are not whole there
        last = self._last
        if last is not None and self._diff(prev, last) < self.period_s:
            return
        self._last = prev
        self._rows.append((prev, self._left.count, self._right.count))

    def take(self) -> list[tuple[float, int, int]]:
        """The samples noted since the last call, oldest first (any thread; one reader)."""
        rows = self._rows
        taken = []
        while rows:
            taken.append(rows.popleft())
        return taken


class WheelEncoder:
    """One quadrature encoder on two GPIO pins, decoded on every edge.

    Uses two gpiozero :class:`~gpiozero.InputDevice` (so gpiozero reserves the pins and
    sets their pulls) and hooks their pins' ``when_changed``, as gpiozero's own
    ``RotaryEncoder`` does. ``RotaryEncoder`` is not used because it clamps steps at
    ``max_steps``, only counts full detent cycles and cannot report invalid
    transitions. No software debounce: it would drop real edges at speed.

    Example (tests, simulator)::

        from gpiozero.pins.mock import MockFactory
        factory = MockFactory()
        with WheelEncoder(17, 18, pin_factory=factory) as wheel:
            factory.pin(17).drive_low()   # pins start high (pull-ups): AB 11 -> 01
            print(wheel.ticks)            # 1 (x4, A leading B = forward)
    """

    def __init__(
        self,
        a_pin: int | str,
        b_pin: int | str,
        *,
        decoding: Decoding = "x4",
        invert: bool = False,
        pull_up: bool = True,
        pin_factory: Factory,
        lock: threading.Lock | None = None,
    ) -> None:
        if pin_factory is None:
            raise ValueError(
                "WheelEncoder needs an explicit pin_factory "
                "(LGPIOFactory() on the Pi, MockFactory() in tests); "
                "it never falls back to gpiozero's global default"
            )
        #: taken by each edge's callback and by the readers; :class:`WheelEncoders` gives both wheels one
        self._lock = lock if lock is not None else threading.Lock()
        self._closed = False
        self._factory = pin_factory
        #: the pin factory's ticks of the newest edge counted (gpiozero's ``when_changed`` argument)
        self._edge_ticks: float | None = None
        #: called with each edge's stamp after it is counted (:class:`EdgeSamples`); [None]: nothing
        self._edge_hook: list[Callable[[float], None] | None] = [None]
        self._a = InputDevice(a_pin, pull_up=pull_up, pin_factory=pin_factory)
        try:
            self._b = InputDevice(b_pin, pull_up=pull_up, pin_factory=pin_factory)
        except BaseException:
            self._a.close()
            raise
        try:
            for device in (self._a, self._b):
                device.pin.bounce = None
                device.pin.edges = "both"
            # Read the starting levels before any callback can run, then listen.
            initial_ab = (CHANNEL_A if self._a.pin.state else 0) | (
                CHANNEL_B if self._b.pin.state else 0
            )
            self._decoder = QuadratureDecoder(initial_ab, decoding=decoding, invert=invert)
            self._on_a_changed, self._on_b_changed = self._make_callbacks()
            self._a.pin.when_changed = self._on_a_changed
            self._b.pin.when_changed = self._on_b_changed
        except BaseException:
            self._b.close()
            self._a.close()
            raise

    def __repr__(self) -> str:
        if self._closed:
            return f"<WheelEncoder closed, ticks={self._decoder.count}>"
        return (
            f"<WheelEncoder A={self._a.pin!r} B={self._b.pin!r} "
            f"{self._decoder.decoding} ticks={self._decoder.count}>"
        )

    def _make_callbacks(self) -> tuple[PinCallback, PinCallback]:
        """The two ``when_changed`` callbacks: ``(ticks, state)`` on gpiozero's thread.

        Plain closures over local names rather than bound methods: a pin keeps only a
        weak reference to its callback, and for a bound method gpiozero rebuilds the
        method from a ``WeakMethod`` on every edge, which measured as costly as the
        decoding itself. The strong references live on ``self`` (``_on_a_changed``,
        ``_on_b_changed``), so the callbacks last exactly as long as this encoder.
        """
        lock = self._lock
        edge = self._decoder.edge
        hook = self._edge_hook

        # each edge's own time stamp is kept with the count: under load the edges reach this
        # thread in bursts, and the count must be dated by when the wheel turned
        def on_a_changed(ticks: float, state: int) -> None:
            noted = hook[0]
            if noted is not None:
                noted(ticks)
            with lock:
                edge(CHANNEL_A, state)
                self._edge_ticks = ticks

        def on_b_changed(ticks: float, state: int) -> None:
            noted = hook[0]
            if noted is not None:
                noted(ticks)
            with lock:
                edge(CHANNEL_B, state)
                self._edge_ticks = ticks

        return on_a_changed, on_b_changed

    # Readers (any thread).

    @property
    def edge_callbacks(self) -> tuple[PinCallback, PinCallback]:
        """The two ``when_changed`` callbacks (A, B), for timing the decode without pins."""
        return self._on_a_changed, self._on_b_changed

    def read(self) -> tuple[int, int]:
        """``(ticks, invalid_transitions)``, both from the same instant."""
        with self._lock:
            return self._decoder.count, self._decoder.invalid_transitions

    def read_stamped(self) -> tuple[int, int, float | None]:
        """``(ticks, invalid_transitions, edge_ticks)``: ``edge_ticks`` the pin factory's stamp of the newest edge."""
        with self._lock:
            return self.counters()

    def counters(self) -> tuple[int, int, float | None]:
        """:meth:`read_stamped` for a caller that holds this encoder's lock already."""
        return self._decoder.count, self._decoder.invalid_transitions, self._edge_ticks

    def edge_age_s(self, edge_ticks: float | None) -> float | None:
        """Seconds from an edge stamp (:meth:`read_stamped`) to now on the pin factory's clock; None if unusable.

        gpiozero's ticks are only comparable with the same factory's ``ticks()`` through its
        ``ticks_diff`` (lgpio's are the kernel's event stamps in seconds). An age outside
        [0, ``MAX_EDGE_AGE_S``] means the two were not on one clock: unusable, never guessed.
        """
        if edge_ticks is None:
            return None
        try:
            age_s = float(self._factory.ticks_diff(self._factory.ticks(), edge_ticks))
        except (TypeError, ValueError, OverflowError):
            return None
        return age_s if 0.0 <= age_s <= MAX_EDGE_AGE_S else None

    @property
    def ticks(self) -> int:
        """Signed tick total since opening; forward is positive."""
        return self.read()[0]

    @property
    def invalid_transitions(self) -> int:
        return self.read()[1]

    @property
    def direction(self) -> int:
        """+1 or -1: the direction of the last valid edge; 0 before the first one."""
        with self._lock:
            return self._decoder.direction

    @property
    def ticks_per_line(self) -> int:
        return self._decoder.ticks_per_line

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Stop listening and release both pins. Safe to call more than once."""
        if self._closed:
            return
        self._closed = True
        for device in (self._a, self._b):
            with contextlib.suppress(AttributeError):  # pin is None if closed elsewhere
                device.pin.when_changed = None
            device.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


class WheelEncoders:
    """The left and right :class:`WheelEncoder` read together.

    ``clock`` (optional) stamps each reading with ``time_s``. Close the pair (or use it
    as a context manager) to release all four pins.

    Taps (:mod:`mazebot.taps`): ``before_read`` is called before each reading (the simulator
    brings its world up to the moment of the read; what it raises, the read raises); each of
    ``on_read`` is given the reading (a listener's exception is logged, the reading still returned).
    """

    def __init__(
        self, left: WheelEncoder, right: WheelEncoder, *, clock: Clock | None = None
    ) -> None:
        self.left = left
        self.right = right
        self._clock = clock
        self.before_read: Callable[[], None] | None = None
        self.on_read: tuple[Callable[[EncoderReading], None], ...] = ()
        factory = left._factory
        self._factory = factory
        self.samples = EdgeSamples(left, right, factory.ticks_diff)
        left._edge_hook[0] = right._edge_hook[0] = self.samples.note

    @classmethod
    def from_config(
        cls, cfg: EncodersConfig, pin_factory: Factory, *, clock: Clock | None = None
    ) -> WheelEncoders:
        """Build both encoders from the ``[encoders]`` section on ``pin_factory``, on one lock
        (:meth:`read` takes both counts at one instant)."""
        lock = threading.Lock()
        left = WheelEncoder(
            cfg.left_a_pin,
            cfg.left_b_pin,
            decoding=cfg.decoding,
            invert=cfg.left_invert,
            pull_up=cfg.pull_up,
            pin_factory=pin_factory,
            lock=lock,
        )
        try:
            right = WheelEncoder(
                cfg.right_a_pin,
                cfg.right_b_pin,
                decoding=cfg.decoding,
                invert=cfg.right_invert,
                pull_up=cfg.pull_up,
                pin_factory=pin_factory,
                lock=lock,
            )
        except BaseException:
            left.close()
            raise
        return cls(left, right, clock=clock)

    def read(self) -> EncoderReading:
        """Both wheels' totals (each wheel's pair of counters is internally consistent).

        ``edge_age_s`` is the age of the newer of the two wheels' last edges: lgpio delivers
        the edges of all lines in the order of their stamps on one thread (as the simulator's
        GPIO thread does), so both counts hold every edge up to that one. The two wheels are
        read at one instant when they share a lock (:meth:`from_config`): read one after the
        other, the edge thread could run in between (the interpreter hands it the lock every
        few milliseconds, and a starved process's thread then counts a backlog of tens of
        milliseconds of edges), and the second wheel was that far ahead of the first: a
        heading 6.8 degrees off for one reading, and a first wheel "silent" for the health
        monitor, under a 15 % quota.
        """
        if self.before_read is not None:
            self.before_read()
        if self.left._lock is self.right._lock:
            with self.left._lock:
                left_ticks, left_invalid, left_edge = self.left.counters()
                right_ticks, right_invalid, right_edge = self.right.counters()
        else:
            left_ticks, left_invalid, left_edge = self.left.read_stamped()
            right_ticks, right_invalid, right_edge = self.right.read_stamped()
        ages = [a for a in (self.left.edge_age_s(left_edge), self.right.edge_age_s(right_edge)) if a is not None]
        reading = EncoderReading(
            left_ticks=left_ticks,
            right_ticks=right_ticks,
            invalid_transitions=left_invalid + right_invalid,
            time_s=self._clock.now_s() if self._clock is not None else None,
            edge_age_s=min(ages) if ages else None,
            steps=self._steps(),
        )
        if self.on_read:
            notify(self.on_read, reading, "encoders.on_read")
        return reading

    def _steps(self) -> tuple[tuple[float, int, int], ...]:
        """The edge samples since the last reading as (age_s, left, right); those of unusable age left out."""
        rows = self.samples.take()
        if not rows:
            return ()
        factory = self._factory
        try:
            now = factory.ticks()
            aged = [(float(factory.ticks_diff(now, stamp)), left, right) for stamp, left, right in rows]
        except (TypeError, ValueError, OverflowError):
            return ()
        return tuple(row for row in aged if 0.0 <= row[0] <= MAX_EDGE_AGE_S)

    def close(self) -> None:
        """Release all four pins. Safe to call more than once."""
        try:
            self.left.close()
        finally:
            self.right.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()
