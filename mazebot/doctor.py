"""``mazebot doctor``: every part of the robot checked, one line each, with what to do.

A maker's first evening is spent finding out why a wheel spins backwards or why the lidar
shows nothing. Each check here looks at one part through the same drivers the daemon uses
(:class:`mazebot.io.rplidar.RPLidar`, :class:`mazebot.io.encoders.WheelEncoders`,
:class:`mazebot.io.motors.DifferentialMotors`) and gives a :class:`Verdict`: ``ok``,
``warn`` (works, but look at it), ``FAIL`` (fix it before a run) or ``skip`` (not there to
check on this machine, e.g. a Pi's firmware flags on a laptop; not a failure).

What the operating system tells (the serial port, the Pi's firmware flags, the CPU
temperature, free space, the clock) is read through a :class:`SystemProbe`, so the
simulated robot (``mazebot doctor --sim``, :mod:`mazebot.doctor_sim`) can show each
failure line by injecting a fault at that boundary.

Motor safety: each pulse is a :meth:`DifferentialMotors.set` refreshed well within the
command time-to-live (so a hung check brakes by itself), and the motors are stopped in a
``finally`` on every path.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import errno
import itertools
import math
import os
import shutil
import subprocess
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final, Literal

from mazebot.clock import Clock, RealClock
from mazebot.config import LidarConfig
from mazebot.errors import serial_port_hint

Status = Literal["ok", "warn", "FAIL", "skip"]

#: The Raspberry Pi firmware's throttling flags (the bits of ``vcgencmd get_throttled``),
#: as the Raspberry Pi documentation lists them:
#: https://www.raspberrypi.com/documentation/computers/os.html#get_throttled
THROTTLED_NOW: Final = {
    0: "under-voltage now",
    1: "ARM frequency capped now",
    2: "throttled now",
    3: "soft temperature limit now",
}
THROTTLED_SINCE_BOOT: Final = {
    16: "under-voltage since boot",
    17: "ARM frequency capped since boot",
    18: "throttled since boot",
    19: "soft temperature limit since boot",
}
#: The firmware's flags as a file (the raspberrypi firmware driver's sysfs attribute).
THROTTLED_SYSFS: Final = "/sys/devices/platform/soc/soc:firmware/get_throttled"
THERMAL_ZONE: Final = "/sys/class/thermal/thermal_zone0/temp"
#: The Pi 4/5 firmware throttles the ARM from 80 °C (Raspberry Pi documentation, "Frequency
#: management and thermal control"); warn well before.
TEMP_WARN_C: Final = 70.0
TEMP_FAIL_C: Final = 80.0
#: Free space in the state directory: runs and recordings need room (an MCAP of a 10-minute
#: run is tens of MB).
DISK_FAIL_B: Final = 100 * 1024**2
DISK_WARN_B: Final = 1024**3
#: A Pi has no real-time clock: until NTP answers it starts from the time saved at the last
#: shutdown (fake-hwclock), or 1970. A year before this one cannot be today's.
PLAUSIBLE_YEAR: Final = 2025
#: Revolutions watched for the rotation rate and the plausibility of a revolution.
REVOLUTIONS: Final = 4
#: More invalid samples than this in a revolution: the lidar sees little (dirty window, an
#: open room beyond its range); above the FAIL share it sees nearly nothing.
INVALID_WARN: Final = 0.35
INVALID_FAIL: Final = 0.8
#: Nominal rotation of an A1 is 5.5 Hz; the family runs 5-15 Hz (datasheets).
ROTATION_HZ: Final = (2.0, 20.0)


@dataclass(frozen=True)
class Verdict:
    """One checked part: its status, what was seen, and what to do about it."""

    part: str
    status: Status
    detail: str
    action: str = ""

    def line(self) -> str:
        tail = f" -> {self.action}" if self.action and self.status != "ok" else ""
        return f"{self.status:<4} {self.part}: {self.detail}{tail}"

    def as_json(self) -> dict[str, str]:
        return {"part": self.part, "status": self.status, "detail": self.detail, "action": self.action}


def passed(verdicts: list[Verdict]) -> bool:
    """All passed: nothing FAILed (a warning or a skip does not fail)."""
    return all(v.status != "FAIL" for v in verdicts)


# --- what the operating system tells ---------------------------------------------------


def _read_text(path: str) -> str | None:
    try:
        return Path(path).read_text(encoding="ascii").strip()
    except (OSError, UnicodeDecodeError):
        return None


def _vcgencmd_throttled() -> str | None:
    exe = shutil.which("vcgencmd")
    if exe is None:
        return None
    try:
        out = subprocess.run([exe, "get_throttled"], capture_output=True, text=True, timeout=5, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def _ntp_synchronized() -> bool | None:
    """systemd's NTPSynchronized (``timedatectl show``); None where there is no timedatectl."""
    exe = shutil.which("timedatectl")
    if exe is None:
        return None
    try:
        out = subprocess.run([exe, "show", "--property=NTPSynchronized", "--value"], capture_output=True,
                             text=True, timeout=5, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return None
    value = out.stdout.strip()
    return {"yes": True, "no": False}.get(value) if out.returncode == 0 else None


def _open_port(port: str) -> None:
    fd = os.open(port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    os.close(fd)


@dataclass
class SystemProbe:
    """The operating system as the doctor reads it; each field can be replaced (the simulated robot does)."""

    throttled: Callable[[], str | None] = field(
        default=lambda: _read_text(THROTTLED_SYSFS) or _vcgencmd_throttled())
    cpu_temp_text: Callable[[], str | None] = field(default=lambda: _read_text(THERMAL_ZONE))
    ntp_synchronized: Callable[[], bool | None] = _ntp_synchronized
    now: Callable[[], dt.datetime] = field(default=lambda: dt.datetime.now(dt.UTC))
    disk_usage: Callable[[str], Any] = shutil.disk_usage
    open_port: Callable[[str], None] = _open_port


def parse_throttled(text: str) -> int:
    """The flags of ``throttled=0x50005`` (vcgencmd) or ``50005`` (the sysfs file, hexadecimal)."""
    value = text.strip().removeprefix("throttled=")
    return int(value, 16)


def check_power(probe: SystemProbe) -> Verdict:
    text = probe.throttled()
    if text is None:
        return Verdict("power", "skip", "not a Raspberry Pi (no firmware throttling flags): skipped")
    try:
        flags = parse_throttled(text)
    except ValueError:
        return Verdict("power", "warn", f"cannot read the firmware's throttling flags {text!r}",
                       "update the Pi's firmware")
    now = [name for bit, name in THROTTLED_NOW.items() if flags >> bit & 1]
    since = [name for bit, name in THROTTLED_SINCE_BOOT.items() if flags >> bit & 1]
    supply = ("power the Pi from a 5 V supply that holds up when the motors start (5.1 V 3 A, short thick "
              "cable), and the motors from their own battery")
    if now:
        return Verdict("power", "FAIL", f"{', '.join(now + since)} (flags {flags:#x})", supply)
    if since:
        return Verdict("power", "warn", f"{', '.join(since)} (flags {flags:#x}): a brown-out happened", supply)
    return Verdict("power", "ok", f"no under-voltage or throttling since boot (flags {flags:#x})")


def check_temperature(probe: SystemProbe) -> Verdict:
    text = probe.cpu_temp_text()
    if text is None:
        return Verdict("CPU temperature", "skip", f"no {THERMAL_ZONE} on this machine: skipped")
    try:
        temp_c = int(text) / 1000.0  # millidegrees Celsius (Linux thermal sysfs ABI)
    except ValueError:
        return Verdict("CPU temperature", "warn", f"unreadable temperature {text!r}")
    cool = "give the Pi a heatsink or a fan and air around it"
    if temp_c >= TEMP_FAIL_C:
        return Verdict("CPU temperature", "FAIL", f"{temp_c:.1f} °C: the Pi throttles from {TEMP_FAIL_C:.0f} °C", cool)
    if temp_c >= TEMP_WARN_C:
        return Verdict("CPU temperature", "warn", f"{temp_c:.1f} °C, close to throttling", cool)
    return Verdict("CPU temperature", "ok", f"{temp_c:.1f} °C")


def check_disk(probe: SystemProbe, state_dir: Path) -> Verdict:
    where = state_dir
    while not where.exists() and where != where.parent:
        where = where.parent  # the state dir is made on the first run: ask its filesystem
    try:
        free_b = int(probe.disk_usage(str(where)).free)
    except OSError as exc:
        return Verdict("free space", "FAIL", f"cannot look at {state_dir} ({exc.strerror or exc})",
                       "set [daemon] state_dir to a folder this user can write")
    text = f"{free_b / 1024**3:.2f} GB free for {state_dir}"
    clean = "delete old runs (`mazebot runs`) and recordings, or use a larger SD card"
    if free_b < DISK_FAIL_B:
        return Verdict("free space", "FAIL", text, clean)
    if free_b < DISK_WARN_B:
        return Verdict("free space", "warn", text, clean)
    return Verdict("free space", "ok", text)


def check_clock(probe: SystemProbe) -> Verdict:
    now = probe.now()
    if now.year < PLAUSIBLE_YEAR:
        return Verdict("clock", "FAIL", f"the clock says {now:%Y-%m-%d}: it was never set",
                       "connect the Pi to a network with internet (NTP) or set the time: sudo date -s ...")
    synced = probe.ntp_synchronized()
    if synced is False:
        return Verdict("clock", "warn", f"{now:%Y-%m-%d %H:%M} UTC, not synchronized by NTP",
                       "run names and recordings carry this time; check the network and timedatectl")
    how = "NTP synchronized" if synced else "no timedatectl to ask about NTP"
    return Verdict("clock", "ok", f"{now:%Y-%m-%d %H:%M} UTC ({how})")


def check_serial_port(probe: SystemProbe, port: str) -> Verdict:
    try:
        probe.open_port(port)
    except OSError as exc:
        # the same one-line hint the driver gives (it names the dialout group)
        status: Status = "FAIL"
        part = "serial port"
        if exc.errno in (errno.EACCES, errno.EPERM):
            return Verdict(part, status, f"{port} exists but this user may not open it",
                           "add your user to the 'dialout' group (sudo usermod -aG dialout $USER, then log in again)")
        return Verdict(part, status, f"{port}: {exc.strerror or exc}", serial_port_hint(port, exc).split("; ", 1)[-1])
    return Verdict("serial port", "ok", f"{port} opens for reading and writing")


def system_checks(probe: SystemProbe, state_dir: Path) -> list[Verdict]:
    """The checks that move nothing and talk to no device (the page runs these while the robot runs)."""
    return [check_power(probe), check_temperature(probe), check_disk(probe, state_dir), check_clock(probe)]


# --- the lidar -------------------------------------------------------------------------


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


async def lidar_checks(lidar: Any, *, revolutions: int = REVOLUTIONS, timeout_s: float = 6.0) -> list[Verdict]:
    """GET_INFO, GET_HEALTH, the scan modes, then a few revolutions: rotation rate and plausibility.

    ``lidar`` is an :class:`mazebot.io.rplidar.RPLidar`; the caller closes it (which stops
    the scan and the motor). A lidar that does not answer fails the first check and skips
    the rest (they would say the same).
    """
    from mazebot.errors import MazebotError
    from mazebot.io.rplidar_models import model_name

    out: list[Verdict] = []
    try:
        info = await lidar.get_info()
    except (MazebotError, OSError, TimeoutError) as exc:
        out.append(Verdict("lidar info", "FAIL", f"no answer to GET_INFO ({_one_line(exc)})",
                           "check the lidar's USB cable and [lidar] port and baudrate; power-cycle the lidar"))
        return out + [Verdict(p, "skip", "lidar did not answer") for p in
                      ("lidar health", "lidar scan modes", "lidar rotation", "lidar revolution")]
    out.append(Verdict("lidar info", "ok", f"{model_name(info.model)} firmware {info.firmware_version}, "
                                           f"hardware {info.hardware}, serial {info.serial_hex}"))
    try:
        health = await lidar.get_health()
        if health.status == 0:
            out.append(Verdict("lidar health", "ok", "good"))
        else:
            out.append(Verdict("lidar health", "FAIL" if health.status == 2 else "warn",
                               f"{health.status_name}, error code {health.error_code:#06x}",
                               "power-cycle the lidar; if it stays, check that its motor turns freely"))
        modes, typical = await lidar.get_scan_modes()
        names = ", ".join(m.name + (" (typical)" if m.id == typical else "") for m in modes)
        out.append(Verdict("lidar scan modes", "ok", names))
    except (MazebotError, OSError, TimeoutError) as exc:
        out.append(Verdict("lidar health", "FAIL", _one_line(exc), "power-cycle the lidar"))
        return out
    out.extend(await _revolution_checks(lidar, revolutions, timeout_s))
    return out


async def _revolution_checks(lidar: Any, revolutions: int, timeout_s: float) -> list[Verdict]:
    scans: list[Any] = []

    async def collect() -> None:
        async for scan in lidar.scans():
            scans.append(scan)
            if len(scans) > revolutions:
                return

    try:
        await asyncio.wait_for(collect(), timeout_s)
    except TimeoutError:
        pass
    except Exception as exc:  # a scan mode the unit lacks (ConfigError) and the like
        return [Verdict("lidar rotation", "FAIL", _one_line(exc), "check [lidar] scan_mode"),
                Verdict("lidar revolution", "skip", "no revolution")]
    full = scans[1:] if len(scans) > 1 else []  # the first revolution after a start is partial
    if len(full) < 2:
        return [Verdict("lidar rotation", "FAIL", f"{len(scans)} revolutions in {timeout_s:.0f} s: the head "
                        "does not turn or sends nothing",
                        "check that the lidar's motor spins (A1: its USB adapter's motor power, [lidar] "
                        "motor_control)"),
                Verdict("lidar revolution", "skip", "no full revolution")]
    starts = [s.start_time_s for s in full]
    periods = [b - a for a, b in itertools.pairwise(starts)]
    period_s = sorted(periods)[len(periods) // 2]
    rate_hz = 1.0 / period_s if period_s > 0 else math.inf
    samples = sorted(len(s) for s in full)[len(full) // 2]
    rotation = f"{rate_hz:.1f} Hz, {samples} samples per revolution ({lidar.active_mode.name} mode)"
    if not ROTATION_HZ[0] <= rate_hz <= ROTATION_HZ[1]:
        verdict_rot = Verdict("lidar rotation", "FAIL", rotation, "the head turns at a rate no RPLidar has: "
                              "check its motor supply")
    else:
        verdict_rot = Verdict("lidar rotation", "ok", rotation)
    return [verdict_rot, judge_revolution(full[-1])]


def judge_revolution(scan: Any) -> Verdict:
    """One revolution's plausibility: the share of invalid samples and the ranges seen."""
    n = max(1, len(scan))
    valid = int(scan.valid.sum())
    invalid = 1.0 - valid / n
    ranges = scan.range_m[scan.valid]
    detail = (f"{invalid:.0%} invalid samples, ranges {float(ranges.min()):.2f}-{float(ranges.max()):.2f} m"
              if valid else "no valid sample at all")
    see = "clean the lidar's window, and see that nothing covers it; walls must be within its range"
    if invalid > INVALID_FAIL:
        return Verdict("lidar revolution", "FAIL", detail, see)
    if invalid > INVALID_WARN:
        return Verdict("lidar revolution", "warn", detail, see)
    return Verdict("lidar revolution", "ok", detail)


# --- motors and encoders ----------------------------------------------------------------

#: Throttle and length of one motor pulse: a wheel turns a fraction of a revolution.
PULSE_THROTTLE: Final = 0.5
PULSE_S: Final = 0.4
#: After a pulse, wait this long for the wheel to come to rest before reading the counts.
SETTLE_S: Final = 0.25


@dataclass(frozen=True)
class Pulse:
    """What the encoders counted while one motor was pulsed forward."""

    side: str
    left_ticks: int
    right_ticks: int


async def pulse_motor(motors: Any, encoders: Any, clock: Clock, side: str, *, throttle: float = PULSE_THROTTLE,
                      pulse_s: float = PULSE_S) -> Pulse:
    """Drive one motor forward for ``pulse_s``, the other braked; the ticks each encoder counted.

    The throttle is re-sent every third of the command time-to-live, so if this task stops
    being run the driver's TTL brakes the motor; ``finally`` brakes both on every path.
    """
    before = encoders.read()
    left, right = (throttle, 0.0) if side == "left" else (0.0, throttle)
    refresh_s = motors.command_ttl_s / 3.0
    try:
        end_s = clock.now_s() + pulse_s
        while clock.now_s() < end_s:
            motors.set(left, right)
            await clock.sleep(min(refresh_s, max(0.0, end_s - clock.now_s())))
    finally:
        motors.stop()
    await clock.sleep(SETTLE_S)
    after = encoders.read()
    return Pulse(side, after.left_ticks - before.left_ticks, after.right_ticks - before.right_ticks)


def judge_pulses(pulses: list[Pulse], ticks_per_rev: int) -> list[Verdict]:
    """Encoders, their signs and the motor channel mapping from one pulse of each motor.

    A pulse turns its wheel a good part of a revolution; a count of at least 1/50 of a
    revolution is "moved", and the other wheel (braked) should stay below that.
    """
    moved = max(4, ticks_per_rev // 50)
    by_side = {p.side: p for p in pulses}
    out: list[Verdict] = []
    swapped = all(
        abs(getattr(p, f"{p.side}_ticks")) < moved and abs(getattr(p, f"{_other(p.side)}_ticks")) >= moved
        for p in pulses
    )
    if swapped and len(pulses) == 2:
        out.append(Verdict("motor channels", "FAIL", "pulsing the left motor turned the right wheel and the "
                           "other way round", "swap [motors] left_channel and right_channel (or the encoder "
                           "plugs: [encoders] left_*_pin and right_*_pin)"))
    else:
        out.append(Verdict("motor channels", "ok", "each motor turns its own wheel"))
    for side in ("left", "right"):
        p = by_side[side]
        own, other = getattr(p, f"{side}_ticks"), getattr(p, f"{_other(side)}_ticks")
        seen = f"{own:+d} ticks on a forward pulse of the {side} motor (the {_other(side)} counted {other:+d})"
        if swapped:
            out.append(Verdict(f"{side} encoder", "skip", "see motor channels"))
        elif abs(own) < moved:
            out.append(Verdict(f"{side} encoder", "FAIL", seen, f"the {side} wheel did not count: if it turned, "
                               f"check the {side} encoder's wires and [encoders] {side}_a_pin/{side}_b_pin; if it "
                               f"did not, the {side} motor's wires and [motors] {side}_channel"))
        elif own < 0:
            out.append(Verdict(f"{side} encoder", "FAIL", seen, f"counts backwards: if the {side} wheel turned "
                               f"backwards flip [motors] {side}_invert, else flip [encoders] {side}_invert"))
        else:
            out.append(Verdict(f"{side} encoder", "ok", seen))
    return out


def _other(side: str) -> str:
    return "right" if side == "left" else "left"


async def motor_checks(motors: Any, encoders: Any, clock: Clock, ticks_per_rev: int) -> list[Verdict]:
    """Pulse each motor once and judge what the encoders counted; the motors end braked."""
    from mazebot.io.motors import MotorWriteError

    pulses = []
    try:
        for side in ("left", "right"):
            pulses.append(await pulse_motor(motors, encoders, clock, side))
    except (MotorWriteError, OSError) as exc:
        return [Verdict("motor driver", "FAIL", _one_line(exc), "check the motor board's wiring and power"),
                *(Verdict(p, "skip", "the motors could not be driven")
                  for p in ("motor channels", "left encoder", "right encoder"))]
    finally:
        motors.stop()
    return judge_pulses(pulses, ticks_per_rev)


@dataclass
class Parts:
    """How one doctor run reaches the robot's parts: the real ones or the simulator's."""

    probe: SystemProbe
    lidar: LidarConfig
    open_kit: Callable[[], Any]  # the motor board, MotorKit-shaped; raises HardwareUnavailable
    kit_name: str
    open_pins: Callable[[], Any]  # the encoders' gpiozero pin factory
    clock: Clock = field(default_factory=RealClock)
    link_factory: Callable[[], Any] | None = None
    state_dir: Path | None = None
    close_pins: bool = True  # False: the pins belong to someone else (the simulator)
