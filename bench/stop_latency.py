"""Stop button -> both motors at zero, pressed hundreds of times on the running daemon.

The whole daemon (``run_daemon``: lidar and encoder drivers, SLAM, the planner, the control
loop, the aiohttp server) runs on the simulated robot in real time. A viewer in another
process, like the phone, connects to ``/ws`` and presses start, lets the robot explore for a
random 0.4-1.0 s, presses stop, waits 0.4 s, and so on ``--presses`` times. Latency of a press
= the first moment the fake motor HAT holds both drive throttles at zero (0 or coasting) minus
the moment just before the stop frame went into the viewer's socket (``time.monotonic`` on
both sides: the HAT's clock is the loop's, which is the same system-wide monotonic clock).
Presses that found the wheels already stopped (the planner pausing) are counted, not timed.

    .venv/bin/python bench/stop_latency.py --presses 250 [--pin 0,1] --out /tmp/stop.json
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import sys
import time
from collections import deque
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np
from aiohttp.test_utils import unused_port

from mazebot.config import Config
from mazebot.main import Hardware, run_daemon
from mazebot.sim.backend import sim_hardware_builder
from mazebot.state import SharedState
from mazebot.tasks.supervisor import Supervisor

PIN = "2468"


def _pin(cpu: int | None, who: str) -> None:
    """Keep this process (and what it starts from now on) on one CPU."""
    if cpu is not None:
        os.sched_setaffinity(0, {cpu})
        print(f"stop_latency: {who} pinned to CPU {cpu} (os.sched_setaffinity)", file=sys.stderr, flush=True)


# -- the viewer's process ------------------------------------------------------------------


async def _presser(url: str, presses: int, seed: int) -> dict[str, Any]:
    """Start, drive a while, stop; the send time of every stop frame and the server's replies."""
    rng = random.Random(seed)
    replies: list[dict[str, Any]] = []
    stops_s: list[float] = []
    starts_s: list[float] = []

    async def read(ws: aiohttp.ClientWebSocketResponse) -> None:
        async for msg in ws:
            if msg.type == aiohttp.WSMsgType.TEXT:
                m = json.loads(msg.data)
                if m.get("type") in ("reply", "error"):
                    replies.append(m)

    async with aiohttp.ClientSession() as session, session.ws_connect(url, max_msg_size=0) as ws:
        reader = asyncio.ensure_future(read(ws))
        await asyncio.sleep(1.0)
        for _ in range(presses):
            starts_s.append(time.monotonic())
            await ws.send_str(json.dumps({"type": "start", "token": PIN}))
            await asyncio.sleep(rng.uniform(0.4, 1.0))
            stops_s.append(time.monotonic())
            await ws.send_str(json.dumps({"type": "stop", "token": PIN}))
            await asyncio.sleep(0.4)
        await asyncio.sleep(0.5)
        reader.cancel()
    accepted = sum(1 for r in replies if r.get("ok"))
    refused = [r for r in replies if not r.get("ok")]
    return {"starts_s": starts_s, "stops_s": stops_s, "accepted": accepted, "refused": refused[:5],
            "refused_count": len(refused)}


# -- the analysis --------------------------------------------------------------------------


