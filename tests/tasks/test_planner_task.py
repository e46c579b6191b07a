"""The planner task: a motion half between the stages of a goal half that runs longer than a period.

The goal half of a tick on a large map can take several planner periods of wall time on a
slow CPU; the control loop stops the wheels when the command is 10 control ticks old. The
task then runs a motion half between two of the goal half's stages. On a clock that does
not move inside a tick (the virtual clock) it never does, so what the robot decides there
is what it decided before.
"""

from __future__ import annotations

import asyncio
from collections.abc import Generator

from mazebot.tasks import planner_task


class _Clock:
    def __init__(self) -> None:
        self.t_s = 0.0

    def now_s(self) -> float:
        return self.t_s


class _Pilot:
    """Duck-typed stand-in for :class:`~mazebot.planner.pilot.Pilot`: each goal stage moves the clock."""

    period_s = 0.2

    def __init__(self, clock: _Clock, stage_s: float, stages: int = 4) -> None:
        self.clock, self.stage_s, self.stages = clock, stage_s, stages
        self.last_command_s = 0.0
        self.log: list[str] = []

    def plan_steps(self, state: object, now_s: float) -> Generator[None, None, bool]:
        for k in range(self.stages):
            self.clock.t_s += self.stage_s
            self.log.append(f"stage {k}")
            yield
        return True

    def motion_due(self, now_s: float) -> bool:
        return now_s - self.last_command_s >= self.period_s

    def interim_drive_steps(self, state: object, now_s: float) -> Generator[None, None, None]:
        self.log.append("drive")
        yield
        self.last_command_s = now_s


def _goal_half(stage_s: float) -> list[str]:
    clock = _Clock()
    pilot = _Pilot(clock, stage_s)
    cpu_s = [0.0]
    follow = asyncio.run(planner_task._goal_half(object(), clock, pilot, cpu_s))  # type: ignore[arg-type]
    assert follow is True
    return pilot.log


def test_a_goal_half_longer_than_a_period_gets_a_motion_half_between_its_stages() -> None:
    # 4 stages of 0.15 s: due after the 2nd (0.30 s since the command), again after the 4th (0.30 s)
    assert _goal_half(0.15) == ["stage 0", "stage 1", "drive", "stage 2", "stage 3", "drive"]


def test_a_goal_half_on_a_clock_that_does_not_move_runs_no_motion_half() -> None:
    assert _goal_half(0.0) == ["stage 0", "stage 1", "stage 2", "stage 3"]


def test_the_pilot_drives_between_stages_only_after_a_goal_half_that_chose_to_drive() -> None:
    from mazebot.config import Config
    from mazebot.planner.pilot import Pilot, PilotParams
    from mazebot.state import RunState, SharedState

    pilot = Pilot(PilotParams.from_config(Config()))
    state = SharedState()
    assert not pilot.motion_due(1e9)  # nothing followed yet
    state.run_state = RunState.EXPLORING
    assert pilot.plan(state, 1.0) is False  # no map yet: it holds the robot
    assert state.motion_command is not None and state.motion_command.v_mps == 0.0
    assert pilot.last_command_s == 1.0
    assert not pilot.motion_due(1e9)  # a hold leaves nothing to follow between stages


def test_a_goal_half_a_few_milliseconds_longer_than_the_last_sets_off_no_extra_motion_half() -> None:
    import numpy as np

    from mazebot.config import Config
    from mazebot.planner.pilot import DriveInputs, Pilot, PilotParams

    params = PilotParams.from_config(Config())
    pilot = Pilot(params)
    pilot._last_drive_inputs = DriveInputs(np.zeros((4, 4), dtype=np.int8), (0.0, 0.0), 0.02, (0.5, 0.5))
    pilot.last_command_s = 10.0  # the previous tick's motion half, after its goal half
    # this tick's goal half runs 5 ms longer than the previous one: the regular motion half is right behind
    assert not pilot.motion_due(10.0 + params.period_s + 0.005)
    # a whole control period late: the control loop would run a tick on a stale command
    assert pilot.motion_due(10.0 + params.period_s + params.control_period_s)
