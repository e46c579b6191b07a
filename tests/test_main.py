"""The whole daemon on the simulated robot: starts, serves, faults safely, stops on signals."""

from __future__ import annotations

import asyncio
import gc
import os
import signal
import subprocess
import sys
import threading
import time
from contextlib import AsyncExitStack
from pathlib import Path

import aiohttp
import pytest
from aiohttp.test_utils import unused_port
from gpiozero import InputDevice
from gpiozero.pins.mock import MockFactory

from mazebot import main as main_module
from mazebot.cli import main
from mazebot.clock import Clock
from mazebot.config import Config
from mazebot.errors import HardwareUnavailable, MazebotError
from mazebot.io.motors import FakeMotorKit
from mazebot.main import Hardware, robot_hardware_builder, run_daemon
from mazebot.sim.backend import sim_hardware_builder
from mazebot.state import RunState, SharedState
from mazebot.tasks.supervisor import Supervisor

CONTROL_TOKEN = "2468"


def _config(port: int) -> Config:
    config = Config()
    config.web.host = "127.0.0.1"
    config.web.port = port
    config.web.control_token = CONTROL_TOKEN
    return config


async def _get_status(port: int) -> dict:
    async with aiohttp.ClientSession() as session, session.get(f"http://127.0.0.1:{port}/api/status") as resp:
        assert resp.status == 200
        return await resp.json()


@pytest.mark.slow
async def test_daemon_runs_the_real_drivers_on_the_simulated_robot() -> None:
    port = unused_port()
    ready = asyncio.Event()
    started: dict[str, object] = {}

    def on_started(hw: Hardware, state: SharedState, sup: Supervisor) -> None:
        started.update(hw=hw, state=state, sup=sup)

    daemon = asyncio.create_task(
        run_daemon(_config(port), sim_hardware_builder(), ready=ready, install_signal_handlers=False,
                   on_started=on_started, autonomous=False)
    )
    await asyncio.wait_for(ready.wait(), 10)
    state: SharedState = started["state"]  # type: ignore[assignment]
    hw: Hardware = started["hw"]  # type: ignore[assignment]
    # a few revolutions come through the emulator, the byte stream and the real driver
    for _ in range(100):
        if state.sensors.lidar_revolutions >= 3:
            break
        await asyncio.sleep(0.1)
    # start-up's objects sit out the garbage collector's full scans (57 ms each on the loop otherwise)
    assert gc.get_freeze_count() > 10_000
    status = await _get_status(port)
    assert status["state"] == "idle"
    assert status["sensors"]["lidar_revolutions"] >= 3
    assert status["sensors"]["lidar_bytes_dropped"] == 0
    assert state.latest_scan is not None and state.latest_scan.valid.sum() > 100

    # start: the control task may now apply commands; stop: zero at once
    async with aiohttp.ClientSession() as session:
        async with session.post(f"http://127.0.0.1:{port}/api/start", headers={"X-Mazebot-Token": "0000"}) as resp:
            assert resp.status == 403  # a wrong PIN moves nothing
        async with session.post(f"http://127.0.0.1:{port}/api/start",
                                headers={"X-Mazebot-Token": CONTROL_TOKEN}) as resp:
            assert resp.status == 200
        await asyncio.sleep(0.1)
        assert state.run_state is RunState.EXPLORING
        state.throttle_command = (0.5, 0.5, asyncio.get_running_loop().time() + 10.0)
        await asyncio.sleep(0.3)
        assert state.sensors.encoder_ticks_left > 0  # the wheels turned and the encoders counted
        async with session.post(f"http://127.0.0.1:{port}/api/stop",
                                headers={"X-Mazebot-Token": CONTROL_TOKEN}) as resp:
            assert resp.status == 200
        await asyncio.sleep(0.1)
    assert state.run_state is RunState.STOPPED
    kit = hw.sim.kit
    assert kit.motor1.throttle == 0.0 and kit.motor2.throttle == 0.0

    started["sup"].request_stop("test over")  # type: ignore[union-attr]
    assert await asyncio.wait_for(daemon, 10) == 0
    assert gc.get_freeze_count() == 0  # collectable again once the daemon is over


