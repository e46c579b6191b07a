"""The simulator's backend reaches the daemon's drivers through their taps, not by patching them."""

from __future__ import annotations

import asyncio
from contextlib import AsyncExitStack

from mazebot.clock import RealClock
from mazebot.config import Config
from mazebot.io.encoders import WheelEncoders
from mazebot.sim.backend import sim_hardware_builder, simulated_robot


async def test_each_encoder_reading_shows_the_world_at_the_moment_of_the_read() -> None:
    config, clock = Config(), RealClock()
    async with AsyncExitStack() as stack:
        hardware = await sim_hardware_builder(size=(3, 3), seed=1)(config, clock, stack)
        robot = simulated_robot(hardware)
        encoders = hardware.encoders
        assert isinstance(encoders, WheelEncoders) and robot.encoders is encoders
        assert "read" not in vars(encoders)  # the class's own method: nothing assigned over it
        await asyncio.sleep(0.1)  # nobody steps the world meanwhile (its task is not started here)
        encoders.read()
        assert robot.time_s is not None
        assert robot.time_s >= clock.now_s() - config.sim.step_period_s - 0.05  # caught up by before_read
