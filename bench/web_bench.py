"""Web figures over a simulated exploration: bytes/s per viewer, map change -> viewer latency, control jitter.

Runs the daemon (``run_daemon``: SLAM and the web server) on the simulated robot, drives
the depth-first tour of the maze (the bench's scripted driver), and connects ``--viewers``
websocket viewers from a separate process (so their decoding does not load the daemon's
loop). Optionally a headless Chromium (Debian's, through Playwright) opens the page as
one more viewer.

    .venv/bin/python bench/web_bench.py --viewers 20 --seconds 120 [--browser] [--out web.json]
    .venv/bin/python bench/web_bench.py --viewers 1 --seconds 60 --abuse [--out abused.json]
    .venv/bin/python bench/web_bench.py --compare-abuse 3 --seconds 60 [--pin 0,1] --out abuse.json

``--abuse`` adds the network abuse set from another process: a client flooding
resync requests as fast as it can (reconnecting whenever it is closed for it), 50 clients
connecting and dropping in a loop (polite closes, vanished TCP connections, half-sent
handshakes), a client that never reads, and a client sending junk frames (bad JSON, binary,
oversized, deep nesting). ``--compare-abuse N`` runs N quiet and N abused runs alternately,
each in a fresh process, and reports the control loop's p99 lateness of each and the medians.
``--pin D,C`` pins the daemon (and the processes it starts, such as SLAM's worker) to CPU D and
the viewers' and abusers' processes to CPU C (``os.sched_setaffinity``): on the robot the
clients run on other machines, so here they should not take the daemon's core. Every run reports
the loop thread's CPU time and the time it waited for a CPU (``/proc``'s schedstat);
``--sample-stalls`` also samples the loop thread's stack whenever the loop is 30 ms late.

Latency of a map change = time the viewer received the first packet built after it minus
the time a 100 Hz poll of the live grid saw the cell change (wall clock, one machine;
the poll makes it up to 10 ms short).
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import json
import os
import socket
import statistics
import subprocess
import sys
import threading
import time
import traceback
from collections import Counter
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np
from aiohttp.test_utils import unused_port

from mazebot.bench.scripted_drive import ScriptedDriver, dfs_tour, straighten
from mazebot.clock import RealClock
from mazebot.config import Config
from mazebot.main import Hardware, run_daemon
from mazebot.sim.backend import sim_hardware_builder
from mazebot.state import SharedState
from mazebot.tasks.supervisor import Supervisor
from mazebot.web.protocol import decode_packet

PIN = "2468"


def _pin(cpu: int | None, who: str) -> None:
    """Keep this process (and the threads and processes it starts from now on) on one CPU."""
    if cpu is not None:
        os.sched_setaffinity(0, {cpu})
        print(f"web_bench: {who} pinned to CPU {cpu} (os.sched_setaffinity)", file=sys.stderr, flush=True)


def _pins(text: str | None) -> tuple[int | None, int | None]:
    if not text:
        return None, None
    daemon, clients = (int(x) for x in text.split(","))
    return daemon, clients


# -- the viewers' process ------------------------------------------------------------------


async def _viewer(url: str, seconds: float, log: list[tuple] | None, totals: list[int], index: int,
                  connected: asyncio.Event) -> None:
    async with aiohttp.ClientSession() as session, session.ws_connect(url, max_msg_size=0) as ws:
        connected.set()
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            try:
                msg = await asyncio.wait_for(ws.receive(), left)
            except TimeoutError:
                break
            if msg.type == aiohttp.WSMsgType.BINARY:
                now = time.time()
                totals[index] += len(msg.data)
                if log is not None:
                    p = decode_packet(msg.data)
                    cells = 0 if p.map is None else (len(p.map) if p.kind == 2 else int(p.map.codes.size))
                    log.append((p.seq, p.kind, len(msg.data), p.status.get("t_ms"), now * 1000.0, cells))
            elif msg.type == aiohttp.WSMsgType.TEXT:
                totals[index] += len(msg.data)
            else:
                break


async def _viewers(url: str, count: int, seconds: float) -> dict[str, Any]:
    log: list[tuple] = []
    totals = [0] * count
    events = [asyncio.Event() for _ in range(count)]

    async def say_connected() -> None:
        # The parent starts the abusers only after this line: the churning clients share the
        # viewers' address, and the daemon's per-address connect limit would refuse a viewer
        # that came second (on a quiet machine the abusers' process starts first).
        await asyncio.gather(*(e.wait() for e in events))
        print("viewers connected", flush=True)

    announce = asyncio.ensure_future(say_connected())
    await asyncio.gather(*(_viewer(url, seconds, log if i == 0 else None, totals, i, events[i])
                           for i in range(count)))
    announce.cancel()
    return {"log": log, "totals": totals, "seconds": seconds}


# -- the abusers' process ------------------------------------------------------------------


_JUNK = [
    "hello robot", '{"type": "start", "token": ', "[1, 2, 3]", '{"type": "launch"}', '{"type": ["start"]}',
    '{"type": "start", "token": "000000"}', "[" * 1500 + "]" * 1500, "x" * 5000,
]


async def _drain(ws: aiohttp.ClientWebSocketResponse) -> None:
    async for _ in ws:
        pass


async def _flooder(url: str, end: float, counts: dict[str, int]) -> None:
    """Resync requests as fast as the socket takes them; reconnects when closed for it (1008)."""
    async with aiohttp.ClientSession() as session:
        while time.monotonic() < end:
            try:
                async with session.ws_connect(url, max_msg_size=0) as ws:
                    counts["flood_connections"] += 1
                    reader = asyncio.ensure_future(_drain(ws))
                    while time.monotonic() < end and not ws.closed and not reader.done():
                        await ws.send_str('{"type":"resync"}')
                        counts["flood_messages"] += 1
                        if counts["flood_messages"] % 50 == 0:
                            await asyncio.sleep(0)
                    reader.cancel()
            except (aiohttp.ClientError, ConnectionError, RuntimeError):
                pass
            await asyncio.sleep(0.05)


async def _junk(url: str, end: float, counts: dict[str, int], rng: np.random.Generator) -> None:
    """Junk frames, 100 a second, reconnecting after each close (oversized: 1009, too fast: 1008)."""
    async with aiohttp.ClientSession() as session:
        while time.monotonic() < end:
            try:
                async with session.ws_connect(url, max_msg_size=0) as ws:
                    reader = asyncio.ensure_future(_drain(ws))
                    while time.monotonic() < end and not reader.done():
                        if rng.random() < 0.3:
                            await ws.send_bytes(rng.bytes(int(rng.integers(1, 6000))))
                        else:
                            await ws.send_str(_JUNK[int(rng.integers(len(_JUNK)))])
                        counts["junk_frames"] += 1
                        await asyncio.sleep(0.01)
                    reader.cancel()
            except (aiohttp.ClientError, ConnectionError, RuntimeError):
                pass
            await asyncio.sleep(0.05)


def _handshake(host: str, port: int) -> bytes:
    key = base64.b64encode(os.urandom(16)).decode()
    return (f"GET /ws HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n").encode()


async def _churn(url: str, host: str, port: int, end: float, counts: dict[str, int]) -> None:
    """Rounds of 50 clients at once: a third close politely, a third vanish after the handshake,
    a third send half a request and go."""

    async def one(i: int, session: aiohttp.ClientSession) -> None:
        try:
            if i % 3 == 0:
                async with session.ws_connect(url, max_msg_size=0) as ws:
                    await ws.receive()
            else:
                reader, writer = await asyncio.open_connection(host, port)
                writer.write(_handshake(host, port) if i % 3 == 1 else b"GET /ws HTTP/1.1\r\nHost: x\r\n")
                if i % 3 == 1:
                    await reader.readuntil(b"\r\n\r\n")
                writer.transport.abort()
            counts["churn_connections"] += 1
        except (aiohttp.ClientError, OSError, asyncio.IncompleteReadError):
            counts["churn_failures"] += 1

    async with aiohttp.ClientSession() as session:
        while time.monotonic() < end:
            await asyncio.gather(*(one(i, session) for i in range(50)))
            await asyncio.sleep(0.1)


async def _sleeper(host: str, port: int, end: float) -> None:
    """Handshakes with a tiny receive window and never reads again."""
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.setblocking(False)
    loop = asyncio.get_running_loop()
    await loop.sock_connect(sock, (host, port))
    await loop.sock_sendall(sock, _handshake(host, port))
    await asyncio.sleep(end - time.monotonic())
    sock.close()


async def _abusers(url: str, seconds: float) -> dict[str, Any]:
    host, port = url.split("//")[1].split("/")[0].split(":")
    end = time.monotonic() + seconds
    counts: dict[str, int] = {k: 0 for k in ("flood_connections", "flood_messages", "junk_frames",
                                             "churn_connections", "churn_failures")}
    await asyncio.gather(_flooder(url, end, counts), _junk(url, end, counts, np.random.default_rng(7)),
                         _churn(url, host, int(port), end, counts), _sleeper(host, int(port), end))
    async with aiohttp.ClientSession() as session, session.get(url.replace("ws", "http", 1)[:-3] + "/api/status") as r:
        network = (await r.json())["network"]  # what the server saw: bad messages, flood closes, ...
    return {**counts, "seconds": seconds, "server_network": network, "abusers_cpu_s": time.process_time()}


# -- the daemon's side ---------------------------------------------------------------------


class ChangeWatcher:
    """Notes when map cells change (polling the live grid every ``period_s``; up to that much late)."""

    def __init__(self, state: SharedState, period_s: float = 0.01) -> None:
        self.state = state
        self.period_s = period_s
        self.changes: list[tuple[float, int]] = []  # (wall ms, cells whose three-state changed)
        self.shape: tuple[int, int] = (0, 0)

    async def run(self) -> None:
        prev, prev_key = None, None
        while True:
            await asyncio.sleep(self.period_s)
            grid = self.state.map
            if grid is None:
                continue
            now = grid.three_state()
            key = (id(grid), now.shape, tuple(grid.origin_m))
            n = int((now != prev).sum()) if prev is not None and key == prev_key else int((now != -1).sum())
            if n:
                self.changes.append((time.time() * 1000.0, n))
            prev, prev_key, self.shape = now, key, now.shape


def _schedstat_s(native_id: int) -> tuple[float, float]:
    """(CPU time, time spent runnable but waiting for a CPU) of one thread of this process, in s.

    From ``/proc/PID/task/TID/schedstat`` (Linux, Documentation/scheduler/sched-stats.rst):
    the second figure tells lateness caused by other processes on the same CPU from lateness
    caused by work on the loop.
    """
    try:
        fields = Path(f"/proc/self/task/{native_id}/schedstat").read_text().split()
    except OSError:
        return float("nan"), float("nan")
    return int(fields[0]) / 1e9, int(fields[1]) / 1e9


class StallSampler:
    """Where the event loop's thread is while the loop is late: a thread samples its stack.

    A task stamps the time every ``period_s``; a thread looks every ``period_s`` too and, while
    the stamp is older than ``late_s``, records the loop thread's innermost frames and its CPU
    time. A stall during which the loop thread's CPU time grew is work done on the loop; one
    during which it did not is the process waiting for a CPU (or for the GIL).
    """

    def __init__(self, period_s: float = 0.005, late_s: float = 0.03, depth: int = 8) -> None:
        self.period_s, self.late_s, self.depth = period_s, late_s, depth
        self.stamp_s = time.monotonic()
        self.stacks: Counter[str] = Counter()
        self.stalls: list[tuple[float, float]] = []  # (wall s, loop thread CPU s) of each stall
        self._tid = threading.get_ident()
        self._clock = time.pthread_getcpuclockid(self._tid)
        self._stop = threading.Event()

    async def run(self) -> None:
        thread = threading.Thread(target=self._watch, name="stall-sampler", daemon=True)
        thread.start()
        try:
            while True:
                await asyncio.sleep(self.period_s)
                self.stamp_s = time.monotonic()
        finally:
            self._stop.set()

    def _watch(self) -> None:
        stall: tuple[float, float] | None = None
        while not self._stop.wait(self.period_s):
            now = time.monotonic()
            if now - self.stamp_s > self.late_s:
                if stall is None:
                    stall = (self.stamp_s, time.clock_gettime(self._clock))
                frame = sys._current_frames().get(self._tid)
                if frame is not None:
                    frames = traceback.extract_stack(frame)[-self.depth:]
                    self.stacks[" < ".join(f"{Path(f.filename).name}:{f.lineno} {f.name}"
                                           for f in reversed(frames))] += 1
            elif stall is not None:
                self.stalls.append((self.stamp_s - stall[0], time.clock_gettime(self._clock) - stall[1]))
                stall = None

    def summary(self, top: int = 15) -> dict[str, Any]:
        return {"stalls": len(self.stalls), "stalled_s": round(sum(w for w, _ in self.stalls), 3),
                "loop_cpu_in_stalls_s": round(sum(c for _, c in self.stalls), 3),
                "longest_s": round(max((w for w, _ in self.stalls), default=0.0), 3),
                "samples": sum(self.stacks.values()), "top_stacks": self.stacks.most_common(top)}


def _latencies_ms(log: list[list], changes: list[tuple[float, int]]) -> np.ndarray:
    """Per changed cell: receive time of the first packet built after its change minus the change time."""
    packets = sorted((p[3], p[4]) for p in log if p[3] is not None)  # (built ms, received ms)
    built = np.array([b for b, _ in packets])
    received = np.array([r for _, r in packets])
    out = []
    for t, n in changes:
        k = int(np.searchsorted(built, t))
        if 0 < k < len(built) and n > 0:  # changes before the viewer's first packet are not latency
            out.append(np.full(n, received[k] - t))
    return np.concatenate(out) if out else np.zeros(0)


def _browser(url: str, seconds: float, out: dict[str, Any]) -> None:
    from playwright.sync_api import sync_playwright

    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync"]
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path="/usr/bin/chromium", args=flags)
        page = browser.new_page(viewport={"width": 360, "height": 640})
        transferred = []
        page.on("response", lambda r: transferred.append((r.url, len(r.body()) if r.ok else 0)))
        page.goto(url)
        page.wait_for_selector("body[data-conn='open']")
        time.sleep(seconds)
        out["page_weight_bytes"] = sum(n for _, n in transferred)
        out["page_files"] = transferred
        out["browser_stats"] = page.evaluate(
            "({fulls: mazebot.stats.fulls, deltas: mazebot.stats.deltas, bytes: mazebot.stats.bytes,"
            " gaps: mazebot.stats.gaps, lat: mazebot.stats.latencyMs})")
        page.screenshot(path=str(Path(out["out_dir"]) / "web_bench_phone.png"))
        browser.close()


def _compare_abuse(args: argparse.Namespace) -> int:
    """Quiet and abused runs alternately, each in its own process; p99 control lateness of each."""
    runs: list[dict[str, Any]] = []
    out_path = Path(args.out)
    for i in range(2 * args.compare_abuse):
        abused = i % 2 == 1
        out = out_path.with_suffix(f".run{i}.json")
        cmd = [sys.executable, __file__, "--viewers", str(args.viewers), "--seconds", str(args.seconds),
               "--seed", str(args.seed), "--out", str(out), "--abuser-nice", str(args.abuser_nice)]
        cmd += ["--abuse"] if abused else []
        cmd += ["--pin", args.pin] if args.pin else []
        cmd += ["--sample-stalls"] if args.sample_stalls else []
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        r = json.loads(out.read_text())
        out.unlink()
        runs.append({"abused": abused, **r["control_lateness_ms"], "load_average": r["load_average"],
                     "pinned": r.get("pinned"),
                     "daemon_cpu_s": r["daemon_cpu_s"], "loop_thread_cpu_s": r.get("loop_thread_cpu_s"),
                     "loop_thread_waiting_for_cpu_s": r.get("loop_thread_waiting_for_cpu_s"),
                     "stall_sampler": r.get("stall_sampler"), "abuse": r.get("abuse")})
        print(json.dumps(runs[-1]), flush=True)
    summary = {}
    for name, abused in (("quiet", False), ("abused", True)):
        p99 = [r["p99"] for r in runs if r["abused"] == abused]
        mine = [r for r in runs if r["abused"] == abused]
        summary[name] = {"p99_ms": p99, "median_p99_ms": statistics.median(p99),
                         "median_p50_ms": statistics.median(r["p50"] for r in mine),
                         "median_daemon_cpu_s": statistics.median(r["daemon_cpu_s"] for r in mine)}
    summary["abused_minus_quiet_median_p99_ms"] = summary["abused"]["median_p99_ms"] - summary["quiet"]["median_p99_ms"]
    summary["pinned"] = runs[0]["pinned"]
    out_path.write_text(json.dumps({"runs": runs, "summary": summary}, indent=2))
    print(json.dumps(summary, indent=2))
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--viewers", type=int, default=1)
    ap.add_argument("--seconds", type=float, default=120.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--maze", default=None)
    ap.add_argument("--browser", action="store_true", help="also open the page in headless Chromium")
    ap.add_argument("--out", default="web_bench.json")
    ap.add_argument("--abuse", action="store_true", help="also run the network abuse set")
    ap.add_argument("--compare-abuse", type=int, default=0, metavar="N",
                    help="N quiet and N abused runs, alternating, each in a fresh process")
    ap.add_argument("--abuser-nice", type=int, default=0, metavar="N",
                    help="run the abusers N nice levels lower (on a robot their CPU is another machine's)")
    ap.add_argument("--pin", default=None, metavar="D,C",
                    help="pin the daemon to CPU D and the viewers and abusers to CPU C (os.sched_setaffinity)")
    ap.add_argument("--sample-stalls", action="store_true",
                    help="sample the event loop thread's stack whenever the loop is 30 ms late")
    ap.add_argument("--viewer-child", nargs=4, metavar=("URL", "N", "SECONDS", "OUT"), help=argparse.SUPPRESS)
    ap.add_argument("--abuse-child", nargs=4, metavar=("URL", "SECONDS", "OUT", "NICE"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.compare_abuse:
        return _compare_abuse(args)
    daemon_cpu, client_cpu = _pins(args.pin)
    if args.abuse_child:
        url, seconds, out, nice = args.abuse_child
        _pin(client_cpu, "abusers")
        os.nice(int(nice))
        Path(out).write_text(json.dumps(asyncio.run(_abusers(url, float(seconds)))))
        return 0
    if args.viewer_child:
        url, n, seconds, out = args.viewer_child
        _pin(client_cpu, "viewers")
        Path(out).write_text(json.dumps(asyncio.run(_viewers(url, int(n), float(seconds)))))
        return 0

    _pin(daemon_cpu, "daemon")
    pin_args = ["--pin", args.pin] if args.pin else []
    config = Config()
    config.web.host, config.web.port, config.web.control_token = "127.0.0.1", unused_port(), PIN
    base = f"http://127.0.0.1:{config.web.port}"
    out_path = Path(args.out)
    child_out = out_path.with_suffix(".viewers.json")
    abuse_out = out_path.with_suffix(".abuse.json")
    result: dict[str, Any] = {"viewers": args.viewers, "seconds": args.seconds, "out_dir": str(out_path.parent),
                              "pinned": None if daemon_cpu is None else {"daemon_cpu": daemon_cpu,
                                                                         "viewers_and_abusers_cpu": client_cpu}}
    started: dict[str, Any] = {}
    sampler = StallSampler() if args.sample_stalls else None

    def on_started(hardware: Hardware, state: SharedState, supervisor: Supervisor) -> None:
        robot = hardware.sim
        layout = robot.world.maze
        tour = straighten(dfs_tour(layout))
        driver = ScriptedDriver(
            [layout.cell_center_m(c) for c in tour[1:]], robot.physics,
            speed_mps=config.drive.max_speed_mps * 0.8, yaw_rate_radps=config.drive.max_yaw_rate_radps * 0.8,
            track_width_m=config.drive.track_width_m, full_throttle_mps=config.drive.max_wheel_speed_mps,
            deadband=config.sim.deadband,
        )
        watcher = ChangeWatcher(state)
        started.update(state=state, watcher=watcher, driver=driver)

        async def session() -> None:
            await asyncio.sleep(0.5)
            state.control_lateness_ms.clear()
            if sampler is not None:  # only the measured part
                sampler.stacks.clear()
                sampler.stalls.clear()
            cpu0 = time.process_time()  # the daemon's own CPU (every thread), not the clients'
            sched0 = _schedstat_s(threading.get_native_id())
            proc = None
            if args.viewers:
                proc = await asyncio.create_subprocess_exec(
                    sys.executable, __file__, "--viewer-child", base.replace("http", "ws") + "/ws",
                    str(args.viewers), str(args.seconds), str(child_out), *pin_args,
                    stdout=asyncio.subprocess.PIPE)
                assert proc.stdout is not None
                await asyncio.wait_for(proc.stdout.readline(), 30.0)  # "viewers connected"
            abusers = None
            if args.abuse:
                abusers = await asyncio.create_subprocess_exec(
                    sys.executable, __file__, "--abuse-child", base.replace("http", "ws") + "/ws",
                    str(args.seconds), str(abuse_out), str(args.abuser_nice), *pin_args)
            browser = None
            if args.browser:
                browser = asyncio.get_running_loop().run_in_executor(None, _browser, base + "/", args.seconds, result)
            await asyncio.sleep(0.5)
            drive = asyncio.ensure_future(driver.run(state, RealClock(), config.daemon.control_period_s))
            await asyncio.sleep(args.seconds)
            drive.cancel()
            if proc is not None:
                await proc.wait()
            if abusers is not None:
                await abusers.wait()
            if browser is not None:
                await browser
            lateness = np.array(state.control_lateness_ms)
            result["control_lateness_ms"] = {"p50": float(np.percentile(lateness, 50)),
                                             "p99": float(np.percentile(lateness, 99)),
                                             "max": float(lateness.max()), "n": int(lateness.size)}
            result["load_average"] = os.getloadavg()
            result["daemon_cpu_s"] = time.process_time() - cpu0
            sched1 = _schedstat_s(threading.get_native_id())
            result["loop_thread_cpu_s"] = sched1[0] - sched0[0]
            result["loop_thread_waiting_for_cpu_s"] = sched1[1] - sched0[1]
            result["tour_done"] = driver.done
            # each part's thread CPU since the daemon started (web packet, sends per viewer among them)
            result["cpu_budget"] = state.cpu.table(state.cpu.age_s(RealClock().now_s()))
            result["tour_index"] = [driver.index, len(driver.waypoints_m)]
            supervisor.request_stop("web bench over")

        supervisor.start("bench-watcher", watcher.run)
        if sampler is not None:
            supervisor.start("bench-stall-sampler", sampler.run)
        supervisor.start("bench-session", session)

    builder = sim_hardware_builder(maze_path=args.maze, seed=None if args.maze else args.seed,
                                   size=None if args.maze else (6, 6))
    asyncio.run(run_daemon(config, builder, install_signal_handlers=False, on_started=on_started))

    if args.viewers:
        child = json.loads(child_out.read_text())
        totals = child["totals"]
        result["bytes_per_s_per_viewer"] = {"mean": float(np.mean(totals)) / args.seconds,
                                            "max": float(np.max(totals)) / args.seconds}
        log = child["log"]
        result["packets"] = {"total": len(log), "full": sum(1 for p in log if p[1] == 1),
                             "bytes_full": sum(p[2] for p in log if p[1] == 1),
                             "bytes_delta": sum(p[2] for p in log if p[1] == 2)}
        lat = _latencies_ms(log, started["watcher"].changes)
        if lat.size:
            result["map_change_to_viewer_ms"] = {"p50": float(np.percentile(lat, 50)),
                                                 "p95": float(np.percentile(lat, 95)),
                                                 "max": float(lat.max()), "cells": int(lat.size)}
        child_out.unlink()
    result["map_cells"] = list(started["watcher"].shape)
    if sampler is not None:
        result["stall_sampler"] = sampler.summary()
    if args.abuse:
        result["abuse"] = json.loads(abuse_out.read_text())
        abuse_out.unlink()
    if "browser_stats" in result:
        lat = np.array(result["browser_stats"].pop("lat"))
        result["tick_to_page_ms"] = {"p50": float(np.percentile(lat, 50)), "p95": float(np.percentile(lat, 95))}
        result["browser_bytes_per_s"] = result["browser_stats"]["bytes"] / args.seconds
    out_path.write_text(json.dumps(result, indent=2, default=str))
    print(json.dumps({k: v for k, v in result.items() if k != "page_files"}, indent=2, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
