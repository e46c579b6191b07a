"""The control surface against curious people on the same network: who may connect from
which page, which interface the server listens on, and that the PIN never reaches the log
after the one notice on first start."""

from __future__ import annotations

import asyncio
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import aiohttp
import pytest
from aiohttp.test_utils import unused_port

from mazebot.config import Config
from mazebot.errors import ConfigError, HardwareUnavailable
from mazebot.state import SharedState
from mazebot.web import server as server_module
from mazebot.web.app import WebSettings, create_app
from mazebot.web.server import start_web_server

TOKEN = "135790"


def _app(state: SharedState, **settings: object):
    return create_app(state, settings=WebSettings(control_token=TOKEN, broadcast_hz=0, **settings))  # type: ignore[arg-type]


# -- Origin ---------------------------------------------------------------------------------------------


async def test_clients_without_origin_may_watch_and_with_the_pin_control(aiohttp_client) -> None:
    """curl, scripts, the bench: no Origin header, so no browser page can be abusing them (docs/protocol.md)."""
    state = SharedState()
    client = await aiohttp_client(_app(state))
    ws = await client.ws_connect("/ws")  # aiohttp's client sends no Origin
    assert (await ws.receive()).type == aiohttp.WSMsgType.TEXT  # hello
    await ws.close()
    resp = await client.post("/api/start", headers={"X-Mazebot-Token": TOKEN})
    assert resp.status == 200 and await state.commands.get() == "start"
    assert (await client.post("/api/stop")).status == 401  # still needs the PIN


@pytest.mark.parametrize("origin", [
    "http://{host}:{port}.evil.example",  # the page's host:port as a prefix of another name
    "http://{host}:{other}",  # another program on the same machine
    "http://evil.example:{port}",
    "https://evil.example",
    "null",  # sandboxed iframes, file:// pages
    "file://",
    "http://{host}",  # port 80: another site
])
async def test_look_alike_origins_are_refused_even_with_the_pin(aiohttp_client, origin: str) -> None:
    state = SharedState()
    client = await aiohttp_client(_app(state))
    host, port = client.server.host, client.server.port
    origin = origin.format(host=host, port=port, other=port + 1)
    resp = await client.post("/api/start", headers={"Origin": origin, "X-Mazebot-Token": TOKEN})
    assert resp.status == 403, origin
    assert "may not use this robot; add it to [web] allowed_origins" in await resp.text()
    with pytest.raises(aiohttp.WSServerHandshakeError) as err:
        await client.ws_connect("/ws", headers={"Origin": origin})
    assert err.value.status == 403
    assert state.commands.empty()


async def test_the_page_s_own_origin_and_configured_ones_are_let_in(aiohttp_client) -> None:
    state = SharedState()
    client = await aiohttp_client(_app(state, allowed_origins=("http://mazebot.local:8080",)))
    own = f"http://{client.server.host}:{client.server.port}"
    for origin in (own, "http://mazebot.local:8080"):
        ws = await client.ws_connect("/ws", headers={"Origin": origin})
        assert (await ws.receive()).type == aiohttp.WSMsgType.TEXT
        await ws.close()
        resp = await client.post("/api/start", headers={"Origin": origin, "X-Mazebot-Token": TOKEN})
        assert resp.status == 200
    assert (await client.post("/api/start", headers={"Origin": "http://mazebot.local:9090",
                                                     "X-Mazebot-Token": TOKEN})).status == 403


# -- the interface the server listens on -----------------------------------------------------------------


