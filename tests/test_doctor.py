"""``mazebot doctor``: each check's verdicts, and ``doctor --sim`` on a healthy and on a broken robot.

The simulated runs use the real drivers: the lidar emulator on a pseudo-terminal opened as
a serial port, the encoders on gpiozero mock pins, the motors on the simulator's HAT.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import errno
import json
from pathlib import Path

import pytest

from mazebot.cli import main
from mazebot.clock import RealClock
from mazebot.config import Config
from mazebot.doctor import (
    Pulse,
    SystemProbe,
    check_clock,
    check_power,
    check_serial_port,
    check_temperature,
    judge_pulses,
    parse_throttled,
    passed,
    pulse_motor,
)
from mazebot.doctor_cli import run_checks
from mazebot.io.motors import DifferentialMotors, FakeMotorKit
from mazebot.sim.doctor_sim import SIM_FAULTS, sim_parts


def test_throttled_flags_are_read_in_both_formats() -> None:
    assert parse_throttled("throttled=0x50005") == 0x50005  # vcgencmd get_throttled
    assert parse_throttled("50005\n") == 0x50005  # the firmware's sysfs file


@pytest.mark.parametrize(("text", "status", "words"), [
    ("0", "ok", "no under-voltage"),
    ("50000", "warn", "under-voltage since boot, throttled since boot"),
    ("throttled=0x1", "FAIL", "under-voltage now"),
    ("80008", "FAIL", "soft temperature limit now, soft temperature limit since boot"),
])
def test_power_names_each_flag(text: str, status: str, words: str) -> None:
    verdict = check_power(SystemProbe(throttled=lambda: text))
    assert verdict.status == status
    assert words in verdict.detail


def test_off_a_pi_the_firmware_checks_are_skipped_not_failed() -> None:
    probe = SystemProbe(throttled=lambda: None, cpu_temp_text=lambda: None)
    verdicts = [check_power(probe), check_temperature(probe)]
    assert [v.status for v in verdicts] == ["skip", "skip"]
    assert "not a Raspberry Pi" in verdicts[0].detail
    assert passed(verdicts)


def test_temperature_is_read_in_millidegrees() -> None:
    assert check_temperature(SystemProbe(cpu_temp_text=lambda: "52300")).detail == "52.3 °C"
    assert check_temperature(SystemProbe(cpu_temp_text=lambda: "73000")).status == "warn"


def test_an_unsynchronized_clock_warns_and_an_unset_one_fails() -> None:
    now = dt.datetime(2026, 5, 1, tzinfo=dt.UTC)
    assert check_clock(SystemProbe(now=lambda: now, ntp_synchronized=lambda: False)).status == "warn"
    assert check_clock(SystemProbe(now=lambda: now, ntp_synchronized=lambda: True)).status == "ok"
    old = dt.datetime(2023, 1, 1, tzinfo=dt.UTC)
    assert check_clock(SystemProbe(now=lambda: old, ntp_synchronized=lambda: True)).status == "FAIL"


def test_a_real_port_that_is_missing_or_refused(tmp_path: Path) -> None:
    missing = check_serial_port(SystemProbe(), str(tmp_path / "ttyUSB0"))
    assert missing.status == "FAIL" and "No such file" in missing.detail

    def refuse(port: str) -> None:
        raise PermissionError(errno.EACCES, "Permission denied", port)

    refused = check_serial_port(SystemProbe(open_port=refuse), "/dev/ttyUSB0")
    assert refused.status == "FAIL" and "dialout" in refused.action


def test_pulses_judged_healthy_swapped_dead_and_inverted() -> None:
    def parts(pulses: list[Pulse]) -> dict[str, str]:
        return {v.part: v.status for v in judge_pulses(pulses, ticks_per_rev=840)}

    healthy = parts([Pulse("left", 400, 0), Pulse("right", 1, 390)])
    assert healthy == {"motor channels": "ok", "left encoder": "ok", "right encoder": "ok"}
    assert parts([Pulse("left", 0, 400), Pulse("right", 390, 0)])["motor channels"] == "FAIL"
    dead = parts([Pulse("left", 0, 0), Pulse("right", 0, 390)])
    assert (dead["left encoder"], dead["right encoder"], dead["motor channels"]) == ("FAIL", "ok", "ok")
    assert parts([Pulse("left", 400, 0), Pulse("right", 0, -390)])["right encoder"] == "FAIL"


class _Encoders:
    def read(self) -> object:
        from mazebot.io.encoders import EncoderReading

        return EncoderReading(0, 0, 0)


class _Interrupting(RealClock):
    """The clock of a doctor whose user presses Ctrl-C during the first pulse."""

    async def sleep(self, seconds: float) -> None:
        raise KeyboardInterrupt


def test_ctrl_c_during_a_pulse_leaves_both_motors_braked() -> None:
    kit = FakeMotorKit()
    clock = _Interrupting()

    async def go() -> None:
        motors = DifferentialMotors(kit, command_ttl_s=0.3, clock=clock)
        await pulse_motor(motors, _Encoders(), clock, "left")

    with pytest.raises(KeyboardInterrupt):
        asyncio.run(go())
    assert any(w.throttle == 0.5 for w in kit.command_log)  # it did drive ...
    assert (kit.motor1.throttle, kit.motor2.throttle) == (0.0, 0.0)  # ... and braked on the way out


def test_a_pulse_is_bounded_by_the_command_time_to_live() -> None:
    """A pulse that is never refreshed (its task starved) is braked by the driver's own TTL."""
    kit = FakeMotorKit()

    async def go() -> tuple[float | None, float | None]:
        motors = DifferentialMotors(kit, command_ttl_s=0.05, clock=RealClock())
        motors.set(0.5, 0.0)  # the first write of a pulse ...
        await asyncio.sleep(0.2)  # ... and then nothing (no refresh, no finally yet)
        return kit.motor1.throttle, kit.motor2.throttle

    assert asyncio.run(go()) == (0.0, 0.0)


def test_doctor_sim_passes_on_the_healthy_robot_and_leaves_the_motors_braked() -> None:
    async def go() -> tuple[list, FakeMotorKit]:
        config = Config()
        async with sim_parts(config) as parts:
            verdicts = await run_checks(config, parts)
            return verdicts, parts.open_kit()

    verdicts, kit = asyncio.run(go())
    assert [v.line() for v in verdicts if v.status != "ok"] == []
    parts_seen = {v.part for v in verdicts}
    assert set(SIM_FAULTS.values()) <= parts_seen
    assert any(w.throttle not in (0.0, None) for w in kit.command_log)  # the wheels were pulsed
    assert (kit.motor1.throttle, kit.motor2.throttle) == (0.0, 0.0)


@pytest.mark.parametrize("fault", sorted(SIM_FAULTS))
def test_doctor_sim_names_each_injected_fault(fault: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["doctor", "--sim", "--sim-fault", fault, "--json"]) == 1
    report = json.loads(capsys.readouterr().out)
    failed = [c["part"] for c in report["checks"] if c["status"] == "FAIL"]
    assert failed == [SIM_FAULTS[fault]]  # that part, and no other
    assert report["passed"] is False
    assert all(c["action"] for c in report["checks"] if c["status"] == "FAIL" and c["part"] != "motor driver")


def test_doctor_sim_exit_code_and_lines(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["doctor", "--sim"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[-1] == "all checks passed"
    assert any(line.startswith("ok   lidar rotation: ") and "samples per revolution" in line for line in out)


def test_a_fault_without_sim_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["doctor", "--sim-fault", "hot"]) == 2
    assert "--sim-fault only makes sense with --sim" in capsys.readouterr().err
