"""The ``mazebot`` command line: lazy per subcommand, help on everything, the safety net robust."""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import types
from pathlib import Path
from typing import Any

import pytest

from mazebot.cli import ALL, COMMANDS, build_parser, main
from mazebot.io.motors import FakeMotorKit

#: What the safety net (``motors stop``) and the bare parser must never pull in.
HEAVY = ("numpy", "scipy", "aiohttp", "mazebot.slam", "mazebot.planner", "mazebot.sim", "mazebot.web",
         "mazebot.tasks", "mazebot.main")


def _imported_modules(argv: list[str], tmp_path: Path) -> set[str]:
    """Every module a fresh ``python -m mazebot ARGV`` imports (``-X importtime`` lists them on stderr)."""
    proc = subprocess.run([sys.executable, "-X", "importtime", "-m", "mazebot", *argv], capture_output=True,
                          text=True, timeout=60, check=False, cwd=tmp_path)
    names = set(re.findall(r"^import time:\s+\d+ \|\s+\d+ \|\s+(\S+)$", proc.stderr, flags=re.M))
    assert "mazebot.cli" in names, proc.stderr[-2000:]
    return names


def _heavy(names: set[str]) -> list[str]:
    return sorted(n for n in names if any(n == h or n.startswith(h + ".") for h in HEAVY))


def test_motors_stop_imports_neither_numpy_nor_scipy_nor_the_slam_nor_the_web(tmp_path: Path) -> None:
    # no HAT here: it ends with exit 69 after the same imports it does on the robot
    names = _imported_modules(["motors", "stop"], tmp_path)
    assert _heavy(names) == []
    # nor the whole configuration's models: [motors] is read alone
    assert {"mazebot.config", "mazebot.slam_config", "mazebot.sim_config"} & names == set()


def test_the_top_level_help_imports_no_command_module(tmp_path: Path) -> None:
    names = _imported_modules(["--help"], tmp_path)
    assert _heavy(names) == []
    assert not {c.module for c in COMMANDS} & names
    assert "pydantic" not in names


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def test_the_table_names_every_command_with_the_help_its_module_registers() -> None:
    full = build_parser(ALL)
    for action in full._actions:
        if isinstance(action, argparse._SubParsersAction):
            registered = {a.dest: a.help for a in action._choices_actions}
    assert registered == {c.name: c.help for c in COMMANDS}
    lazy = build_parser()
    assert list(_subparsers(lazy)) == list(_subparsers(full)) == [c.name for c in COMMANDS]


@pytest.mark.parametrize("name", [c.name for c in COMMANDS])
def test_each_command_builds_its_own_full_parser_next_to_the_others_lines(name: str) -> None:
    parser = build_parser(name)
    assert list(_subparsers(parser)) == [c.name for c in COMMANDS]
    assert _subparsers(parser)[name].add_help  # the real parser, with its options and --help


def _walk(parser: argparse.ArgumentParser, path: str) -> list[tuple[str, argparse.ArgumentParser]]:
    found = [(path, parser)]
    for name, child in _subparsers(parser).items():
        found += _walk(child, f"{path} {name}")
    return found


def test_every_command_has_a_description_and_every_option_a_help_text() -> None:
    missing = []
    for path, parser in _walk(build_parser(ALL), "mazebot"):
        subs = _subparsers(parser)
        if not subs and not parser.description:
            missing.append(f"{path}: no description")
        for action in parser._actions:
            if isinstance(action, argparse._HelpAction | argparse._SubParsersAction):
                continue
            if not action.help:
                missing.append(f"{path} {'/'.join(action.option_strings) or action.dest}: no help")
    assert missing == []


def test_an_unknown_command_is_a_usage_error_naming_it(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["drive"])
    assert exit_info.value.code == 2
    assert "invalid choice: 'drive'" in capsys.readouterr().err


def test_version_comes_from_the_installed_metadata(capsys: pytest.CaptureFixture[str]) -> None:
    from importlib.metadata import version

    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out == f"mazebot {version('mazebot')}\n"


# -- mazebot motors stop: the safety net after every exit of the daemon --------------------------------


