"""The boundary between the world's process and the daemon's: edges, throttles, the GPIO thread.

The real encoder code (:class:`mazebot.io.encoders.WheelEncoders`) counts what the GPIO
thread drives from the world's recorded edges; the count must equal what the same
encoders count when they sit on the world's own pins (the in-process simulator).
"""

from __future__ import annotations

import math
import multiprocessing
import random
import time

import pytest

from mazebot.config import Config
from mazebot.io.encoders import WheelEncoders
from mazebot.sim.encoder_signals import QuadratureSignal
from mazebot.sim.remote_devices import GpioEdgeThread, PipeMotorKit
from mazebot.sim.world_process import (
    EDGES_TIME,
    EdgeRecordingFactory,
    decode_throttle,
    edge_byte,
    encode_throttle,
    encoder_pins,
)


def test_throttles_cross_the_wire_unchanged_and_coasting_stays_none() -> None:
    for channel, throttle in ((1, 0.5), (2, -1.0), (3, 0.0), (4, None), (1, 0.123456789)):
        assert decode_throttle(encode_throttle(channel, throttle)) == (channel, throttle)


def test_the_world_records_each_driven_edge_in_order_but_not_a_lost_one() -> None:
    config = Config()
    pins = encoder_pins(config)
    factory = EdgeRecordingFactory(pins)
    a, b = factory.pin(pins[0]), factory.pin(pins[1])
    a.drive_high()  # already high? MockPin's default is low (no pull): this is an edge
    a.drive_high()  # no change: no edge
    b.drive_high()
    a.drive_low()
    b._change_state(False)  # the level changes without an interrupt: lost
    a.drive_high()
    assert factory.take_edges() == bytes([edge_byte(0, 1), edge_byte(1, 1), edge_byte(0, 0), edge_byte(0, 1)])
    assert factory.take_edges() == b""  # taken once
    factory.pin(27).drive_high()  # not an encoder pin: never on the wire
    assert factory.take_edges() == b""


class Wheels:
    """The world's two wheels as quadrature signals on ``factory``'s pins."""

    def __init__(self, factory: EdgeRecordingFactory, config: Config) -> None:
        enc = config.encoders
        self.left = QuadratureSignal(factory, enc.left_a_pin, enc.left_b_pin, enc.counts_per_rev,
                                     idle_high=enc.pull_up)
        self.right = QuadratureSignal(factory, enc.right_a_pin, enc.right_b_pin, enc.counts_per_rev,
                                      idle_high=enc.pull_up)

    def turn(self, left_rad: float, right_rad: float, time_s: float | None = None) -> None:
        """Both wheels to these angles, their edges at ``time_s`` (None: now)."""
        for signal, angle in ((self.left, left_rad), (self.right, right_rad)):
            for _, step in signal.edges_to(angle):
                signal.emit(step, time_s)


def test_the_daemons_encoders_count_the_worlds_edges_through_the_gpio_thread() -> None:
    """Both wheels forward, back and forward again, through a real pipe and the thread."""
    config = Config()
    rng = random.Random(3)
    angles, left, right = [], 0.0, 0.0
    for step in range(400):
        sign = 1 if step < 200 or step >= 300 else -1
        left += sign * rng.uniform(0.0, 0.05)
        right += sign * rng.uniform(0.0, 0.06)
        angles.append((left, right))
    # the reference: the same encoders on the world's own pins (as the in-process simulator has them)
    reference_factory = EdgeRecordingFactory(encoder_pins(config))
    with WheelEncoders.from_config(config.encoders, reference_factory) as reference:
        wheels = Wheels(reference_factory, config)
        for angle in angles:
            wheels.turn(*angle)
        expected = reference.read()
    assert abs(expected.left_ticks) > 500 and abs(expected.right_ticks) > 500  # (a wheel may count inverted)

    world = EdgeRecordingFactory(encoder_pins(config))
    rx, tx = multiprocessing.Pipe(duplex=False)
    daemon_pins = GpioEdgeThread.pin_factory()
    with WheelEncoders.from_config(config.encoders, daemon_pins) as encoders:
        thread = GpioEdgeThread(rx, daemon_pins, encoder_pins(config))
        thread.start()
        wheels = Wheels(world, config)  # its idle levels are the first message
        sent = 0
        step_s = time.monotonic() - 1.0  # the steps happened a second ago: the edges reach the daemon late
        for angle in angles:  # one message per world step, its edges with their times, as the world sends them
            step_s += 0.001
            wheels.turn(*angle, time_s=step_s)
            message = world.take_message()
            if message:
                tx.send_bytes(message)
                sent += (len(message) - EDGES_TIME.size) // 5
        deadline = time.monotonic() + 10.0
        while thread.edges < sent and time.monotonic() < deadline:
            time.sleep(0.01)
        cpu_s = thread.cpu_s()  # its own clock, read from this thread: what driving the edges cost it
        assert cpu_s is not None and 0 < cpu_s <= time.process_time()
        tx.close()  # the world is gone: the thread ends once it has driven every edge
        thread.join(10.0)
        assert not thread.is_alive()
        assert thread.cpu_s() is None
        got = encoders.read()
        age_s = time.monotonic() - step_s
    assert thread.edges == sent > 2000
    assert (got.left_ticks, got.right_ticks) == (expected.left_ticks, expected.right_ticks)
    assert got.invalid_transitions == 0
    # the counts are dated by the world's step, not by when the thread drove them
    assert got.edge_age_s is not None and age_s - 0.05 <= got.edge_age_s <= age_s


def test_the_motor_kit_checks_the_range_and_sends_every_write_it_accepts() -> None:
    rx, tx = multiprocessing.Pipe(duplex=False)
    kit = PipeMotorKit(tx)
    kit.motor1.throttle = 0.25
    kit.motor2.throttle = None
    with pytest.raises(ValueError, match="between -1"):
        kit.motor1.throttle = 1.5  # as adafruit_motor's DCMotor: refused, not clamped, not sent
    assert kit.writes_sent == 2
    assert decode_throttle(rx.recv_bytes()) == (1, 0.25)
    assert decode_throttle(rx.recv_bytes()) == (2, None)
    assert not rx.poll()
    rx.close()
    with pytest.raises(OSError, match="motor HAT is gone"):
        kit.motor1.throttle = 0.0  # the world is gone: as an I2C bus that stopped answering
    assert math.isclose(kit.motor1.throttle or 0.0, 0.25)
