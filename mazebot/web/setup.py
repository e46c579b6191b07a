"""The setup view's routes: the raw scan and the wheels for the page, hold-to-run jogging, the doctor.

Routes::

    GET  /api/setup    the latest raw revolution (angles, ranges), encoder counts, wheel speeds
    POST /api/jog      {"left": t, "right": t}: drive for one command time-to-live (PIN, robot not running)
    GET  /api/doctor   the doctor's checks that move nothing (power, temperature, space, clock, lidar)
    ...  /api/calibration   calibration from the page (mazebot.web.calibration)

Jogging is enforced here and in the control task, never trusted to the page: a jog needs
the PIN (the same :class:`~mazebot.web.auth.ControlAuth` as start/stop), is refused while
a run is going or a fault is active, is clamped to :data:`JOG_MAX_THROTTLE`, and is only a
time-stamped request (``SharedState.jog_command``) that the control task applies while it
is younger than ``[motors] command_ttl_s``. The page re-sends it every 100 ms while a
button is held; a release sends zeros, and a lost connection or a page that stops sending
leaves a request that goes stale, so the wheels stop within the time-to-live.
"""

from __future__ import annotations

import asyncio
import math
from pathlib import Path
from typing import Any, Final

from aiohttp import web

from mazebot.clock import RealClock
from mazebot.state import RunState
from mazebot.web import calibration as calibration_routes
from mazebot.web.access import STATE_KEY, authorize_command, check_view

#: The fastest a jog may drive a wheel (a setup jog is for watching a wheel turn, not for racing).
JOG_MAX_THROTTLE: Final = 0.4
#: Samples of a revolution sent to the page at most (an A1 has ~360; an S2 ~3200).
SCAN_POINTS_MAX: Final = 720

STATE_DIR_KEY = web.AppKey("setup_state_dir", Path)


def calibration_running(application: web.Application) -> bool:
    return calibration_routes.running(application)



def jog_refusal(run_state: RunState, calibrating: bool = False) -> str | None:
    """Why the wheels may not be jogged now; None when they may."""
    if calibrating:
        return "a calibration drives the wheels: stop it before jogging"
    if run_state.moving:
        return f"the robot is {run_state.value}: stop the run before jogging"
    if run_state is RunState.FAULT:
        return "a fault is active: the motors stay at zero until it clears"
    return None


async def get_setup(request: web.Request) -> web.Response:
    if (denied := check_view(request)) is not None:
        return denied
    state = request.app[STATE_KEY]
    scan = state.latest_scan
    body: dict[str, Any] = {
        "state": state.run_state.value,
        "jog_refused": jog_refusal(state.run_state, calibration_running(request.app)),
        "jog_max_throttle": JOG_MAX_THROTTLE,
        "encoders": {"left_ticks": state.sensors.encoder_ticks_left, "right_ticks": state.sensors.encoder_ticks_right,
                     "invalid_transitions": state.sensors.encoder_invalid_transitions},
        "wheel_speeds_mps": [round(v, 4) for v in state.wheel_speeds_mps],
        "throttles": [round(v, 3) for v in state.throttles],
        "scan": None,
    }
    if scan is not None and len(scan):
        step = max(1, math.ceil(len(scan) / SCAN_POINTS_MAX))
        valid = scan.valid[::step]
        body["scan"] = {
            "revolution": scan.revolution,
            "samples": len(scan),
            "valid": int(scan.valid.sum()),
            "angle_rad": [round(float(a), 4) for a in scan.angle_rad[::step][valid]],
            "range_m": [round(float(r), 3) for r in scan.range_m[::step][valid]],
        }
    return web.json_response(body, headers={"Cache-Control": "no-store"})


async def post_jog(request: web.Request) -> web.Response:
    if (refused := authorize_command(request, "jog")) is not None:
        return refused
    try:
        data = await request.json()
        left, right = float(data["left"]), float(data["right"])
    except (ValueError, KeyError, TypeError):
        return web.json_response({"error": 'send {"left": throttle, "right": throttle}'}, status=400)
    if not (math.isfinite(left) and math.isfinite(right)):
        return web.json_response({"error": "throttles must be finite numbers"}, status=400)
    state = request.app[STATE_KEY]
    if calibration_running(request.app):  # the calibration is the one writer of the jog request meanwhile
        return web.json_response({"error": jog_refusal(state.run_state, True)}, status=409)
    if (refusal := jog_refusal(state.run_state)) is not None:
        state.jog_command = None
        return web.json_response({"error": refusal}, status=409)
    clamp = JOG_MAX_THROTTLE
    left, right = max(-clamp, min(clamp, left)), max(-clamp, min(clamp, right))
    state.jog_command = None if left == 0.0 and right == 0.0 else (left, right, RealClock().now_s())
    return web.json_response({"accepted": [left, right]})


async def get_doctor(request: web.Request) -> web.Response:
    """The doctor's checks that neither move the robot nor take its devices from the running daemon."""
    from mazebot.doctor import SystemProbe, Verdict, judge_revolution, system_checks

    if (denied := check_view(request)) is not None:
        return denied
    state_dir = request.app.get(STATE_DIR_KEY) or Path(".")
    loop = asyncio.get_running_loop()
    verdicts = await loop.run_in_executor(None, system_checks, SystemProbe(), state_dir)  # subprocesses, files
    scan = request.app[STATE_KEY].latest_scan
    if scan is None:
        verdicts.append(Verdict("lidar revolution", "FAIL", "no revolution from the lidar yet",
                                "run `mazebot doctor` with the daemon stopped to check the lidar"))
    else:
        verdicts.append(judge_revolution(scan))
    verdicts.append(Verdict("motors and encoders", "skip", "pulsing the motors takes the robot from the daemon: "
                            "stop it and run `mazebot doctor`"))
    return web.json_response({"checks": [v.as_json() for v in verdicts]}, headers={"Cache-Control": "no-store"})


def add_routes(application: web.Application, state_dir: Path | None = None, calibration: Any = None) -> None:
    """The setup view's routes, and its calibration's (:mod:`mazebot.web.calibration`)."""

    calibration_routes.add_routes(application, calibration)
    application.router.add_get("/api/setup", get_setup)
    application.router.add_post("/api/jog", post_jog)
    application.router.add_get("/api/doctor", get_doctor)
    if state_dir is not None:
        application[STATE_DIR_KEY] = state_dir
