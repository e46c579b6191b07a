"""Fleet figures: what publishing on Zenoh costs the robot, and how late the watcher's page is.

    .venv/bin/python bench/fleet_bench.py overhead --runs 3 --seconds 40 [--out fleet_overhead.json]
    .venv/bin/python bench/fleet_bench.py latency --robots 3 --seconds 60 [--out fleet_latency.json]

``overhead``: the simulated robot exploring its 6x6 maze (seed 1) on the real clock, in a
fresh process per run, alternately without ``[zenoh]`` and with it on and one watcher
(``mazebot watch`` in another process, connected by an explicit loopback endpoint). Per run:
the control loop's p50/p99/max lateness over the measured window, the daemon's process CPU
(all threads) per robot-second, and the Zenoh parts of its CPU budget.

``latency``: ``--robots`` ``mazebot run --sim`` processes with ``[zenoh]`` on (each its own
seed) and one ``mazebot watch``; all started exploring. This process opens each robot's own
page websocket and the same robot's page on the watcher, and notes when each packet
(by robot and sequence number) arrives on each (one monotonic clock). The figure per robot
is the p50/p95/max of (arrival on the watcher's page - arrival on the robot's page).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np
from aiohttp.test_utils import unused_port

PIN = "2468"
ROOT = Path(__file__).resolve().parent.parent


def _watch_cmd(port: int, endpoints: list[str]) -> list[str]:
    cmd = [sys.executable, "-m", "mazebot", "watch", "--port", str(port), "--no-multicast", "--log-level", "warning"]
    for e in endpoints:
        cmd += ["--connect", e]
    return cmd


def _spawn(cmd: list[str], env: dict[str, str] | None = None, nice: int = 0) -> subprocess.Popen[bytes]:
    """A child process, output discarded (starting one takes a millisecond: fine on the loop here).

    ``nice`` lowers its priority: a watcher that stands for another computer should not take
    this machine's cores from the robot it watches.
    """
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env, cwd=ROOT,
                            preexec_fn=(lambda: os.nice(nice)) if nice else None)


# -- overhead ---------------------------------------------------------------------------------


def _overhead_child(zenoh_on: bool, seconds: float, out: Path, watcher_nice: int) -> None:
    from mazebot.config import Config
    from mazebot.main import run_daemon
    from mazebot.sim.backend import sim_hardware_builder

    config = Config()
    config.web.host, config.web.port, config.web.control_token = "127.0.0.1", unused_port(), PIN
    config.persist.enabled = False
    zport = unused_port()
    if zenoh_on:
        config.zenoh.enabled = True
        config.zenoh.robot_name = "bench"
        config.zenoh.listen = [f"tcp/127.0.0.1:{zport}"]
        config.zenoh.multicast_scouting = False
    result: dict[str, Any] = {"zenoh": zenoh_on, "seconds": seconds}

    def on_started(hardware: Any, state: Any, supervisor: Any) -> None:
        async def session() -> None:
            watcher = None
            if zenoh_on:
                watcher = _spawn(_watch_cmd(unused_port(), [f"tcp/127.0.0.1:{zport}"]), nice=watcher_nice)
            await asyncio.sleep(3.0)  # the watcher's imports and session
            state.commands.put_nowait("start")
            await asyncio.sleep(1.0)
            state.control_lateness_ms.clear()
            cpu0, t0 = time.process_time(), time.monotonic()
            await asyncio.sleep(seconds)
            lateness = np.array(state.control_lateness_ms)
            result["control_lateness_ms"] = {"p50": float(np.percentile(lateness, 50)),
                                             "p99": float(np.percentile(lateness, 99)),
                                             "max": float(lateness.max()), "n": int(lateness.size)}
            wall = time.monotonic() - t0
            result["cpu_ms_per_robot_s"] = 1e3 * (time.process_time() - cpu0) / wall
            table = state.cpu.table(state.cpu.age_s(time.monotonic()))
            result["zenoh_parts"] = {k: table[k] for k in ("zenoh poll", "zenoh publish")}
            result["state"] = state.run_state.value
            result["load_average"] = os.getloadavg()
            if watcher is not None:
                watcher.terminate()
                watcher.wait(10)
            supervisor.request_stop("bench over")

        supervisor.start("bench-session", session)

    builder = sim_hardware_builder(seed=1, size=(6, 6))
    asyncio.run(run_daemon(config, builder, install_signal_handlers=False, on_started=on_started))
    out.write_text(json.dumps(result))


def overhead(args: argparse.Namespace) -> dict[str, Any]:
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.runs):
            for on in (False, True):
                out = Path(tmp) / f"run{i}-{int(on)}.json"
                env = {**os.environ, "XDG_STATE_HOME": tmp}
                subprocess.run([sys.executable, __file__, "overhead-child", str(int(on)), str(args.seconds), str(out),
                                str(args.watcher_nice)],
                               check=True, env=env, cwd=ROOT)
                runs.append(json.loads(out.read_text()))
                r = runs[-1]
                print(f"zenoh={on}: p99 {r['control_lateness_ms']['p99']:.2f} ms, "
                      f"CPU {r['cpu_ms_per_robot_s']:.1f} ms/s", flush=True)
    summary = {}
    for on in (False, True):
        mine = [r for r in runs if r["zenoh"] is on]
        summary["with" if on else "without"] = {
            "median_p99_lateness_ms": statistics.median(r["control_lateness_ms"]["p99"] for r in mine),
            "median_cpu_ms_per_robot_s": statistics.median(r["cpu_ms_per_robot_s"] for r in mine)}
    return {"runs": runs, "summary": summary}


# -- latency ----------------------------------------------------------------------------------


async def _listen(url: str, name: str, where: str, arrivals: dict[tuple[str, str], dict[int, float]],
                  end_s: float) -> None:
    log = arrivals.setdefault((name, where), {})
    from mazebot.web.protocol import decode_packet

    async with aiohttp.ClientSession() as http, http.ws_connect(url) as ws:
        while time.monotonic() < end_s:
            try:
                msg = await ws.receive(timeout=max(0.1, end_s - time.monotonic()))
            except TimeoutError:
                break
            if msg.type == aiohttp.WSMsgType.BINARY:
                now = time.monotonic()
                seq = int.from_bytes(msg.data[4:8], "little")
                log.setdefault(seq, now)
                decode_packet(msg.data)  # a real client decodes (the page does too)
            elif msg.type in (aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.ERROR):
                break


async def _latency(args: argparse.Namespace, tmp: str) -> dict[str, Any]:
    names = [f"r{i + 1}" for i in range(args.robots)]
    procs, ports = [], {}
    env = {**os.environ, "XDG_STATE_HOME": tmp}
    for i, name in enumerate(names):
        web, zp = unused_port(), unused_port()
        ports[name] = (web, zp)
        cfg = Path(tmp) / f"{name}.toml"
        cfg.write_text(f'[web]\ncontrol_token = "{PIN}"\n[persist]\nenabled = false\n[zenoh]\nenabled = true\n'
                       f'robot_name = "{name}"\nlisten = ["tcp/127.0.0.1:{zp}"]\nmulticast_scouting = false\n')
        procs.append(_spawn([sys.executable, "-m", "mazebot", "run", "--sim", "--seed", str(i + 1),
                             "--config", str(cfg), "--host", "127.0.0.1", "--port", str(web)], env))
    wport = unused_port()
    procs.append(_spawn(_watch_cmd(wport, [f"tcp/127.0.0.1:{p[1]}" for p in ports.values()]), env))
    try:
        async with aiohttp.ClientSession() as http:
            deadline = time.monotonic() + 60
            while True:
                try:
                    robots = await (await http.get(f"http://127.0.0.1:{wport}/api/robots")).json()
                    if len([r for r in robots if r["seq"] > 0]) == len(names):
                        break
                except aiohttp.ClientError:
                    pass
                assert time.monotonic() < deadline, "the watcher did not find every robot within 60 s"
                await asyncio.sleep(0.5)
            for name in names:
                await http.post(f"http://127.0.0.1:{ports[name][0]}/api/start", headers={"X-Mazebot-Token": PIN})
        arrivals: dict[tuple[str, str], dict[int, float]] = {}
        end_s = time.monotonic() + args.seconds
        await asyncio.gather(*(
            _listen(url, name, where, arrivals, end_s)
            for name in names
            for where, url in (("robot", f"ws://127.0.0.1:{ports[name][0]}/ws"),
                               ("watch", f"ws://127.0.0.1:{wport}/robot/{name}/ws"))))
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(15)
    per_robot = {}
    for name in names:
        robot, watch = arrivals[(name, "robot")], arrivals[(name, "watch")]
        common = sorted(set(robot) & set(watch))[2:]  # the first ones are the join's full packets
        lag_ms = np.array([1e3 * (watch[s] - robot[s]) for s in common])
        per_robot[name] = {"packets": len(common), "p50_ms": float(np.percentile(lag_ms, 50)),
                           "p95_ms": float(np.percentile(lag_ms, 95)), "max_ms": float(lag_ms.max()),
                           "missing_on_watch": len(set(robot) - set(watch))}
    return {"robots": args.robots, "seconds": args.seconds, "per_robot": per_robot, "load_average": os.getloadavg()}


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] == "overhead-child":
        _overhead_child(sys.argv[2] == "1", float(sys.argv[3]), Path(sys.argv[4]), int(sys.argv[5]))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=["overhead", "latency"])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--robots", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=40.0)
    ap.add_argument("--out", default=None)
    ap.add_argument("--watcher-nice", type=int, default=0,
                    help="overhead: nice value of the watcher process (19: it stands for another computer)")
    args = ap.parse_args()
    if args.what == "overhead":
        result = overhead(args)
    else:
        with tempfile.TemporaryDirectory() as tmp:
            result = asyncio.run(_latency(args, tmp))
    text = json.dumps(result, indent=1)
    print(json.dumps(result.get("summary", result.get("per_robot")), indent=1))
    if args.out:
        Path(args.out).write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
