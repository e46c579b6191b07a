"""Foxglove live: a simulated run served by foxglove-sdk, watched by a client that speaks the
Foxglove WebSocket protocol (aiohttp's client, subprotocol ``foxglove.sdk.v1``: the one the
0.30 SDK's server accepts; it refuses the older ``foxglove.websocket.v1`` handshake).

Wire format (Foxglove WebSocket protocol spec, docs/spec.md of foxglove/ws-protocol):
text frames are JSON ops (``serverInfo``, ``advertise``, ``subscribe``); a binary frame
``0x01`` is message data: opcode, subscription id (uint32 LE), log time (uint64 LE), payload.
"""

from __future__ import annotations

import asyncio
import json
import struct
import subprocess
import sys
from contextlib import AsyncExitStack

import aiohttp
import pytest
from aiohttp.test_utils import unused_port

from mazebot.config import Config
from mazebot.errors import ConfigError
from mazebot.main import _start_foxglove, run_daemon
from mazebot.sim.backend import sim_hardware_builder
from mazebot.state import RunState

pytestmark = pytest.mark.slow  # the daemon with a live Foxglove server

CONTROL_TOKEN = "2468"
SUBPROTOCOL = "foxglove.sdk.v1"
EXPECTED = {
    "/scan": ("foxglove.LaserScan", "protobuf"),
    "/tf": ("foxglove.FrameTransform", "protobuf"),
    "/pose": ("foxglove.PoseInFrame", "protobuf"),
    "/odom": ("foxglove.PoseInFrame", "protobuf"),
    "/goal": ("foxglove.PoseInFrame", "protobuf"),
    "/path": ("foxglove.PosesInFrame", "protobuf"),
    "/map": ("foxglove.Grid", "protobuf"),
    "/log": ("foxglove.Log", "protobuf"),
    "/mazebot/run_state": ("mazebot.RunState", "json"),
    "/mazebot/motors": ("mazebot.MotorCommand", "json"),
    "/mazebot/encoders": ("mazebot.EncoderTicks", "json"),
}


def _config(web_port: int, fox_port: int) -> Config:
    config = Config()
    config.web.host = "127.0.0.1"
    config.web.port = web_port
    config.web.control_token = CONTROL_TOKEN
    config.foxglove.enabled = True
    config.foxglove.port = fox_port  # host: empty, so the web page's 127.0.0.1
    return config


async def test_a_foxglove_client_sees_the_channels_and_receives_the_live_run() -> None:
    web_port, fox_port = unused_port(), unused_port()
    ready = asyncio.Event()
    started: dict = {}
    daemon = asyncio.create_task(
        run_daemon(_config(web_port, fox_port), sim_hardware_builder(), ready=ready, install_signal_handlers=False,
                   on_started=lambda hw, state, sup: started.update(state=state, sup=sup))
    )
    try:
        await asyncio.wait_for(ready.wait(), 20)
        state = started["state"]
        async with (
            aiohttp.ClientSession() as session,
            session.ws_connect(f"ws://127.0.0.1:{fox_port}/", protocols=(SUBPROTOCOL,)) as ws,
        ):
            assert ws.protocol == SUBPROTOCOL
            info = json.loads((await ws.receive(timeout=5)).data)
            assert info["op"] == "serverInfo" and info["name"] == "mazebot"
            channels: dict[str, dict] = {}
            while set(channels) != set(EXPECTED):
                op = json.loads((await ws.receive(timeout=5)).data)
                if op["op"] == "advertise":
                    channels.update({c["topic"]: c for c in op["channels"]})
            assert {t: (c["schemaName"], c["encoding"]) for t, c in channels.items()} == EXPECTED
            assert json.loads(channels["/mazebot/run_state"]["schema"])["title"] == "mazebot.RunState"
            subs = {topic: i + 1 for i, topic in enumerate(EXPECTED)}
            await ws.send_str(json.dumps({
                "op": "subscribe",
                "subscriptions": [{"id": sid, "channelId": channels[t]["id"]} for t, sid in subs.items()],
            }))
            # explore, so the planner has a goal and a path and the wheels turn
            async with session.post(f"http://127.0.0.1:{web_port}/api/start",
                                    headers={"X-Mazebot-Token": CONTROL_TOKEN}) as resp:
                assert resp.status == 200
            topic_of = {sid: t for t, sid in subs.items()}
            got: dict[str, list[bytes]] = {}
            want = set(EXPECTED) - {"/log"}  # a log line needs something to happen
            for _ in range(2000):
                if want <= set(got):
                    break
                msg = await ws.receive(timeout=10)
                if msg.type is not aiohttp.WSMsgType.BINARY:
                    continue
                opcode, sid, log_time_ns = struct.unpack_from("<BIQ", msg.data)
                assert opcode == 0x01 and log_time_ns > 1_600_000_000 * 10**9
                got.setdefault(topic_of[sid], []).append(msg.data[13:])
            assert want <= set(got), f"nothing on {sorted(want - set(got))}"
        assert state.run_state in (RunState.EXPLORING, RunState.RETURNING, RunState.DONE)
        # the JSON channels carry the recording's own encoding
        states = [json.loads(p)["state"] for p in got["/mazebot/run_state"]]
        assert "exploring" in states
        ticks = json.loads(got["/mazebot/encoders"][-1])
        assert set(ticks) == {"time_s", "left_ticks", "right_ticks", "invalid_transitions"}
        # protobuf payloads name their frames (a string field's bytes appear as they are)
        assert all(b"laser" in p for p in got["/scan"])
        assert any(b"map" in p and b"odom" in p for p in got["/tf"])
        assert all(b"occupancy" in p for p in got["/map"])
    finally:
        if "sup" in started:
            started["sup"].request_stop("test over")
        assert await asyncio.wait_for(daemon, 20) == 0


def test_enabled_without_the_package_is_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "foxglove", None)  # `import foxglove` raises ImportError
    config = Config()
    config.foxglove.enabled = True

    async def start() -> None:
        async with AsyncExitStack() as stack:
            _start_foxglove(config, stack)

    with pytest.raises(ConfigError, match=r"needs the foxglove-sdk package: pip install 'mazebot\[foxglove\]'"):
        asyncio.run(start())


def test_the_daemon_does_not_import_the_sdk_when_foxglove_is_off() -> None:
    code = (
        "import asyncio, sys, contextlib\n"
        "from mazebot.config import Config\n"
        "from mazebot.main import _start_foxglove\n"
        "async def go():\n"
        "    async with contextlib.AsyncExitStack() as stack:\n"
        "        assert _start_foxglove(Config(), stack) is None\n"
        "asyncio.run(go())\n"
        "assert 'foxglove' not in sys.modules, 'imported'\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr


def test_a_port_in_use_is_one_line() -> None:
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        config = Config()
        config.foxglove.enabled = True
        config.foxglove.host = "127.0.0.1"
        config.foxglove.port = taken.getsockname()[1]

        async def start() -> None:
            async with AsyncExitStack() as stack:
                _start_foxglove(config, stack)

        with pytest.raises(ConfigError, match=r"\[foxglove\] cannot listen on 127\.0\.0\.1:"):
            asyncio.run(start())