def _connects(host: str, port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(2)
        return s.connect_ex((host, port)) == 0


@pytest.mark.parametrize(("bind", "reachable", "unreachable"), [
    ("127.0.0.1", "127.0.0.1", "127.0.0.2"),  # one interface: the other loopback address is not served
    ("0.0.0.0", "127.0.0.2", None),  # every interface
])
async def test_web_host_binds_a_single_interface_or_all(tmp_path: Path, bind: str, reachable: str,
                                                         unreachable: str | None) -> None:
    config = Config()
    config.web.host, config.web.port, config.web.control_token = bind, unused_port(), TOKEN
    runner = await start_web_server(SharedState(), config)
    try:
        async with aiohttp.ClientSession() as session, \
                session.get(f"http://{reachable}:{config.web.port}/api/status") as resp:
            assert resp.status == 200
        loop = asyncio.get_running_loop()
        if unreachable is not None:
            assert not await loop.run_in_executor(None, _connects, unreachable, config.web.port)
    finally:
        await runner.cleanup()


async def test_a_web_host_that_is_no_address_is_a_config_error_naming_the_key() -> None:
    config = Config()
    config.web.host, config.web.port, config.web.control_token = "no-such-host.invalid", unused_port(), TOKEN
    with pytest.raises(ConfigError, match=r"^web.host: 'no-such-host.invalid' is not an address of this machine"):
        await start_web_server(SharedState(), config)


async def test_an_address_not_up_yet_is_waited_for_then_named_with_exit_69(caplog) -> None:
    """192.0.2.1 (TEST-NET-1, RFC 5737) is on no interface: the bind fails with EADDRNOTAVAIL."""
    config = Config()
    config.web.host, config.web.port, config.web.control_token = "192.0.2.1", unused_port(), TOKEN
    config.web.bind_wait_s = 1.0
    with pytest.raises(HardwareUnavailable, match=r"no interface of this machine has that address \(waited 1 s"):
        await start_web_server(SharedState(), config)
    assert any("not an address of this machine yet; waiting up to 1 s" in r.getMessage() for r in caplog.records)


async def test_the_page_is_served_once_its_address_comes_up(monkeypatch: pytest.MonkeyPatch) -> None:
    """Wi-Fi joining after boot: the first probes find no such address, then it exists."""
    answers = [False, False]
    real_is_up = server_module._address_is_up

    def up_on_the_third_look(host: str) -> bool:
        return answers.pop(0) if answers else real_is_up(host)

    monkeypatch.setattr(server_module, "_address_is_up", up_on_the_third_look)
    monkeypatch.setattr(server_module, "BIND_RETRY_S", 0.05)
    config = Config()
    config.web.host, config.web.port, config.web.control_token = "127.0.0.1", unused_port(), TOKEN
    runner = await start_web_server(SharedState(), config)
    try:
        assert answers == []
        async with aiohttp.ClientSession() as session, \
                session.get(f"http://127.0.0.1:{config.web.port}/api/status") as resp:
            assert resp.status == 200
    finally:
        await runner.cleanup()


def test_the_address_probe_tells_a_missing_address_from_a_present_one() -> None:
    assert server_module._address_is_up("127.0.0.1")
    assert server_module._address_is_up("0.0.0.0")
    assert not server_module._address_is_up("192.0.2.1")


async def test_a_port_in_use_is_not_waited_for() -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        config = Config()
        config.web.host, config.web.port, config.web.control_token = "127.0.0.1", taken.getsockname()[1], TOKEN
        started_s = time.monotonic()
        with pytest.raises(HardwareUnavailable, match=r"choose another \[web\] port"):
            await start_web_server(SharedState(), config)
        assert time.monotonic() - started_s < config.web.bind_wait_s  # raised, not retried for a minute


# -- no secret in the log ---------------------------------------------------------------------------------


async def _poke(port: int, pin: str) -> None:
    """Everything that carries a PIN: right and wrong, in headers, query strings and websocket messages."""
    base = f"http://127.0.0.1:{port}"
    async with aiohttp.ClientSession() as session:
        for token in (pin, "000001", "000002"):
            async with session.post(f"{base}/api/start", headers={"X-Mazebot-Token": token}):
                pass
            async with session.post(f"{base}/api/stop", headers={"Authorization": f"Bearer {token}"}):
                pass
            async with session.get(f"{base}/api/status?token={token}"):
                pass
        async with session.ws_connect(f"{base}/ws?token={pin}") as ws:
            for token in (pin, "000003"):
                await ws.send_json({"type": "stop", "token": token})
                await ws.send_str('{"type": "stop", "token": "' + token)  # broken JSON holding a PIN
            await ws.send_json({"type": token})  # a PIN where the type goes (echoed as an unknown type)
            await asyncio.sleep(0.3)


def _daemon_log(state_home: Path, poke: bool) -> str:
    port = unused_port()
    env = {**os.environ, "XDG_STATE_HOME": str(state_home)}
    proc = subprocess.Popen([sys.executable, "-m", "mazebot", "run", "--sim", "--host", "127.0.0.1", "--port",
                             str(port), "--log-level", "debug"], stderr=subprocess.PIPE, text=True, env=env)
    try:
        deadline = time.monotonic() + 180  # a loaded machine: start-up takes its time
        while not _connects("127.0.0.1", port):
            assert proc.poll() is None and time.monotonic() < deadline, "the daemon did not start"
            time.sleep(0.2)
        if poke:
            pin = (state_home / "mazebot" / "control_token").read_text().strip()
            asyncio.run(_poke(port, pin))
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
        return proc.stderr.read()  # type: ignore[union-attr]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stderr.close()  # type: ignore[union-attr]


def test_the_pin_is_logged_once_on_first_start_and_never_again(tmp_path: Path) -> None:
    first = _daemon_log(tmp_path, poke=True)
    pin = (tmp_path / "mazebot" / "control_token").read_text().strip()
    notices = [line for line in first.splitlines() if pin in line]
    assert notices == [f"WARNING mazebot.web.server: control PIN for start/stop: {pin} "
                       f"(generated once, kept in {tmp_path / 'mazebot' / 'control_token'})"]
    assert "refused start from 127.0.0.1 (403)" in first  # the refusals are logged, without the PIN tried
    for wrong in ("000001", "000002", "000003"):
        assert wrong not in first
    second = _daemon_log(tmp_path, poke=True)
    assert pin not in second and "control PIN" not in second
    assert "refused stop from 127.0.0.1 over the websocket (403)" in second
