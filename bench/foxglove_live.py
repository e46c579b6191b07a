"""The control loop's lateness and the daemon's CPU with Foxglove live on (one client) and off.

Runs the real daemon on the real clock and the simulated robot (``run_daemon`` with
``sim_hardware_builder``, the planner exploring the default maze), in this process, for
``--seconds`` of exploration, alternating ``[foxglove] enabled`` off and on ``--runs`` times.
With it on, one Foxglove client in a process of its own (aiohttp, subprotocol
``foxglove.sdk.v1``) subscribes to every channel and counts what arrives, as Foxglove would.
Prints per run: control-tick lateness p50/p99/max (ms past the 20 Hz deadline, from
``state.control_lateness_ms``), the process's CPU per second (the simulated world, SLAM,
planner and the SDK's Rust threads included), and the messages and bytes the client got::

    nice -n 19 .venv/bin/python bench/foxglove_live.py --runs 3 --seconds 40
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import struct
import sys
import time
from collections import deque

import aiohttp
import numpy as np
from aiohttp.test_utils import unused_port

from mazebot.config import Config
from mazebot.main import run_daemon
from mazebot.sim.backend import sim_hardware_builder
from mazebot.state import RunState, SharedState


async def client(port: int, seconds: float) -> None:
    """Subscribe to every advertised channel; print ``{"messages": N, "bytes": B}`` at the end."""
    messages = size = 0
    async with aiohttp.ClientSession() as session:
        for _ in range(100):
            try:
                ws = await session.ws_connect(f"ws://127.0.0.1:{port}/", protocols=("foxglove.sdk.v1",))
                break
            except aiohttp.ClientError:
                await asyncio.sleep(0.1)
        channels: dict[str, dict] = {}
        end = time.monotonic() + seconds
        subscribed = False
        while time.monotonic() < end:
            try:
                msg = await ws.receive(timeout=0.5)
            except TimeoutError:
                continue
            if msg.type is aiohttp.WSMsgType.TEXT:
                op = json.loads(msg.data)
                if op["op"] == "advertise":
                    channels.update({c["topic"]: c for c in op["channels"]})
                    if not subscribed and len(channels) >= 11:
                        subs = [{"id": i, "channelId": c["id"]} for i, c in enumerate(channels.values())]
                        await ws.send_str(json.dumps({"op": "subscribe", "subscriptions": subs}))
                        subscribed = True
            elif msg.type is aiohttp.WSMsgType.BINARY:
                struct.unpack_from("<BIQ", msg.data)
                messages += 1
                size += len(msg.data)
            else:
                break
        await ws.close()
    print(json.dumps({"messages": messages, "bytes": size, "channels": len(channels)}), flush=True)


async def one_run(foxglove: bool, seconds: float) -> dict:
    config = Config()
    config.web.host = "127.0.0.1"
    config.web.port = unused_port()
    config.foxglove.enabled = foxglove
    config.foxglove.port = unused_port()
    state = SharedState()
    state.control_lateness_ms = deque(maxlen=100_000)
    ready = asyncio.Event()
    started: dict = {}
    daemon = asyncio.create_task(run_daemon(
        config, sim_hardware_builder(), ready=ready, install_signal_handlers=False, state=state,
        on_started=lambda hw, st, sup: started.update(sup=sup),
    ))
    await asyncio.wait_for(ready.wait(), 30)
    proc = None
    if foxglove:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, __file__, "--client", str(config.foxglove.port), "--seconds", str(seconds + 1),
            stdout=asyncio.subprocess.PIPE,
        )
        await asyncio.sleep(1.0)  # connected and subscribed
    state.control_lateness_ms.clear()
    await state.commands.put("start")
    cpu0, t0 = time.process_time(), time.monotonic()
    await asyncio.sleep(seconds)
    cpu_s, wall_s = time.process_time() - cpu0, time.monotonic() - t0
    lateness = np.asarray(state.control_lateness_ms, dtype=float)
    got = {}
    if proc is not None:
        out, _ = await proc.communicate()
        got = json.loads(out.decode().strip().splitlines()[-1])
    started["sup"].request_stop("bench over")
    await asyncio.wait_for(daemon, 30)
    return {
        "foxglove": foxglove,
        "state": state.run_state.value if isinstance(state.run_state, RunState) else str(state.run_state),
        "ticks": int(lateness.size),
        "p50_ms": round(float(np.percentile(lateness, 50)), 2),
        "p99_ms": round(float(np.percentile(lateness, 99)), 2),
        "max_ms": round(float(lateness.max()), 2),
        "cpu_percent": round(100.0 * cpu_s / wall_s, 1),
        "foxglove_part": state.cpu.part("foxglove live").summary(wall_s) if foxglove else None,
        **got,
    }


async def main(runs: int, seconds: float) -> None:
    results = []
    for i in range(runs):
        for foxglove in (False, True) if i % 2 == 0 else (True, False):
            r = await one_run(foxglove, seconds)
            results.append(r)
            print(json.dumps(r), flush=True)
    for on in (False, True):
        rows = [r for r in results if r["foxglove"] is on]
        print(f"foxglove {'on ' if on else 'off'}: median p99 {statistics.median(r['p99_ms'] for r in rows)} ms, "
              f"median p50 {statistics.median(r['p50_ms'] for r in rows)} ms, "
              f"median CPU {statistics.median(r['cpu_percent'] for r in rows)} % of one core")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=40.0)
    parser.add_argument("--client", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.client is not None:
        asyncio.run(client(args.client, args.seconds))
    else:
        asyncio.run(main(args.runs, args.seconds))
