"""Random frames thrown at the websocket handler of the real aiohttp server (hypothesis).

Each example connects, sends a few frames (random text, random JSON of any shape,
messages shaped like the protocol's with wrong types and tokens, deep nesting, binary
junk, oversized frames) and checks that every frame gets exactly one clear answer: a
one-line error, a refused command (the token is never guessed), or the full map a
resync asks for; an oversized frame is answered and closed with 1009. Meanwhile a
well-behaved viewer on the same server keeps getting every packet, nothing is queued
for the motors, and nothing lands in the log as an error.

The suite runs a moderate number of examples; ``bench/fuzz.py`` runs 10^4 frames
(``MAZEBOT_FUZZ_WS_EXAMPLES``).
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import secrets
from collections import Counter
from typing import Any

import aiohttp
import pytest
from aiohttp import WSMsgType
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from mazebot.state import SharedState
from mazebot.web.app import BROADCASTER_KEY, WebSettings, create_app
from mazebot.web.protocol import KIND_DELTA, KIND_FULL, ProtocolError, decode_packet, parse_client_message

TOKEN = secrets.token_hex(16)  # nothing a fuzzer can guess: every command must be refused
MAX_MESSAGE_BYTES = 4096
EXAMPLES = int(os.environ.get("MAZEBOT_FUZZ_WS_EXAMPLES", "60"))
FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=None,
    database=None,
    derandomize=os.environ.get("MAZEBOT_FUZZ_RANDOM") != "1",
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow, HealthCheck.data_too_large],
)
#: Frames sent, by kind (bench/fuzz.py reads them from $MAZEBOT_FUZZ_REPORT).
FRAMES: Counter[str] = Counter()


def report_counts() -> None:
    """Append the counts so far to ``$MAZEBOT_FUZZ_REPORT`` (one line per call; the last one of
    each process is its total, so an interrupted run still says how far it got)."""
    path = os.environ.get("MAZEBOT_FUZZ_REPORT")
    if path:
        with open(path, "a", encoding="utf-8") as f:
            f.write(json.dumps({"suite": "websocket", "pid": os.getpid(), "frames": dict(FRAMES)}) + "\n")


@pytest.fixture(scope="module", autouse=True)
def _report_counts():
    yield
    report_counts()


# -- frames ---------------------------------------------------------------------------------------

_scalars = st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=20))
json_values = st.recursive(
    _scalars,
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=8), inner, max_size=4)),
    max_leaves=12,
)
protocol_shaped = st.fixed_dictionaries(
    {"type": st.one_of(st.sampled_from(["start", "stop", "resync", "Start", "", "launch"]), json_values)},
    optional={"token": st.one_of(st.text(max_size=12), json_values), "seq": json_values},
)


def _deep(depth: int, kind: str) -> str:
    return "[" * depth + "]" * depth if kind == "list" else '{"a":' * depth + "1" + "}" * depth


frames = st.one_of(
    st.tuples(st.just("text"), st.text(max_size=300)),
    st.tuples(st.just("json"), json_values.map(json.dumps)),
    st.tuples(st.just("shaped"), protocol_shaped.map(json.dumps)),
    st.tuples(st.just("deep"), st.builds(_deep, st.integers(1, 2000), st.sampled_from(["list", "object"]))),
    st.tuples(st.just("binary"), st.binary(max_size=300)),
    st.tuples(st.just("oversized"), st.integers(MAX_MESSAGE_BYTES + 1, 4 * MAX_MESSAGE_BYTES).map(
        lambda n: json.dumps({"type": "start", "token": "x" * n}))),
    st.tuples(st.just("oversized-binary"), st.integers(MAX_MESSAGE_BYTES + 1, 4 * MAX_MESSAGE_BYTES).map(
        lambda n: os.urandom(n))),
)


# -- the server ------------------------------------------------------------------------------------


@pytest.fixture
async def served(aiohttp_client, caplog) -> dict[str, Any]:
    """One server for every example of a test, with a bystander that never misbehaves."""
    caplog.set_level(logging.WARNING)
    state = SharedState()
    # no rate limits here (tests/web/test_netsec.py covers flooding): every frame must be answered
    settings = WebSettings(control_token=TOKEN, broadcast_hz=0, max_message_bytes=MAX_MESSAGE_BYTES,
                           message_rate_per_s=10000, message_burst=100000, connect_rate_per_s=10000,
                           connect_burst=100000, heartbeat_s=300)  # the bystander reads only between examples
    app = create_app(state, settings=settings)
    client = await aiohttp_client(app)
    bystander = await client.ws_connect("/ws")
    await _next_of(bystander, WSMsgType.BINARY)
    yield {"state": state, "app": app, "client": client, "bystander": bystander, "log": caplog}
    await bystander.close()


async def _receive(ws: aiohttp.ClientWebSocketResponse) -> aiohttp.WSMessage:
    return await asyncio.wait_for(ws.receive(), 10)


async def _next_of(ws: aiohttp.ClientWebSocketResponse, kind: WSMsgType) -> aiohttp.WSMessage:
    while (msg := await _receive(ws)).type != kind:
        assert msg.type in (WSMsgType.TEXT, WSMsgType.BINARY), msg
    return msg


def _expected(text: str) -> tuple[str, Any]:
    """What the server must answer to a text frame: ("error", message), ("full", None) or ("refused", token)."""
    try:
        msg = parse_client_message(text)
    except ProtocolError as exc:
        return "error", str(exc)
    if msg.type == "resync":
        return "full", None
    return "refused", msg.token


def _check_answer(kind: str, payload: str | bytes, answer: aiohttp.WSMessage) -> None:
    if kind == "binary":
        assert answer.type == WSMsgType.TEXT, answer
        assert json.loads(answer.data) == {"type": "error", "status": 400,
                                           "message": "binary frames are not part of the protocol; send JSON text"}
        return
    want, detail = _expected(payload)  # type: ignore[arg-type]
    if want == "full":
        assert answer.type == WSMsgType.BINARY and decode_packet(answer.data).kind == KIND_FULL
        return
    assert answer.type == WSMsgType.TEXT, (payload, answer)
    reply = json.loads(answer.data)
    if want == "error":
        assert reply == {"type": "error", "status": 400, "message": detail}
        assert "\n" not in detail and len(detail) < 200
    else:  # start/stop with a token nobody has: refused (401 none, 403 wrong, 429 locked out for guessing)
        assert reply["type"] == "reply" and reply["ok"] is False, reply
        assert reply["status"] in ((401, 429) if not detail else (403, 429)), reply
        assert reply["message"] and "\n" not in reply["message"]


@FUZZ
@given(batch=st.lists(frames, min_size=1, max_size=8))
@example(batch=[("deep", _deep(1500, "list")), ("shaped", '{"type": ["start"]}'), ("shaped", '{"type": {}}')])
@example(batch=[("text", ""), ("json", "null"), ("json", '"start"'), ("shaped", '{"type": "resync", "token": 5}')])
async def test_every_random_frame_gets_one_clear_answer_and_the_others_are_served(
    served: dict[str, Any], batch: list[tuple[str, str | bytes]]
) -> None:
    state, app, client, bystander = served["state"], served["app"], served["client"], served["bystander"]
    ws = await client.ws_connect("/ws", max_msg_size=0)
    await _next_of(ws, WSMsgType.BINARY)  # hello, then the full map
    for kind, payload in batch:
        FRAMES[kind] += 1
        if sum(FRAMES.values()) % 1000 == 0:
            report_counts()
        if ws.closed:
            ws = await client.ws_connect("/ws", max_msg_size=0)
            await _next_of(ws, WSMsgType.BINARY)
        if isinstance(payload, bytes):
            await ws.send_bytes(payload)
        else:
            await ws.send_str(payload)
        answer = await _receive(ws)
        size = len(payload if isinstance(payload, bytes) else payload.encode())
        if size > MAX_MESSAGE_BYTES:  # the oversized kinds, and deep nesting past the limit
            assert answer.type == WSMsgType.TEXT
            assert json.loads(answer.data) == {"type": "error", "status": 1009,
                                               "message": f"message larger than {MAX_MESSAGE_BYTES} bytes"}
            close = await _receive(ws)
            assert close.type == WSMsgType.CLOSE and close.data == 1009, close
            await ws.close()
            continue
        _check_answer(kind, payload, answer)
    await ws.close()
    # the bystander never heard any of it, and is served the next change at once
    state.pose.x_m += 0.001
    app[BROADCASTER_KEY].tick()
    packet = decode_packet((await _next_of(bystander, WSMsgType.BINARY)).data)
    assert packet.kind in (KIND_DELTA, KIND_FULL) and packet.status["pose"][0] == round(state.pose.x_m, 3)
    assert state.commands.empty()
    problems = [r for r in served["log"].records if r.levelno >= logging.ERROR or r.exc_info]
    assert not problems, [f"{r.name}: {r.getMessage()}" for r in problems]


# -- regressions the fuzzing found ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[" * 1500 + "]" * 1500, "message is nested too deeply; expected a flat JSON object"),
        ('{"a":' * 1500 + "1" + "}" * 1500, "message is nested too deeply; expected a flat JSON object"),
        ('{"type": ["start"]}', "message type must be a string, got list"),
        ('{"type": {"start": 1}}', "message type must be a string, got dict"),
        ('{"type": 7}', "message type must be a string, got int"),
        ('{"type": "' + "x" * 500 + '"}', "unknown message type '" + "x" * 40 + "…'; expected start, stop or resync"),
        # 20 unprintable characters were echoed as 200 characters of escapes (a 255-character "line")
        (json.dumps({"type": "\U000e0001" * 20}),
         "unknown message type '" + "\\U000e0001" * 4 + "…'; expected start, stop or resync"),
        (json.dumps({"type": "\x00" * 30}),
         "unknown message type '" + "\\x00" * 10 + "…'; expected start, stop or resync"),
    ],
    ids=["deep-list", "deep-object", "list-type", "object-type", "number-type", "long-type", "unprintable-type",
         "control-type"],
)
async def test_deep_nesting_and_unhashable_types_are_answered_not_crashed_on(aiohttp_client, caplog, text: str,
                                                                             message: str) -> None:
    """Deep nesting raised RecursionError and a list as ``type`` TypeError out of the parser: the
    handler died with a traceback in the log and the client got no answer. A long unknown type
    was echoed whole into the reply and into /api/status. (``[web] max_message_bytes`` may be
    up to 1 MiB: nesting deeper than Python's recursion limit fits.)"""
    caplog.set_level(logging.WARNING)
    settings = WebSettings(control_token=TOKEN, broadcast_hz=0, max_message_bytes=1 << 16)
    client = await aiohttp_client(create_app(SharedState(), settings=settings))
    ws = await client.ws_connect("/ws")
    await _next_of(ws, WSMsgType.BINARY)
    await ws.send_str(text)
    reply = json.loads((await _next_of(ws, WSMsgType.TEXT)).data)
    assert reply == {"type": "error", "status": 400, "message": message}
    await ws.send_json({"type": "resync"})  # still connected and served
    assert decode_packet((await _next_of(ws, WSMsgType.BINARY)).data).kind == KIND_FULL
    await ws.close()
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]
