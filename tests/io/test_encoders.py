"""Quadrature decoding, pure and on gpiozero MockFactory pins.

The device tests drive real gpiozero mock pins, so the code under test is the same
``WheelEncoder`` that runs on the Pi (only the pin factory differs).
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Iterator

import pytest
from gpiozero import Device, InputDevice
from gpiozero.exc import GPIOPinInUse
from gpiozero.pins.mock import MockFactory, MockPin

from mazebot.config import EncodersConfig
from mazebot.io.encoders import (
    CHANNEL_A,
    CHANNEL_B,
    INVALID,
    TICKS_PER_LINE,
    TRANSITIONS,
    EncoderReading,
    QuadratureDecoder,
    WheelEncoder,
    WheelEncoders,
)
from tests.fake_clock import FakeClock

A_PIN, B_PIN = 17, 18
MODES = ("x1", "x2", "x4")

# The Gray-code cycle written out independently of the module's table: forward is A
# leading B, as states AB.
FORWARD_CYCLE = (0b00, 0b10, 0b11, 0b01)


@pytest.fixture
def factory() -> Iterator[MockFactory]:
    """A fresh mock pin factory per test; never installed as gpiozero's global default."""
    mock = MockFactory()
    yield mock
    mock.reset()


def pins(factory: MockFactory, a: int = A_PIN, b: int = B_PIN) -> tuple[MockPin, MockPin]:
    return factory.pin(a), factory.pin(b)


def drive(pin: MockPin, level: int) -> None:
    if level:
        pin.drive_high()
    else:
        pin.drive_low()


def drive_unseen(pin: MockPin, level: int) -> None:
    """Change a pin's level without its callback running: a lost edge."""
    callback = pin.when_changed
    pin.when_changed = None
    drive(pin, level)
    pin.when_changed = callback


def cycle_states(start_ab: int, forward: bool) -> list[int]:
    """The four states after ``start_ab`` going one full cycle in one direction."""
    step = 1 if forward else -1
    i = FORWARD_CYCLE.index(start_ab)
    return [FORWARD_CYCLE[(i + step * k) % 4] for k in range(1, 5)]


def drive_cycles(a: MockPin, b: MockPin, cycles: int, *, forward: bool) -> None:
    """Drive the pins through ``cycles`` full quadrature cycles, one edge at a time."""
    ab = (CHANNEL_A if a.state else 0) | (CHANNEL_B if b.state else 0)
    for _ in range(cycles):
        for new_ab in cycle_states(ab, forward):
            changed = ab ^ new_ab
            pin = a if changed == CHANNEL_A else b
            drive(pin, new_ab & changed)
            ab = new_ab


# --- the pure decoder -----------------------------------------------------------------


def test_transition_table_is_the_gray_code_cycle() -> None:
    for prev in range(4):
        for new in range(4):
            i = FORWARD_CYCLE.index(prev)
            if new == prev:
                expected = 0
            elif new == FORWARD_CYCLE[(i + 1) % 4]:
                expected = +1
            elif new == FORWARD_CYCLE[(i - 1) % 4]:
                expected = -1
            else:
                expected = INVALID  # both bits changed
            assert TRANSITIONS[(prev << 2) | new] == expected, (bin(prev), bin(new))
    assert sum(t is INVALID for t in TRANSITIONS) == 4


@pytest.mark.parametrize("decoding", MODES)
@pytest.mark.parametrize("forward", [True, False])
@pytest.mark.parametrize("start_ab", FORWARD_CYCLE)
def test_full_cycles_count_lines_times_mode(decoding: str, forward: bool, start_ab: int) -> None:
    decoder = QuadratureDecoder(start_ab, decoding=decoding)  # type: ignore[arg-type]
    for _ in range(25):
        for ab in cycle_states(decoder.state, forward):
            assert decoder.update(ab) is not None
    expected = 25 * TICKS_PER_LINE[decoding]  # type: ignore[index]
    assert decoder.count == (expected if forward else -expected)
    assert decoder.invalid_transitions == 0
    assert decoder.direction == (1 if forward else -1)


@pytest.mark.parametrize("decoding", MODES)
@pytest.mark.parametrize("start_ab", FORWARD_CYCLE)
def test_a_bouncing_without_b_nets_zero(decoding: str, start_ab: int) -> None:
    """Chatter on A (B steady) at any point of the cycle must not accumulate counts."""
    decoder = QuadratureDecoder(start_ab, decoding=decoding)  # type: ignore[arg-type]
    for _ in range(101):
        decoder.update(decoder.state ^ CHANNEL_A)
    decoder.update(decoder.state ^ CHANNEL_A)  # even number of toggles: back at start
    assert decoder.state == start_ab
    assert decoder.count == 0
    assert decoder.invalid_transitions == 0


