"""Web figures over a simulated exploration: bytes/s per viewer, map change -> viewer latency, control jitter.

Runs the daemon (``run_daemon``: SLAM and the web server) on the simulated robot, drives
the depth-first tour of the maze (the bench's scripted driver), and connects ``--viewers``
websocket viewers from a separate process (so their decoding does not load the daemon's
loop). Optionally a headless Chromium (Debian's, through Playwright) opens the page as
one more viewer.

    .venv/bin/python bench/web_bench.py --viewers 20 --seconds 120 [--browser] [--out web.json]

Latency of a map change = time the viewer received the first packet built after it minus
the time a 100 Hz poll of the live grid saw the cell change (wall clock, one machine;
the poll makes it up to 10 ms short).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import time
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


# -- the viewers' process ------------------------------------------------------------------


async def _viewer(url: str, seconds: float, log: list[tuple] | None, totals: list[int], index: int) -> None:
    async with aiohttp.ClientSession() as session, session.ws_connect(url, max_msg_size=0) as ws:
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
    await asyncio.gather(*(_viewer(url, seconds, log if i == 0 else None, totals, i) for i in range(count)))
    return {"log": log, "totals": totals, "seconds": seconds}


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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--viewers", type=int, default=1)
    ap.add_argument("--seconds", type=float, default=120.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--maze", default=None)
    ap.add_argument("--browser", action="store_true", help="also open the page in headless Chromium")
    ap.add_argument("--out", default="web_bench.json")
    ap.add_argument("--viewer-child", nargs=4, metavar=("URL", "N", "SECONDS", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.viewer_child:
        url, n, seconds, out = args.viewer_child
        Path(out).write_text(json.dumps(asyncio.run(_viewers(url, int(n), float(seconds)))))
        return 0

    config = Config()
    config.web.host, config.web.port, config.web.control_token = "127.0.0.1", unused_port(), PIN
    base = f"http://127.0.0.1:{config.web.port}"
    out_path = Path(args.out)
    child_out = out_path.with_suffix(".viewers.json")
    result: dict[str, Any] = {"viewers": args.viewers, "seconds": args.seconds, "out_dir": str(out_path.parent)}
    started: dict[str, Any] = {}

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
            proc = None
            if args.viewers:
                proc = await asyncio.create_subprocess_exec(
                    sys.executable, __file__, "--viewer-child", base.replace("http", "ws") + "/ws",
                    str(args.viewers), str(args.seconds), str(child_out))
            browser = None
            if args.browser:
                browser = asyncio.get_running_loop().run_in_executor(None, _browser, base + "/", args.seconds, result)
            await asyncio.sleep(0.5)
            drive = asyncio.ensure_future(driver.run(state, RealClock(), config.daemon.control_period_s))
            await asyncio.sleep(args.seconds)
            drive.cancel()
            if proc is not None:
                await proc.wait()
            if browser is not None:
                await browser
            lateness = np.array(state.control_lateness_ms)
            result["control_lateness_ms"] = {"p50": float(np.percentile(lateness, 50)),
                                             "p99": float(np.percentile(lateness, 99)), "n": int(lateness.size)}
            result["tour_done"] = driver.done
            result["tour_index"] = [driver.index, len(driver.waypoints_m)]
            supervisor.request_stop("web bench over")

        supervisor.start("bench-watcher", watcher.run)
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
    if "browser_stats" in result:
        lat = np.array(result["browser_stats"].pop("lat"))
        result["tick_to_page_ms"] = {"p50": float(np.percentile(lat, 50)), "p95": float(np.percentile(lat, 95))}
        result["browser_bytes_per_s"] = result["browser_stats"]["bytes"] / args.seconds
    out_path.write_text(json.dumps(result, indent=2, default=str))
    print(json.dumps({k: v for k, v in result.items() if k != "page_files"}, indent=2, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
