"""systemd notify protocol: READY=1 when the daemon serves, watchdog pings only while control ticks."""

from __future__ import annotations

import asyncio
import os
import socket
from pathlib import Path

import pytest
from aiohttp.test_utils import unused_port

from mazebot import sdnotify
from mazebot.clock import RealClock
from mazebot.config import Config
from mazebot.main import Hardware, run_daemon
from mazebot.sim.backend import sim_hardware_builder
from mazebot.state import SharedState
from mazebot.tasks.supervisor import Supervisor


@pytest.fixture
def notify_socket(tmp_path: Path):
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = tmp_path / "notify"
    sock.bind(str(path))
    sock.setblocking(False)
    yield sock, str(path)
    sock.close()


def _messages(sock: socket.socket) -> list[str]:
    out = []
    while True:
        try:
            out.append(sock.recv(4096).decode())
        except BlockingIOError:
            return out


def test_notify_writes_to_the_socket_and_is_a_no_op_outside_systemd(notify_socket) -> None:
    sock, path = notify_socket
    assert sdnotify.notify("READY=1", {"NOTIFY_SOCKET": path})
    assert _messages(sock) == ["READY=1"]
    assert sdnotify.notify("READY=1", {}) is False


def test_abstract_socket_names_start_with_at() -> None:
    name = f"mazebot-test-{os.getpid()}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind("\0" + name)
        assert sdnotify.notify("STATUS=ok", {"NOTIFY_SOCKET": "@" + name})
        assert sock.recv(100) == b"STATUS=ok"


def test_watchdog_period_is_read_for_this_process_only() -> None:
    pid = str(os.getpid())
    assert sdnotify.watchdog_period_s({"WATCHDOG_USEC": "4000000", "WATCHDOG_PID": pid}) == 4.0
    assert sdnotify.watchdog_period_s({"WATCHDOG_USEC": "4000000"}) == 4.0
    assert sdnotify.watchdog_period_s({"WATCHDOG_USEC": "4000000", "WATCHDOG_PID": "1"}) is None
    assert sdnotify.watchdog_period_s({}) is None
    assert sdnotify.watchdog_period_s({"WATCHDOG_USEC": "soon"}) is None


async def test_the_watchdog_starves_when_the_control_loop_stops_ticking(notify_socket) -> None:
    sock, path = notify_socket
    heartbeat = sdnotify.ControlHeartbeat(RealClock())
    feeder = asyncio.create_task(sdnotify.feed_watchdog(heartbeat, 0.02, 0.1, {"NOTIFY_SOCKET": path}))
    for _ in range(5):  # a ticking loop
        await heartbeat.sleep(0.02)
    fed = _messages(sock)
    assert fed and set(fed) == {"WATCHDOG=1"}
    await asyncio.sleep(0.3)  # the loop hangs: pings stop
    _messages(sock)
    await asyncio.sleep(0.1)
    assert _messages(sock) == []
    feeder.cancel()
    with pytest.raises(asyncio.CancelledError):
        await feeder


@pytest.mark.slow
async def test_the_daemon_says_ready_once_it_serves_then_feeds_the_watchdog(notify_socket, monkeypatch) -> None:
    sock, path = notify_socket
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    monkeypatch.setenv("WATCHDOG_USEC", "400000")
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    config = Config()
    config.web.host, config.web.port, config.web.control_token = "127.0.0.1", unused_port(), "1234"
    started: dict[str, Supervisor] = {}

    def on_started(hw: Hardware, state: SharedState, sup: Supervisor) -> None:
        started["sup"] = sup

    ready = asyncio.Event()
    daemon = asyncio.create_task(run_daemon(config, sim_hardware_builder(), ready=ready,
                                            install_signal_handlers=False, on_started=on_started))
    await asyncio.wait_for(ready.wait(), 10)
    await asyncio.sleep(0.5)
    messages = _messages(sock)
    ready_messages = [m for m in messages if m.startswith("READY=1")]
    assert len(ready_messages) == 1 and "\nSTATUS=simulated robot" in ready_messages[0]
    assert messages.count("WATCHDOG=1") >= 3  # every 0.1 s (a quarter of WatchdogSec)
    started["sup"].request_stop("test over")
    assert await asyncio.wait_for(daemon, 10) == 0
    assert _messages(sock)[-1] == "STOPPING=1"