def test_x1_counts_once_per_cycle_at_the_same_edge_both_ways() -> None:
    decoder = QuadratureDecoder(0b00, decoding="x1")
    steps = [decoder.update(ab) for ab in (0b10, 0b11, 0b01, 0b00)]
    assert steps == [1, 0, 0, 0]  # A rising while B low
    steps = [decoder.update(ab) for ab in (0b01, 0b11, 0b10, 0b00)]
    assert steps == [0, 0, 0, -1]  # the same edge crossed backwards


@pytest.mark.parametrize("prev, new", [(0b00, 0b11), (0b11, 0b00), (0b01, 0b10), (0b10, 0b01)])
def test_impossible_transition_is_counted_not_applied(prev: int, new: int) -> None:
    decoder = QuadratureDecoder(prev)
    assert decoder.update(new) is None
    assert decoder.count == 0
    assert decoder.invalid_transitions == 1
    assert decoder.state == new  # back in step with the pins
    for ab in cycle_states(new, forward=True):
        decoder.update(ab)
    assert decoder.count == 4  # and counting normally again


def test_edge_api_matches_update_and_flags_repeated_levels() -> None:
    decoder = QuadratureDecoder(0b00)
    assert decoder.edge(CHANNEL_A, 1) == 1  # 00 -> 10
    assert decoder.edge(CHANNEL_B, 1) == 1  # 10 -> 11
    assert decoder.edge(CHANNEL_B, 1) is None  # B "rose" again: its falling edge was lost
    assert (decoder.count, decoder.invalid_transitions, decoder.state) == (2, 1, 0b11)


@pytest.mark.parametrize("decoding", MODES)
def test_inversion_negates_every_count(decoding: str) -> None:
    plain = QuadratureDecoder(0b00, decoding=decoding)  # type: ignore[arg-type]
    inverted = QuadratureDecoder(0b00, decoding=decoding, invert=True)  # type: ignore[arg-type]
    for ab in [*cycle_states(0b00, True), *cycle_states(0b00, True), 0b01, 0b11]:
        plain.update(ab)
        inverted.update(ab)
    assert plain.count > 0
    assert inverted.count == -plain.count
    assert inverted.direction == -plain.direction


def test_decoder_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="decoding"):
        QuadratureDecoder(decoding="x3")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="2-bit"):
        QuadratureDecoder(4)


# --- one wheel on mock pins -----------------------------------------------------------


@pytest.mark.parametrize("decoding", MODES)
def test_wheel_counts_cycles_both_directions(factory: MockFactory, decoding: str) -> None:
    a, b = pins(factory)
    wheel = WheelEncoder(A_PIN, B_PIN, decoding=decoding, pin_factory=factory)  # type: ignore[arg-type]
    with wheel:
        per_cycle = TICKS_PER_LINE[decoding]  # type: ignore[index]
        drive_cycles(a, b, 10, forward=True)
        assert wheel.ticks == 10 * per_cycle
        assert wheel.direction == 1
        drive_cycles(a, b, 25, forward=False)
        assert wheel.ticks == -15 * per_cycle
        assert wheel.direction == -1
        assert wheel.invalid_transitions == 0
        assert wheel.ticks_per_line == per_cycle


def test_wheel_starts_from_the_pulled_levels(factory: MockFactory) -> None:
    a, b = pins(factory)
    with WheelEncoder(A_PIN, B_PIN, pull_up=False, pin_factory=factory) as wheel:
        assert (a.state, b.state) == (False, False)
        drive_cycles(a, b, 3, forward=True)
        assert wheel.read() == (12, 0)


def test_wheel_a_bounce_without_b_nets_zero_in_x4(factory: MockFactory) -> None:
    a, b = pins(factory)
    with WheelEncoder(A_PIN, B_PIN, decoding="x4", pin_factory=factory) as wheel:
        drive_cycles(a, b, 2, forward=True)
        before = wheel.ticks
        for _ in range(50):
            a.drive_low()
            a.drive_high()
        assert wheel.read() == (before, 0)


def test_wheel_inversion(factory: MockFactory) -> None:
    a, b = pins(factory)
    with WheelEncoder(A_PIN, B_PIN, invert=True, pin_factory=factory) as wheel:
        drive_cycles(a, b, 5, forward=True)
        assert wheel.ticks == -20


