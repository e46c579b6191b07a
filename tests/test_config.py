"""Configuration: defaults, validation messages, the CLI's exit codes."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from mazebot.cli import main
from mazebot.config import Config, load_config, parse_config, render_toml
from mazebot.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]


def test_repository_config_is_the_rendered_defaults() -> None:
    # config.toml must list every tunable; regenerate it with `mazebot config defaults`.
    assert (REPO / "config.toml").read_text() == render_toml()


def test_rendered_defaults_parse_back_to_the_defaults() -> None:
    assert parse_config(tomllib.loads(render_toml())) == Config()


def test_every_field_is_rendered() -> None:
    data = tomllib.loads(render_toml())
    for name, field in Config.model_fields.items():
        section_cls = field.default_factory().__class__
        assert set(data[name]) == set(section_cls.model_fields), name


def test_unknown_and_bad_keys_name_the_key_path(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('[lidar]\nbaudrate = "fast"\nprot = 1\n[drive]\nmax_speed_mps = 0.9\n[nope]\n')
    with pytest.raises(ConfigError) as info:
        load_config(bad)
    problems = info.value.problems
    assert len(problems) == 4
    assert any("lidar.baudrate" in p and "'fast'" in p for p in problems)
    assert any("lidar.prot" in p and "unknown key" in p for p in problems)
    assert any("drive.max_speed_mps" in p and "0.9" in p and "0.5" in p for p in problems)
    assert any(p.endswith("nope: unknown key (value {}); check the spelling against `mazebot config defaults`")
               for p in problems)


def test_cross_field_rules(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"encoders: .*four different GPIOs"):
        parse_config({"encoders": {"left_a_pin": 5, "right_b_pin": 5}})
    with pytest.raises(ConfigError, match=r"motors: .*share channel 1"):
        parse_config({"motors": {"right_channel": 1}})
    with pytest.raises(ConfigError, match="min_range_m"):
        parse_config({"lidar": {"min_range_m": 13.0}})


def test_not_toml_is_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "broken.toml"
    bad.write_text("[lidar\nport=")
    with pytest.raises(ConfigError, match=r"broken.toml: not valid TOML"):
        load_config(bad)


def test_environment_variable_selects_the_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = tmp_path / "robot.toml"
    cfg.write_text('[lidar]\nport = "/dev/ttyAMA0"\n')
    monkeypatch.setenv("MAZEBOT_CONFIG", str(cfg))
    assert load_config().lidar.port == "/dev/ttyAMA0"


def test_derived_ticks_per_rev() -> None:
    assert parse_config({"encoders": {"counts_per_rev": 100, "decoding": "x2"}}).encoders.ticks_per_rev == 200


def test_config_check_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["config", "check", str(REPO / "config.toml")]) == 0
    assert capsys.readouterr().out == "ok\n"
    bad = tmp_path / "bad.toml"
    bad.write_text("[web]\nport = 0\n")
    assert main(["config", "check", str(bad)]) == 78
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"{bad}: web.port: 0 is not allowed: Input should be greater than or equal to 1"]


def test_config_check_subprocess_has_no_traceback(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[motors]\nleft_channel = 9\n")
    proc = subprocess.run([sys.executable, "-m", "mazebot", "config", "check", str(bad)],
                          capture_output=True, text=True, check=False)
    assert proc.returncode == 78
    assert "Traceback" not in proc.stderr
    assert "motors.left_channel: 9 is not allowed" in proc.stderr


def test_config_defaults_cli(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["config", "defaults"]) == 0
    assert capsys.readouterr().out == render_toml()