def stop_latencies_s(writes: list[tuple[float, int, float | None]], stops_s: list[float],
                     channels: tuple[int, ...]) -> tuple[list[float], int, int]:
    """(latency of each press that found a wheel turning, presses that found them stopped, never stopped).

    ``writes`` are the HAT's (time s, channel, throttle) in order; a throttle of 0 or None
    (coasting) is a wheel at zero.
    """
    times = np.array([w[0] for w in writes])
    latencies: list[float] = []
    idle = never = 0
    for t0 in stops_s:
        k = int(np.searchsorted(times, t0, side="left"))
        last = {c: None for c in channels}
        for _t, c, v in writes[:k]:
            last[c] = v
        if all(not last[c] for c in channels):
            idle += 1
            continue
        for t, c, v in writes[k:]:
            last[c] = v
            if all(not last[ch] for ch in channels):
                latencies.append(t - t0)
                break
        else:
            never += 1
    return latencies, idle, never


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presses", type=int, default=250)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--size", type=int, default=8, help="side of the generated maze in cells (room to explore)")
    ap.add_argument("--pin", default=None, metavar="D,C",
                    help="pin the daemon to CPU D and the pressing viewer to CPU C (os.sched_setaffinity)")
    ap.add_argument("--out", default="stop_latency.json")
    ap.add_argument("--presser-child", nargs=3, metavar=("URL", "PRESSES", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    daemon_cpu, viewer_cpu = (None, None) if not args.pin else (int(x) for x in args.pin.split(","))
    if args.presser_child:
        url, presses, out = args.presser_child
        _pin(viewer_cpu, "viewer")
        Path(out).write_text(json.dumps(asyncio.run(_presser(url, int(presses), args.seed))))
        return 0

    _pin(daemon_cpu, "daemon")
    config = Config()
    config.web.host, config.web.port, config.web.control_token = "127.0.0.1", unused_port(), PIN
    out_path = Path(args.out)
    child_out = out_path.with_suffix(".presser.json")
    started: dict[str, Any] = {}

    def on_started(hardware: Hardware, state: SharedState, supervisor: Supervisor) -> None:
        kit = hardware.sim.kit
        kit.command_log = deque()  # every write of the run, not the last 10 000
        started.update(kit=kit, state=state)

        async def session() -> None:
            await asyncio.sleep(2.0)  # a first map before the first start
            cmd = [sys.executable, __file__, "--presser-child", f"ws://127.0.0.1:{config.web.port}/ws",
                   str(args.presses), str(child_out), "--seed", str(args.seed)]
            cmd += ["--pin", args.pin] if args.pin else []
            proc = await asyncio.create_subprocess_exec(*cmd)
            started["cpu0"] = time.process_time()
            await proc.wait()
            started["daemon_cpu_s"] = time.process_time() - started["cpu0"]
            started["load_average"] = os.getloadavg()
            started["run_state"] = state.run_state.value
            supervisor.request_stop("stop bench over")

        supervisor.start("bench-session", session)

    builder = sim_hardware_builder(seed=args.seed, size=(args.size, args.size))
    t_wall = time.monotonic()
    code = asyncio.run(run_daemon(config, builder, install_signal_handlers=False, on_started=on_started))
    t_wall = time.monotonic() - t_wall
    child = json.loads(child_out.read_text())
    child_out.unlink()
    writes = [(w.time_s, w.channel, w.throttle) for w in started["kit"].command_log]
    channels = (config.motors.left_channel, config.motors.right_channel)
    lat_s, idle, never = stop_latencies_s(writes, child["stops_s"], channels)
    lat_ms = np.array(lat_s) * 1000.0
    result: dict[str, Any] = {
        "command": " ".join(sys.argv),
        "presses": args.presses,
        "timed": int(lat_ms.size),
        "found_wheels_stopped": idle,
        "never_stopped": never,
        "stop_to_motors_zero_ms": None if not lat_ms.size else {
            "p50": round(float(np.percentile(lat_ms, 50)), 2), "p99": round(float(np.percentile(lat_ms, 99)), 2),
            "max": round(float(lat_ms.max()), 2), "min": round(float(lat_ms.min()), 2)},
        "accepted_commands": child["accepted"], "refused_commands": child["refused_count"],
        "refused_examples": child["refused"],
        "daemon_exit": code, "daemon_cpu_s": round(started["daemon_cpu_s"], 2),
        "wall_s": round(t_wall, 1), "load_average": started["load_average"],
        "pinned": None if daemon_cpu is None else {"daemon_cpu": daemon_cpu, "viewer_cpu": viewer_cpu},
        "final_run_state": started["run_state"], "hat_writes": len(writes), "maze_cells": [args.size, args.size],
    }
    out_path.write_text(json.dumps({**result, "latencies_ms": [round(x, 3) for x in lat_ms.tolist()]}, indent=2))
    print(json.dumps(result, indent=2))
    return 0 if never == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