def test_wheel_lost_edge_is_flagged_and_counting_resumes(factory: MockFactory) -> None:
    a, b = pins(factory)
    with WheelEncoder(A_PIN, B_PIN, pin_factory=factory) as wheel:
        drive_cycles(a, b, 2, forward=True)
        assert wheel.read() == (8, 0)
        # Forward from AB=11 is A falls, B falls, A rises, B rises; A's fall goes unseen.
        drive_unseen(a, 0)
        b.drive_low()  # decoded as 11 -> 10: a backward step, wrongly, as it must be
        a.drive_high()  # A "rises" while the decoder already holds A high: lost edge
        b.drive_high()
        ticks, invalid = wheel.read()
        assert invalid == 1
        assert ticks < 8 + 4  # the lost step cannot be recovered, only flagged
        drive_cycles(a, b, 3, forward=True)
        assert wheel.read() == (ticks + 12, 1)


def test_reading_while_another_thread_drives(factory: MockFactory) -> None:
    a, b = pins(factory)
    cycles = 3000
    with WheelEncoder(A_PIN, B_PIN, pin_factory=factory) as wheel:
        driver = threading.Thread(
            target=drive_cycles, args=(a, b, cycles), kwargs={"forward": True}
        )
        readings = []
        driver.start()
        while driver.is_alive():
            readings.append(wheel.read())
        driver.join()
        readings.append(wheel.read())
    assert readings[-1] == (4 * cycles, 0)
    ticks = [t for t, _ in readings]
    assert ticks == sorted(ticks)  # forward only: never a step back, never a torn value
    assert all(invalid == 0 for _, invalid in readings)


def test_wheel_close_is_idempotent_and_releases_pins(factory: MockFactory) -> None:
    a, b = pins(factory)
    wheel = WheelEncoder(A_PIN, B_PIN, pin_factory=factory)
    drive_cycles(a, b, 1, forward=True)
    wheel.close()
    wheel.close()
    assert wheel.closed
    drive_cycles(a, b, 1, forward=True)
    assert wheel.ticks == 4  # no more counting after close
    assert "closed" in repr(wheel)
    with WheelEncoder(A_PIN, B_PIN, pin_factory=factory) as again:  # pins were released
        drive_cycles(a, b, 1, forward=True)
        assert again.ticks == 4


def test_wheel_releases_a_if_b_is_taken(factory: MockFactory) -> None:
    with InputDevice(B_PIN, pin_factory=factory), pytest.raises(GPIOPinInUse):
        WheelEncoder(A_PIN, B_PIN, pin_factory=factory)
    with InputDevice(A_PIN, pin_factory=factory):  # A is free again
        pass


def test_wheel_needs_an_explicit_factory_and_never_sets_the_global() -> None:
    global_before = Device.pin_factory
    with pytest.raises(ValueError, match="pin_factory"):
        WheelEncoder(A_PIN, B_PIN, pin_factory=None)  # type: ignore[arg-type]
    with WheelEncoder(A_PIN, B_PIN, pin_factory=MockFactory()):
        pass
    assert Device.pin_factory is global_before


# --- the pair -------------------------------------------------------------------------


def test_pair_from_config_reads_both_wheels(factory: MockFactory) -> None:
    cfg = EncodersConfig()  # right_invert=True by default: mirrored right wheel
    clock = FakeClock(12.5)
    with WheelEncoders.from_config(cfg, factory, clock=clock) as encoders:
        left_a, left_b = pins(factory, cfg.left_a_pin, cfg.left_b_pin)
        right_a, right_b = pins(factory, cfg.right_a_pin, cfg.right_b_pin)
        drive_cycles(left_a, left_b, 3, forward=True)
        drive_cycles(right_a, right_b, 2, forward=False)  # B leading: mirrored forward
        right_a.drive_low()
        right_a.drive_high()  # a bounce: nets zero
        reading = encoders.read()
        assert reading.edge_age_s is not None and 0.0 <= reading.edge_age_s < 60.0  # gpiozero's mock stamps: monotonic
        # both counts as they stood after the first edge, sampled as the second came (then at most
        # one sample per 10 ms of the edges' stamps)
        assert reading.steps[0][1:] == (1, 0) and 0.0 <= reading.steps[0][0] < 60.0
        assert encoders.read().steps == ()  # taken by the reading before
        assert dataclasses.replace(reading, edge_age_s=None, steps=()) == EncoderReading(
            left_ticks=3 * cfg.ticks_per_rev // cfg.counts_per_rev,
            right_ticks=2 * 4,
            invalid_transitions=0,
            time_s=12.5,
        )


