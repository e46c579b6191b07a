"""The setup view's calibration routes: start, follow, stop and confirm ``mazebot calibrate`` from the page.

Routes::

    POST /api/calibration          start one (PIN; refused during a run, a fault, a held jog or another calibration)
    GET  /api/calibration?id=ID    its steps, each step's state, detail and figures, the config diff;
                                   the page that started it polls this, and its silence stops it
    POST /api/calibration/stop     stop it: the motors at once, nothing written (PIN)
    POST /api/calibration/write    {"id": ID}: write the finished result to the config file (PIN)
    GET  /api/calibration.png      the report's picture of the runs, once finished

The run itself and its safety rules are :class:`mazebot.calibration.on_daemon.PageCalibration`'s.
"""

from __future__ import annotations

from typing import Any

from aiohttp import web

from mazebot.calibration.geometry import CalibrationError
from mazebot.calibration.on_daemon import PageCalibration
from mazebot.web.access import authorize_command, check_view

CALIBRATION_KEY = web.AppKey("calibration", PageCalibration)

#: Why there is no calibration on a page without a daemon's devices (a replay, a bare test app).
UNAVAILABLE = "calibration needs the robot's daemon (mazebot run)"



def running(application: web.Application) -> bool:
    """Whether a calibration drives the motors now (the jog endpoint refuses meanwhile)."""
    calibration = application.get(CALIBRATION_KEY)
    return calibration is not None and calibration.running


async def _authorized(request: web.Request, command: str) -> web.Response | None:
    """The PIN check of start/stop and jog; a response when refused."""
    if (refused := authorize_command(request, command)) is not None:
        return refused
    return None


async def _json_body(request: web.Request) -> dict[str, Any]:
    if not request.can_read_body:
        return {}
    try:
        body = await request.json()
    except ValueError:
        return {}
    return body if isinstance(body, dict) else {}


async def _calibration_for_a_command(request: web.Request) -> PageCalibration | web.Response:
    """The page's calibration for a command that changes it; a response when the PIN is refused or there is none."""
    if (denied := await _authorized(request, "calibration")) is not None:
        return denied
    calibration = request.app.get(CALIBRATION_KEY)
    if calibration is None:
        return web.json_response({"error": UNAVAILABLE}, status=409)
    return calibration


async def post_calibration(request: web.Request) -> web.Response:
    calibration = await _calibration_for_a_command(request)
    if isinstance(calibration, web.Response):
        return calibration
    if (refusal := calibration.refusal()) is not None:
        return web.json_response({"error": refusal}, status=409)
    return web.json_response(calibration.start().as_json())


async def get_calibration(request: web.Request) -> web.Response:
    if (denied := check_view(request)) is not None:
        return denied
    calibration = request.app.get(CALIBRATION_KEY)
    if calibration is None:
        return web.json_response({"available": False, "why": UNAVAILABLE, "run": None})
    run = calibration.seen(request.query.get("id"))
    if run is None:  # another page, or none started: the state without keeping it alive, and without its id
        run_json = None if calibration.run is None else {**calibration.run.as_json(), "id": None}
    else:
        run_json = run.as_json()
    return web.json_response({"available": True, "refused": calibration.refusal(), "run": run_json},
                             headers={"Cache-Control": "no-store"})


async def post_calibration_stop(request: web.Request) -> web.Response:
    if (denied := await _authorized(request, "calibration")) is not None:
        return denied
    calibration = request.app.get(CALIBRATION_KEY)
    stopped = calibration is not None and calibration.stop("stopped from the page")
    return web.json_response({"stopped": stopped})


async def post_calibration_write(request: web.Request) -> web.Response:
    calibration = await _calibration_for_a_command(request)
    if isinstance(calibration, web.Response):
        return calibration
    body = await _json_body(request)
    try:
        run = calibration.write(body.get("id"))
    except CalibrationError as error:
        return web.json_response({"error": str(error)}, status=409)
    except OSError as error:  # the state directory itself (the report)
        return web.json_response({"error": f"cannot write the calibration report: {error.strerror or error}"},
                                 status=500)
    return web.json_response(run.as_json())


async def get_calibration_png(request: web.Request) -> web.Response:
    if (denied := check_view(request)) is not None:
        return denied
    calibration = request.app.get(CALIBRATION_KEY)
    run = None if calibration is None else calibration.run
    if run is None or run.report_png is None:
        return web.json_response({"error": "no finished calibration"}, status=404)
    return web.Response(body=run.report_png, content_type="image/png", headers={"Cache-Control": "no-store"})


async def _stop_on_shutdown(application: web.Application) -> None:
    calibration = application.get(CALIBRATION_KEY)
    if calibration is not None:
        await calibration.close()


def add_routes(application: web.Application, calibration: PageCalibration | None) -> None:
    application.router.add_post("/api/calibration", post_calibration)
    application.router.add_get("/api/calibration", get_calibration)
    application.router.add_post("/api/calibration/stop", post_calibration_stop)
    application.router.add_post("/api/calibration/write", post_calibration_write)
    application.router.add_get("/api/calibration.png", get_calibration_png)
    if calibration is not None:
        application[CALIBRATION_KEY] = calibration
        application.on_shutdown.append(_stop_on_shutdown)
