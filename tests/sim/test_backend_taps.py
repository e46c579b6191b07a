"""The simulator's backend reaches the daemon's drivers through their taps, not by patching them."""

from __future__ import annotations

import asyncio
from contextlib import AsyncExitStack

from mazebot.clock import RealClock
from mazebot.config import Config
from mazebot.io.encoders import WheelEncoders
from mazebot.sim.backend import sim_hardware_builder, simulated_robot
from tests.sim.test_sim_robot import lidar_lead_over_physics


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


def test_the_lidar_on_its_own_timer_measures_no_pose_the_physics_has_not_reached() -> None:
    """On a slowed virtual CPU the emulator's streaming timer can fire after a loop stall
    before the simulator's tick: it used to measure every sample of the stall from the
    robot's last pose while the robot turned on (up to 0.26 s held), so a revolution
    contradicted the map and the robot was said lost. The world is stepped first now."""
    import contextlib

    from mazebot.sim.virtual_time import SlowCpu, run_virtual

    config = Config()
    slow = SlowCpu(callback_cost_s=0.0045, stall_every_s=0.5, stalls_s=(0.1, 0.25, 0.15))
    lead: list[list[float]] = []  # the head's lead over the physics, filled while the run goes on

    async def run() -> int:
        clock = RealClock()  # the virtual loop's time
        async with AsyncExitStack() as stack:
            hardware = await sim_hardware_builder(size=(4, 4), seed=2)(config, clock, stack)
            robot = simulated_robot(hardware)
            robot.kit.motor1.throttle, robot.kit.motor2.throttle = 0.5, 0.5  # spins in place
            lead.append(lidar_lead_over_physics(robot))
            ((name, factory),) = hardware.extra_tasks
            sim = asyncio.create_task(factory(), name=name)
            scans_seen = 0
            try:
                scans = hardware.lidar.scans()
                async with contextlib.aclosing(scans):  # type: ignore[type-var]
                    async for _ in scans:
                        scans_seen += 1
                        if scans_seen == 15:  # ~3 s: five stalls
                            break
            finally:
                sim.cancel()
            return scans_seen

    assert run_virtual(asyncio.wait_for(run(), 60.0), slow=slow) == 15
    (ahead_s,) = lead
    assert len(ahead_s) > 100
    # within one physics sub-step (2.5 ms at 400 Hz), the physics' own resolution
    assert max(ahead_s) <= 1.0 / 400.0, max(ahead_s)