def test_pair_sums_invalid_transitions_and_omits_time_without_clock(
    factory: MockFactory,
) -> None:
    left = WheelEncoder(A_PIN, B_PIN, pin_factory=factory)
    right = WheelEncoder(22, 23, pin_factory=factory)
    with WheelEncoders(left, right) as encoders:
        la, _ = pins(factory)
        ra, _ = pins(factory, 22, 23)
        drive_unseen(la, 0)
        la.drive_high()
        drive_unseen(ra, 0)
        ra.drive_high()
        reading = encoders.read()
        assert reading.invalid_transitions == 2
        assert reading.time_s is None
    assert left.closed and right.closed
    encoders.close()  # idempotent


def test_pair_from_config_releases_left_if_right_fails(factory: MockFactory) -> None:
    cfg = EncodersConfig()
    with InputDevice(cfg.right_b_pin, pin_factory=factory), pytest.raises(GPIOPinInUse):
        WheelEncoders.from_config(cfg, factory)
    with WheelEncoder(cfg.left_a_pin, cfg.left_b_pin, pin_factory=factory):  # left is free
        pass


# --- edge time stamps -----------------------------------------------------------------


def test_a_reading_says_how_old_its_newest_edge_is_by_the_edges_own_stamp() -> None:
    """Edges handled late (a throttled process) still carry the time they happened.

    The simulator's pins are driven with the world's time stamps, as lgpio's callbacks get
    the kernel's: the reading's ``edge_age_s`` is measured from the stamp, not from when the
    callback ran.
    """
    from mazebot.sim.sim_pins import BoundedHistoryPin, SimPinFactory

    now = [100.0]
    factory = SimPinFactory(pin_class=BoundedHistoryPin, time_source=lambda: now[0])
    cfg = EncodersConfig()
    with WheelEncoders.from_config(cfg, factory) as encoders:
        assert encoders.read().edge_age_s is None  # no edge yet
        left_a = factory.pin(cfg.left_a_pin)
        right_a = factory.pin(cfg.right_a_pin)
        now[0] = 100.050  # both edges reach the callbacks 50 ms and 30 ms after they happened
        factory.drive(left_a, 0, time_s=100.000)
        factory.drive(right_a, 0, time_s=100.020)
        reading = encoders.read()
        assert reading.edge_age_s == pytest.approx(0.030)  # the newer of the two wheels' edges
        assert (abs(reading.left_ticks), abs(reading.right_ticks)) == (1, 1)
        now[0] = 100.070  # read again later: the same edges are older
        assert encoders.read().edge_age_s == pytest.approx(0.050)


def test_an_edge_stamp_on_another_clock_gives_no_age() -> None:
    """A stamp the pin factory's clock cannot be compared with is never taken for an age."""
    from mazebot.sim.sim_pins import BoundedHistoryPin, SimPinFactory

    factory = SimPinFactory(pin_class=BoundedHistoryPin, time_source=lambda: 5.0)
    cfg = EncodersConfig()
    with WheelEncoders.from_config(cfg, factory) as encoders:
        factory.drive(factory.pin(cfg.left_a_pin), 0, time_s=1.7e9)  # an epoch stamp against a monotonic clock
        reading = encoders.read()
        assert reading.edge_age_s is None
        assert reading.left_ticks != 0  # the edge still counts

# -- the taps (mazebot.taps): the simulator brings its world up to the read, a listener watches


def test_pair_taps_act_before_the_read_and_hear_each_reading(factory: MockFactory) -> None:
    cfg = EncodersConfig()
    with WheelEncoders.from_config(cfg, factory, clock=FakeClock(3.0)) as encoders:
        left_a, left_b = pins(factory, cfg.left_a_pin, cfg.left_b_pin)
        heard: list[EncoderReading] = []
        encoders.before_read = lambda: drive_cycles(left_a, left_b, 1, forward=True)  # the world moves first
        encoders.on_read += (heard.append,)
        reading = encoders.read()
        assert reading.left_ticks == cfg.ticks_per_rev // cfg.counts_per_rev  # the cycle driven before the read
        assert heard == [reading]
        encoders.before_read = None
        assert encoders.read() == heard[-1] and len(heard) == 2  # no tap acting: the same counts, heard again


