"""The systemd unit and the udev rule: what they promise, and `systemd-analyze verify` accepts the unit."""

from __future__ import annotations

import configparser
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

SYSTEMD = Path(__file__).resolve().parents[1] / "systemd"
INSTALLED_BIN = "/opt/mazebot/.venv/bin/mazebot"


def _unit() -> configparser.ConfigParser:
    parser = configparser.ConfigParser(strict=False, interpolation=None)
    parser.optionxform = str  # type: ignore[assignment,method-assign]
    parser.read(SYSTEMD / "mazebot.service")
    return parser


def test_the_unit_notifies_is_watched_restarts_runs_unprivileged_and_stops_the_motors() -> None:
    service = _unit()["Service"]
    assert service["Type"] == "notify"
    assert int(service["WatchdogSec"]) > 0
    assert service["Restart"] == "on-failure"
    assert service["User"] not in ("root", "0")
    assert set(service["SupplementaryGroups"].split()) == {"gpio", "i2c", "dialout"}
    assert service["ExecStart"].startswith(f"{INSTALLED_BIN} run ")
    assert service["ExecStopPost"].startswith(f"{INSTALLED_BIN} motors stop")
    assert service["StateDirectory"] == "mazebot"


def test_the_unit_lets_the_control_process_be_real_time_within_bounds() -> None:
    from mazebot.config import DaemonConfig

    service = _unit()["Service"]
    assert service["RestrictRealtime"] == "no"  # yes would refuse sched_setscheduler(SCHED_FIFO)
    assert int(service["LimitRTPRIO"]) >= DaemonConfig().control_rt_priority > 0
    assert service["LimitRTTIME"]  # a runaway real-time loop is killed
    assert int(service["LimitNICE"]) <= DaemonConfig().control_nice
    assert service["CapabilityBoundingSet"] == ""  # the rlimits do it, no capability needed


def test_the_udev_rule_names_the_cp2102_adapter_dev_rplidar() -> None:
    rule = (SYSTEMD / "99-mazebot-rplidar.rules").read_text()
    line = next(x for x in rule.splitlines() if x and not x.startswith("#"))
    assert 'ATTRS{idVendor}=="10c4"' in line and 'ATTRS{idProduct}=="ea60"' in line
    assert 'SYMLINK+="rplidar"' in line


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze missing (apt-get install systemd)")
def test_systemd_analyze_verify_accepts_the_unit(tmp_path: Path) -> None:
    # verify checks that the commands exist: point them at this checkout's mazebot
    mazebot = Path(sys.prefix) / "bin" / "mazebot"
    assert mazebot.exists(), "install the package (pip install -e .) first"
    unit = tmp_path / "mazebot.service"
    unit.write_text((SYSTEMD / "mazebot.service").read_text().replace(INSTALLED_BIN, str(mazebot)))
    proc = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60,
                          check=False)
    assert proc.returncode == 0, proc.stderr
    assert "mazebot.service" not in proc.stderr, proc.stderr  # no warning about our unit