@pytest.fixture
def hat(monkeypatch: pytest.MonkeyPatch) -> list[tuple[int, float, FakeMotorKit]]:
    """A stand-in ``adafruit_motorkit`` whose HAT a crashed daemon left driving; the kits opened."""
    opened: list[tuple[int, float, FakeMotorKit]] = []

    def motorkit(address: int, pwm_frequency: float) -> FakeMotorKit:
        kit = FakeMotorKit()
        for channel in (1, 2, 3, 4):
            getattr(kit, f"motor{channel}").throttle = 0.6
        opened.append((address, pwm_frequency, kit))
        return kit

    module: Any = types.ModuleType("adafruit_motorkit")
    module.MotorKit = motorkit
    monkeypatch.setitem(sys.modules, "adafruit_motorkit", module)
    return opened


def _all_zero(kit: FakeMotorKit) -> bool:
    return all(getattr(kit, f"motor{c}").throttle == 0.0 for c in (1, 2, 3, 4))


def _motors_stop(tmp_path: Path, toml: str | None) -> int:
    """``mazebot motors stop --config`` on a file holding ``toml`` (None: a file that does not exist)."""
    cfg = tmp_path / ("config.toml" if toml is not None else "nope.toml")
    if toml is not None:
        cfg.write_text(toml)
    return main(["motors", "stop", "--config", str(cfg)])


def test_motors_stop_zeroes_all_four_channels_at_the_configured_address(
    hat: list[tuple[int, float, FakeMotorKit]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert _motors_stop(tmp_path, "[motors]\ni2c_address = 0x61\npwm_frequency_hz = 1000.0\n") == 0
    assert [(a, f) for a, f, _ in hat] == [(0x61, 1000.0)]
    assert _all_zero(hat[0][2])
    assert capsys.readouterr().out == "motors stopped (HAT at I2C address 0x61)\n"


def test_a_mistake_outside_motors_does_not_keep_motors_stop_from_zeroing_the_hat(
    hat: list[tuple[int, float, FakeMotorKit]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert _motors_stop(tmp_path, "[motors]\ni2c_address = 0x61\n\n[slam]\nnot_a_key = 1\n") == 0
    assert hat[0][0] == 0x61 and _all_zero(hat[0][2])


def test_an_unusable_motors_section_still_zeroes_the_hat_at_the_default_address_then_exits_78(
    hat: list[tuple[int, float, FakeMotorKit]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert _motors_stop(tmp_path, "[motors]\ni2c_address = 'sixty'\n") == 78
    assert hat[0][0] == 0x60 and _all_zero(hat[0][2])
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "motors.i2c_address" in err[0] and "default I2C address 0x60" in err[0]


def test_motors_stop_on_a_missing_config_file_still_zeroes_the_hat(
    hat: list[tuple[int, float, FakeMotorKit]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert _motors_stop(tmp_path, None) == 78
    assert hat[0][0] == 0x60 and _all_zero(hat[0][2])
    assert "nope.toml: config file not found" in capsys.readouterr().err


# -- shell completion ----------------------------------------------------------------------------------


def _bash_complete(script: Path, words: list[str]) -> list[str]:
    """What bash offers after ``words`` (the last one being typed), with the generated script loaded."""
    array = " ".join(f"'{w}'" for w in words)
    program = (f"source {script}; COMP_WORDS=({array}); COMP_CWORD={len(words) - 1}; "
               "_shtab_mazebot; printf '%s\\n' \"${COMPREPLY[@]}\"")
    proc = subprocess.run(["bash", "-c", program], capture_output=True, text=True, timeout=30, check=True)
    return proc.stdout.split()


@pytest.mark.skipif(shutil.which("bash") is None, reason="bash is not installed")
def test_the_bash_completion_knows_every_command_and_the_options_of_each(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["completion", "bash"]) == 0
    script = tmp_path / "mazebot.bash"
    script.write_text(capsys.readouterr().out)
    assert sorted(_bash_complete(script, ["mazebot", ""])) == sorted(c.name for c in COMMANDS)
    assert _bash_complete(script, ["mazebot", "mo"]) == ["motors"]
    assert _bash_complete(script, ["mazebot", "motors", "stop", "--c"]) == ["--config"]
    levels = sorted(_bash_complete(script, ["mazebot", "run", "--log-level", ""]))
    assert levels == ["debug", "error", "info", "warning"]


def test_the_zsh_completion_names_every_command(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["completion", "zsh"]) == 0
    script = capsys.readouterr().out
    assert script.startswith("#compdef mazebot")
    for command in COMMANDS:
        assert f"\n    {command.name}:'" in script, command.name
    if shutil.which("zsh"):
        subprocess.run(["zsh", "-n"], input=script, text=True, check=True, timeout=30)
