"""Start and stop from a viewer reach the (simulated) motor HAT, through the real daemon.

How fast (milliseconds, hundreds of presses) is ``bench/stop_latency.py``'s figure: a test on a
shared machine checks what happened, not how long it took.
"""

from __future__ import annotations

import asyncio
from typing import Any

import aiohttp
import pytest
from aiohttp.test_utils import unused_port

from mazebot.config import Config
from mazebot.main import Hardware, run_daemon
from mazebot.sim.backend import sim_hardware_builder
from mazebot.state import RunState, SharedState
from mazebot.tasks.supervisor import Supervisor

pytestmark = pytest.mark.slow  # the daemon on the simulated robot in real time

PIN = "2468"


async def _first_write_after(kit: Any, t0: float, moving: bool, timeout_s: float = 30.0) -> float:
    """Clock time of the first write to the HAT after ``t0`` that moves (or stops) a wheel."""
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout_s
    while loop.time() < end:
        for w in list(kit.command_log):
            if w.time_s >= t0 and (w.throttle != 0.0) == moving:
                return w.time_s
        await asyncio.sleep(0.002)
    raise AssertionError(f"no {'moving' if moving else 'stopping'} write within {timeout_s} s")


async def test_start_and_stop_over_the_websocket_reach_the_motors() -> None:
    config = Config()
    config.web.host, config.web.port, config.web.control_token = "127.0.0.1", unused_port(), PIN
    started: dict[str, Any] = {}

    def on_started(hw: Hardware, state: SharedState, sup: Supervisor) -> None:
        started.update(hw=hw, state=state, sup=sup)

    ready = asyncio.Event()
    # the planner is left out: the test stands in for it with a direct throttle command, so
    # what is measured is the path from the page's button to the motor HAT
    daemon = asyncio.create_task(run_daemon(config, sim_hardware_builder(), ready=ready, autonomous=False,
                                            install_signal_handlers=False, on_started=on_started))
    await asyncio.wait_for(ready.wait(), 10)
    state: SharedState = started["state"]
    kit = started["hw"].sim.kit
    loop = asyncio.get_running_loop()
    try:
        async with aiohttp.ClientSession() as session, session.ws_connect(
            f"http://127.0.0.1:{config.web.port}/ws"
        ) as ws:
            for _ in range(3):  # hello, full map
                msg = await ws.receive()
                if msg.type == aiohttp.WSMsgType.BINARY:
                    break
            # what the planner would want once running
            state.throttle_command = (0.5, 0.5, loop.time() + 60.0)
            t0 = loop.time()
            await ws.send_json({"type": "start", "token": PIN})
            await _first_write_after(kit, t0, moving=True)
            assert state.run_state is RunState.EXPLORING
            await asyncio.sleep(0.2)
            t0 = loop.time()
            await ws.send_json({"type": "stop", "token": PIN})
            await _first_write_after(kit, t0, moving=False)
            await asyncio.sleep(0.1)
            assert state.run_state is RunState.STOPPED
            assert kit.motor1.throttle == 0.0 and kit.motor2.throttle == 0.0
    finally:
        started["sup"].request_stop("test over")
        assert await asyncio.wait_for(daemon, 10) == 0
