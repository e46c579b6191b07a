"""The daemon's CPU per part while it does everything at once: exploring, recording, saving, serving viewers.

The benchmark runs (``mazebot bench``) leave out the web server and the recorder; this
script starts the real daemon (``mazebot run --sim --record``) in its own process, connects
``--viewers`` websocket viewers from this process, presses Start with the PIN, lets the robot
explore for ``--seconds`` and then prints the ``cpu`` object of ``/api/status`` as a table
(CPU ms per second since the daemon started, p50/p99 ms per call) and the daemon's whole CPU
time (``/proc/PID/stat`` of the daemon and its children)::

    .venv/bin/python bench/cpu_budget_live.py --viewers 1 --seconds 60 [--out budget.json]

"Web send per viewer" counts every viewer's sends together; divide its ms per second by the
number of viewers for one viewer's share.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import sys
import tempfile
from pathlib import Path
from typing import Any

import aiohttp
from aiohttp.test_utils import unused_port

PIN = "424242"


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process and of its children that have ended (``/proc/PID/stat``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    return sum(int(fields[i]) for i in (11, 12, 13, 14)) / ticks


def _tree_cpu_s(pid: int) -> float:
    """CPU seconds of a process and its living descendants (the loop-closure worker, the fork server)."""
    total = 0.0
    stack = [pid]
    while stack:
        p = stack.pop()
        try:
            total += _cpu_s(p)
            children = Path(f"/proc/{p}/task/{p}/children").read_text().split()
        except OSError:
            continue
        stack.extend(int(c) for c in children)
    return total


async def _viewer(url: str, stop: asyncio.Event, counts: list[int]) -> None:
    async with aiohttp.ClientSession() as session, session.ws_connect(url) as ws:
        while not stop.is_set():
            try:
                msg = await asyncio.wait_for(ws.receive(), 1.0)
            except TimeoutError:
                continue
            if msg.type in (aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.ERROR):
                return
            counts[0] += 1


def _config_file(tmp: str) -> Path:
    """This repository's config.toml with a known PIN and the saved runs in ``tmp``."""
    text = Path("config.toml").read_text()
    text = text.replace('control_token = ""', f'control_token = "{PIN}"', 1)
    text = text.replace('state_dir = ""', f'state_dir = "{tmp}/state"', 1)
    config = Path(tmp) / "config.toml"
    config.write_text(text)
    return config


async def measure(viewers: int, seconds: float) -> dict[str, Any]:
    port = unused_port()
    with tempfile.TemporaryDirectory(prefix="mazebot-budget-") as tmp:
        config = _config_file(tmp)
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "mazebot", "run", "--sim", "--config", str(config), "--host", "127.0.0.1",
            "--port", str(port), "--record", f"{tmp}/run.mcap",
            stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL,
        )
        base = f"http://127.0.0.1:{port}"
        try:
            async with aiohttp.ClientSession() as session:
                for _ in range(300):
                    try:
                        async with session.get(base + "/api/status") as resp:
                            if resp.status == 200:
                                break
                    except aiohttp.ClientError:
                        pass
                    await asyncio.sleep(0.1)
                stop = asyncio.Event()
                counts = [0]
                tasks = [asyncio.create_task(_viewer(base.replace("http", "ws") + "/ws", stop, counts))
                         for _ in range(viewers)]
                cpu0 = _tree_cpu_s(proc.pid)
                async with session.post(base + "/api/start", headers={"X-Mazebot-Token": PIN}) as resp:
                    if resp.status != 200:
                        raise SystemExit(f"start refused: HTTP {resp.status} {await resp.text()}")
                await asyncio.sleep(seconds)
                cpu1 = _tree_cpu_s(proc.pid)
                async with session.get(base + "/api/status") as resp:
                    status = await resp.json()
                stop.set()
                await asyncio.gather(*tasks, return_exceptions=True)
        finally:
            proc.send_signal(signal.SIGINT)
            await proc.wait()
    return {
        "viewers": viewers,
        "seconds": seconds,
        "state": status["state"],
        "coverage": status["coverage"],
        "messages_received": counts[0],
        "daemon_cpu_percent": round(100.0 * (cpu1 - cpu0) / seconds, 1),
        "record": {k: status["record"][k] for k in ("written", "dropped", "saves") if k in status["record"]},
        "cpu": status["cpu"],
        "load_average": os.getloadavg(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--viewers", type=int, default=1)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--out", default=None, help="also write the result as JSON here")
    args = parser.parse_args()
    result = asyncio.run(measure(args.viewers, args.seconds))
    print(f"daemon CPU {result['daemon_cpu_percent']} % of one core (the simulated world included), "
          f"{args.viewers} viewer(s), {args.seconds:.0f} s, state {result['state']}, load {result['load_average']}")
    print("| part | CPU ms per second | p50 ms per call | p99 ms per call | calls |")
    print("|---|---|---|---|---|")
    for part, row in result["cpu"].items():
        print(f"| {part} | {row['cpu_ms_per_s']} | {row['p50_ms']} | {row['p99_ms']} | {row['calls']} |")
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