async def test_the_page_is_served_with_the_motors_zeroed_before_slam_and_planner_are_imported(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Start-up imports SLAM and the planner (numpy, scipy: most of it) after the web server is up,
    in a thread, so the page answers meanwhile; the motors are zero all along."""
    port = unused_port()
    importing, release = threading.Event(), threading.Event()
    opened: list[Hardware] = []
    real_import = main_module._import_the_robot

    def slow_import() -> None:
        importing.set()
        release.wait(timeout=30)  # held until the page answered (never forever)
        real_import()

    monkeypatch.setattr(main_module, "_import_the_robot", slow_import)
    sim = sim_hardware_builder()

    async def build(config: Config, clock: Clock, stack: AsyncExitStack) -> Hardware:
        opened.append(await sim(config, clock, stack))
        return opened[0]

    ready = asyncio.Event()
    stop = asyncio.Event()

    def on_started(hw: Hardware, state: SharedState, sup: Supervisor) -> None:
        asyncio.get_running_loop().create_task(stop.wait()).add_done_callback(lambda _: sup.request_stop("test over"))

    daemon = asyncio.create_task(run_daemon(_config(port), build, ready=ready, install_signal_handlers=False,
                                            on_started=on_started, autonomous=False))
    try:
        await asyncio.wait_for(asyncio.to_thread(importing.wait, 20), 25)
        assert importing.is_set() and not ready.is_set()
        async with aiohttp.ClientSession() as session, session.get(f"http://127.0.0.1:{port}/") as resp:
            assert resp.status == 200
            assert "<script" in await resp.text()
        kit = opened[0].sim.kit
        assert kit.motor1.throttle == 0.0 and kit.motor2.throttle == 0.0
    finally:
        release.set()
    await asyncio.wait_for(ready.wait(), 20)
    stop.set()
    assert await asyncio.wait_for(daemon, 10) == 0


@pytest.mark.slow
async def test_a_crashing_task_stops_the_motors_and_the_daemon_keeps_serving() -> None:
    port = unused_port()
    ready = asyncio.Event()
    started: dict[str, object] = {}

    def on_started(hw: Hardware, state: SharedState, sup: Supervisor) -> None:
        started.update(hw=hw, state=state, sup=sup)

        async def broken() -> None:
            await asyncio.sleep(0.2)
            raise ValueError("matrix not positive definite")

        state.run_state = RunState.EXPLORING
        hw.motors.set(0.4, 0.4)
        sup.start("planner", broken)

    daemon = asyncio.create_task(
        run_daemon(_config(port), sim_hardware_builder(), ready=ready, install_signal_handlers=False,
                   on_started=on_started, autonomous=False)
    )
    await asyncio.wait_for(ready.wait(), 10)
    await asyncio.sleep(0.5)
    status = await _get_status(port)
    assert status["state"] == "fault"
    assert status["fault"]["source"] == "planner"
    assert "ValueError: matrix not positive definite" in status["fault"]["message"]
    kit = started["hw"].sim.kit  # type: ignore[union-attr]
    assert kit.motor1.throttle == 0.0 and kit.motor2.throttle == 0.0
    assert not daemon.done()
    started["sup"].request_stop("test over")  # type: ignore[union-attr]
    assert await asyncio.wait_for(daemon, 10) == 0


@pytest.mark.slow
async def test_sigterm_zeroes_the_motors_at_once_and_exits_0() -> None:
    port = unused_port()
    ready = asyncio.Event()
    started: dict[str, object] = {}

    def on_started(hw: Hardware, state: SharedState, sup: Supervisor) -> None:
        started.update(hw=hw, state=state)
        state.run_state = RunState.EXPLORING
        state.throttle_command = (0.6, 0.6, asyncio.get_running_loop().time() + 60.0)

    daemon = asyncio.create_task(run_daemon(_config(port), sim_hardware_builder(), ready=ready, on_started=on_started,
                                            autonomous=False))
    await asyncio.wait_for(ready.wait(), 10)
    await asyncio.sleep(0.2)
    kit = started["hw"].sim.kit  # type: ignore[union-attr]
    assert kit.motor1.throttle != 0.0  # driving
    loop = asyncio.get_running_loop()
    sent_s = loop.time()
    os.kill(os.getpid(), signal.SIGTERM)
    assert await asyncio.wait_for(daemon, 10) == 0
    # counted, not timed (the latency in milliseconds is bench/stop_latency.py's figure): at most
    # one control tick (a write to each motor) may still go out before the stop, nothing moves after
    after = [w for w in kit.command_log if w.time_s >= sent_s]
    first_stop = next((k for k, w in enumerate(after) if w.throttle == 0.0), None)
    assert first_stop is not None, "no stop written after SIGTERM"
    assert first_stop <= 2, after[: first_stop + 1]
    assert all(not w.throttle for w in after[first_stop:])


@pytest.mark.slow
def test_run_sim_serves_the_page_and_stops_cleanly_on_sigterm(tmp_path: Path) -> None:
    port = unused_port()
    t0 = time.monotonic()
    env = {**os.environ, "XDG_STATE_HOME": str(tmp_path)}  # the generated PIN goes here, not to ~
    proc = subprocess.Popen([sys.executable, "-m", "mazebot", "run", "--sim", "--host", "127.0.0.1",
                             "--port", str(port)], stderr=subprocess.PIPE, text=True, env=env)
    try:
        served = False
        # a generous deadline, not a speed check: how fast it serves is bench/startup_time.py's figure
        while time.monotonic() - t0 < 60.0 and not served:
            try:
                served = asyncio.run(_get_status(port))["version"] is not None
            except aiohttp.ClientError:
                time.sleep(0.1)
        assert served, "nothing served on the port within 60 s"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
        stderr = proc.stderr.read()
        assert "Traceback" not in stderr
        token = (tmp_path / "mazebot" / "control_token").read_text().strip()
        assert stderr.count(token) == 1  # the generated PIN is logged once, on first start
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.stderr.close()


def test_real_run_without_hardware_exits_69_naming_the_device() -> None:
    proc = subprocess.run([sys.executable, "-m", "mazebot", "run"], capture_output=True, text=True, timeout=60,
                          check=False)
    assert proc.returncode == 69
    lines = proc.stderr.strip().splitlines()
    assert lines[-1].startswith("mazebot: motor HAT not found at I2C address 0x60")
    assert "Traceback" not in proc.stderr


@pytest.mark.parametrize("argv", [["run", "--seed", "3"], ["run", "--sim", "--size", "1x99"]])
def test_bad_run_arguments_exit_2(argv: list[str]) -> None:
    proc = subprocess.run([sys.executable, "-m", "mazebot", *argv], capture_output=True, text=True, timeout=60,
                          check=False)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr


# -- a real run with a device missing: exit 69 naming it, and no motor left commanded ---------------------


def _hat_left_driving() -> FakeMotorKit:
    """A HAT as a crashed daemon leaves it: the PCA9685 keeps driving at its last PWM."""
    kit = FakeMotorKit()
    kit.motor1.throttle = 0.7
    kit.motor2.throttle = -0.7
    return kit


def _assert_braked(kit: FakeMotorKit) -> None:
    assert kit.motor1.throttle == 0.0 and kit.motor2.throttle == 0.0
    assert kit.command_log[-1].throttle == 0.0 and kit.command_log[-2].throttle == 0.0


async def _real_run(config: Config, **devices: object) -> str:
    """Start a real (non-sim) run on the given device stand-ins; the error (exit 69) it ends with."""
    with pytest.raises(MazebotError) as info:
        await asyncio.wait_for(run_daemon(config, robot_hardware_builder(**devices), install_signal_handlers=False,
                                          serve_web=False), 30)
    assert info.value.exit_code == 69
    message = str(info.value)
    assert "\n" not in message
    return message


def _no_gpio() -> object:
    raise ImportError("No module named 'lgpio'")


async def test_a_missing_hat_exits_69_before_any_other_device_is_touched() -> None:
    touched = []

    def no_hat(address: int, frequency_hz: float) -> FakeMotorKit:
        raise HardwareUnavailable(f"motor HAT not found at I2C address {address:#04x} (ValueError: No I2C device)")

    message = await _real_run(_config(unused_port()), open_kit=no_hat,
                              make_pin_factory=lambda: touched.append("gpio") or MockFactory())
    assert message.startswith("motor HAT not found at I2C address 0x60")
    assert touched == []


async def test_a_hat_that_refuses_writes_exits_69_naming_the_motor() -> None:
    kit = FakeMotorKit()
    kit.fail_writes()
    message = await _real_run(_config(unused_port()), open_kit=lambda a, f: kit, make_pin_factory=MockFactory)
    assert message.startswith("motor HAT write failed on motor1 (left)"), message


async def test_no_gpio_exits_69_naming_it_and_the_wheels_are_braked() -> None:
    kit = _hat_left_driving()
    message = await _real_run(_config(unused_port()), open_kit=lambda a, f: kit, make_pin_factory=_no_gpio)
    assert message.startswith("GPIO for the wheel encoders is not available (ImportError: No module named 'lgpio')")
    _assert_braked(kit)


async def test_encoder_pins_held_by_another_program_exit_69_naming_the_pins() -> None:
    kit = _hat_left_driving()
    factory = MockFactory()
    squatter = InputDevice(17, pin_factory=factory)  # another program holds the left A pin
    message = await _real_run(_config(unused_port()), open_kit=lambda a, f: kit, make_pin_factory=lambda: factory)
    assert message.startswith("wheel encoder pins GPIO17/GPIO18/GPIO22/GPIO23 cannot be used (GPIOPinInUse")
    _assert_braked(kit)
    squatter.close()


async def test_a_missing_lidar_port_exits_69_naming_the_port_and_releases_the_rest(tmp_path: Path) -> None:
    kit = _hat_left_driving()
    factory = MockFactory()
    config = _config(unused_port())
    config.lidar.port = str(tmp_path / "ttyUSB9")
    message = await _real_run(config, open_kit=lambda a, f: kit, make_pin_factory=lambda: factory)
    assert message.startswith(f"lidar serial port {config.lidar.port} cannot be opened (No such file or directory)")
    _assert_braked(kit)
    InputDevice(17, pin_factory=MockFactory()).close()  # the encoders let their pins go
    assert factory.pins == {} or all(p.function == "input" for p in factory.pins.values())


async def test_a_lidar_that_never_answers_exits_69_naming_its_port() -> None:
    kit = _hat_left_driving()
    device, port = os.openpty()  # a serial port with nothing behind it
    config = _config(unused_port())
    config.lidar.port = os.ttyname(port)
    try:
        message = await _real_run(config, open_kit=lambda a, f: kit, make_pin_factory=MockFactory)
        received = os.read(device, 64)
    finally:
        os.close(device)
        os.close(port)
    assert message == (f"lidar on {config.lidar.port} did not answer GET_HEALTH within 1 s; "
                       "check that the lidar is powered and that this is its port")
    assert received.startswith(b"\xa5\x25\xa5\x52")  # STOP (a scan left running), then GET_HEALTH
    _assert_braked(kit)


@pytest.mark.slow
async def test_run_sim_needs_no_hat_no_gpio_and_no_serial_port(monkeypatch: pytest.MonkeyPatch) -> None:
    def forbidden(*args: object, **kwargs: object) -> None:
        raise AssertionError("the simulated run touched a real device")

    monkeypatch.setattr("mazebot.io.motors.open_motorkit", forbidden)
    monkeypatch.setattr("mazebot.io.serial_link.SerialLink.open", forbidden)
    monkeypatch.setitem(sys.modules, "adafruit_motorkit", None)  # importing them raises ImportError
    monkeypatch.setitem(sys.modules, "gpiozero.pins.lgpio", None)
    config = _config(unused_port())
    config.lidar.port = "/nonexistent/ttyUSB0"
    ready = asyncio.Event()
    started: dict[str, object] = {}
    daemon = asyncio.create_task(run_daemon(config, sim_hardware_builder(), ready=ready, install_signal_handlers=False,
                                            on_started=lambda hw, st, sup: started.update(state=st, sup=sup),
                                            autonomous=False))
    await asyncio.wait_for(ready.wait(), 10)
    for _ in range(100):
        if started["state"].sensors.lidar_revolutions >= 2:  # type: ignore[attr-defined]
            break
        await asyncio.sleep(0.1)
    assert started["state"].sensors.lidar_revolutions >= 2  # type: ignore[attr-defined]
    started["sup"].request_stop("test over")  # type: ignore[attr-defined]
    assert await asyncio.wait_for(daemon, 10) == 0


@pytest.mark.parametrize(("argv", "message"), [
    (["--port", "0"], "--port 0: Input should be greater than or equal to 1"),
    (["--port", "70000"], "--port 70000: Input should be less than or equal to 65535"),
])
def test_bad_host_or_port_overrides_are_usage_errors(capsys: pytest.CaptureFixture[str], argv: list[str],
                                                      message: str) -> None:
    assert main(["run", "--sim", *argv]) == 2
    assert capsys.readouterr().err == f"mazebot: {message}\n"