def test_a_failing_read_listener_is_logged_and_costs_no_reading(
    factory: MockFactory, caplog: pytest.LogCaptureFixture
) -> None:
    with WheelEncoders.from_config(EncodersConfig(), factory) as encoders:
        heard: list[EncoderReading] = []

        def broken(reading: EncoderReading) -> None:
            raise RuntimeError("a logger's bug")

        encoders.on_read = (broken, heard.append)
        with caplog.at_level("ERROR", logger="mazebot.taps"):
            reading = encoders.read()
        assert heard == [reading]  # the next listener still heard it, and odometry got it
        assert "encoders.on_read" in caplog.text and "a logger's bug" in caplog.text


def test_a_failing_before_read_fails_the_read(factory: MockFactory) -> None:
    # the simulator's world not brought up to date must not pass for a reading of now
    with WheelEncoders.from_config(EncodersConfig(), factory) as encoders:

        def world_broken() -> None:
            raise RuntimeError("simulator step failed")

        encoders.before_read = world_broken
        with pytest.raises(RuntimeError, match="simulator step failed"):
            encoders.read()


def test_edge_samples_hold_whole_steps_when_a_steps_edges_come_wheel_by_wheel() -> None:
    """The quota bench's world sends each 10 ms step's edges with the step's time, the left wheel's first.

    A turn on the spot (left back, right forward, one cycle a step each): every sample must
    hold both wheels' counts at one instant (equal and opposite). Read at a step's first
    edge, the right wheel was a whole step behind the left.
    """
    from mazebot.sim.sim_pins import BoundedHistoryPin, SimPinFactory

    cfg = EncodersConfig()
    factory = SimPinFactory(pin_class=BoundedHistoryPin, time_source=lambda: 100.0)
    with WheelEncoders.from_config(cfg, factory) as encoders:
        left = pins(factory, cfg.left_a_pin, cfg.left_b_pin)
        right = pins(factory, cfg.right_a_pin, cfg.right_b_pin)
        for k in range(1, 21):  # 20 steps of 10 ms
            factory._event_time_s = k * 0.01  # what SimPinFactory.drive sets for each edge of the step
            try:
                drive_cycles(*left, 1, forward=False)
                drive_cycles(*right, 1, forward=False)  # mirrored wheel: counts forward, a turn on the spot
            finally:
                factory._event_time_s = None
        reading = encoders.read()
    assert (reading.left_ticks, reading.right_ticks) == (-80, 80)
    assert len(reading.steps) >= 10  # one a step, or every other one (a step is the sample period)
    assert all(left_ticks == -right_ticks != 0 for _, left_ticks, right_ticks in reading.steps)


def test_a_reading_takes_both_wheels_at_one_instant_while_the_edge_thread_counts() -> None:
    # the edge thread (lgpio's on the Pi) counts both wheels' edges in the order they happened,
    # the wheels in step; a reader the interpreter interrupted between the two wheels found the
    # second one ahead by whatever the thread counted meanwhile (a backlog, in a starved process)
    import sys
    import threading

    from gpiozero.pins.mock import MockFactory

    from mazebot.config import EncodersConfig

    cfg = EncodersConfig()
    factory = MockFactory()
    stop = threading.Event()
    with WheelEncoders.from_config(cfg, factory) as encoders:
        pins = [factory.pin(p) for p in (cfg.left_a_pin, cfg.left_b_pin, cfg.right_a_pin, cfg.right_b_pin)]

        def turn() -> None:  # both wheels forward together, one quarter step at a time each
            levels = ((0, 1), (0, 0), (1, 0), (1, 1))  # the pins rest high (pull-ups): 11 -> 01 -> 00 -> 10 -> 11
            k = 0
            while not stop.is_set():
                a, b = levels[k % 4]
                for pin_a, pin_b in ((pins[0], pins[1]), (pins[2], pins[3])):
                    if pin_a.state != a:
                        pin_a.drive_high() if a else pin_a.drive_low()
                    else:
                        pin_b.drive_high() if b else pin_b.drive_low()
                k += 1

        switch_s = sys.getswitchinterval()
        sys.setswitchinterval(1e-6)  # the interpreter switches threads as often as it can
        thread = threading.Thread(target=turn)
        thread.start()
        try:
            apart = [abs(abs(r.left_ticks) - abs(r.right_ticks)) for r in (encoders.read() for _ in range(20000))]
        finally:
            stop.set()
            thread.join()
            sys.setswitchinterval(switch_s)
    assert max(apart) <= 1, max(apart)
