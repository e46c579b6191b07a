"""Configuration: defaults, validation messages, the CLI's exit codes."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from mazebot import config_file
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


@pytest.fixture
def lookup(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> dict[str, Path]:
    """A working directory, an XDG config home and an /etc file, all in tmp_path, none written yet."""
    work, xdg, etc = tmp_path / "work", tmp_path / "xdg", tmp_path / "etc" / "mazebot" / "config.toml"
    work.mkdir()
    monkeypatch.chdir(work)
    monkeypatch.delenv("MAZEBOT_CONFIG", raising=False)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(xdg))
    monkeypatch.setattr(config_file, "SYSTEM_CONFIG", etc)
    return {"local": work / "config.toml", "xdg": xdg / "mazebot" / "config.toml", "etc": etc}


def _write_port(path: Path, port: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f'[lidar]\nport = "{port}"\n')


def test_config_lookup_goes_local_then_xdg_then_etc_then_defaults(
    lookup: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    assert load_config().lidar.port == "/dev/ttyUSB0"
    assert main(["config", "path"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("built-in defaults (no file at config.toml, ") and str(lookup["etc"]) in out
    for name, port in (("etc", "/dev/etc"), ("xdg", "/dev/xdg"), ("local", "/dev/local")):
        _write_port(lookup[name], port)
        assert load_config().lidar.port == port  # each one found wins over the ones written before it
        assert main(["config", "path"]) == 0
        assert capsys.readouterr().out == f"{lookup[name]}\n"


def test_xdg_config_home_defaults_to_dot_config_in_home(
    lookup: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("XDG_CONFIG_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    _write_port(tmp_path / "home" / ".config" / "mazebot" / "config.toml", "/dev/home")
    assert load_config().lidar.port == "/dev/home"


def test_mazebot_config_names_the_file_even_when_it_is_missing(
    lookup: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _write_port(lookup["etc"], "/dev/etc")
    monkeypatch.setenv("MAZEBOT_CONFIG", str(tmp_path / "nope.toml"))
    with pytest.raises(ConfigError, match=r"nope.toml: config file not found"):
        load_config()  # never falls through to /etc when the file named explicitly is missing


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


# -- every invalid file: exit 78 and one line naming the key, from `config check` and from `run` ---------

BAD_FILES = [
    ("bad-type", '[lidar]\nbaudrate = "fast"\n', "lidar.baudrate: 'fast' is not allowed: Input should be a valid int"),
    ("bool-for-int", "[web]\nport = true\n", "web.port: True is not allowed: Input should be a valid integer"),
    ("string-for-int", '[web]\nport = "8080"\n', "web.port: '8080' is not allowed: Input should be a valid integer"),
    ("int-for-bool", "[encoders]\npull_up = 1\n", "encoders.pull_up: 1 is not allowed: Input should be a valid bool"),
    ("unknown-key", "[motors]\nleft_chanel = 3\n", "motors.left_chanel: unknown key (value 3)"),
    ("unknown-section", "[wheels]\nsize = 1\n", "wheels: unknown key"),
    ("out-of-range", "[drive]\nmax_speed_mps = 0.9\n", "drive.max_speed_mps: 0.9 is not allowed"),
    ("cross-field", "[encoders]\nleft_a_pin = 22\n", "encoders: "),
    ("not-an-origin", '[web]\nallowed_origins = ["robot.local:8080"]\n',
     "web.allowed_origins: ['robot.local:8080'] is not allowed: 'robot.local:8080' is not an origin"),
    ("malformed-toml", "[lidar\nport = ", "not valid TOML"),
    ("not-utf8", b"[lidar]\nport = '\xff\xfe'\n", "not valid TOML: the file is not UTF-8 text"),
]


@pytest.mark.parametrize(("text", "expected"), [c[1:] for c in BAD_FILES], ids=[c[0] for c in BAD_FILES])
@pytest.mark.parametrize("command", ["check", "run", "run --sim"])
def test_every_invalid_config_exits_78_with_one_line_naming_the_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str, text: str | bytes, expected: str
) -> None:
    bad = tmp_path / "bad.toml"
    if isinstance(text, bytes):
        bad.write_bytes(text)
    else:
        bad.write_text(text)
    argv = ["config", "check", str(bad)] if command == "check" else [*command.split(), "--config", str(bad)]
    assert main(argv) == 78
    out, err = capsys.readouterr()
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1, lines
    assert str(bad) in lines[0] and expected in lines[0], lines[0]
    if command != "check":
        assert lines[0].startswith(f"mazebot: {bad}: ")


def test_run_names_the_first_problem_and_points_at_config_check_for_the_rest(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[web]\nport = 0\nheartbeat_s = -1\n[nope]\n")
    assert main(["run", "--sim", "--config", str(bad)]) == 78
    assert capsys.readouterr().err == (
        f"mazebot: {bad}: web.port: 0 is not allowed: Input should be greater than or equal to 1 "
        "(and 2 more: `mazebot config check` lists them)\n"
    )
    assert main(["config", "check", str(bad)]) == 78
    assert len(capsys.readouterr().err.splitlines()) == 3


def test_a_missing_config_file_exits_78(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for argv in (["config", "check", str(tmp_path / "nope.toml")], ["run", "--config", str(tmp_path / "nope.toml")]):
        assert main(argv) == 78
        assert "nope.toml: config file not found" in capsys.readouterr().err


def test_run_with_a_bad_config_has_no_traceback(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[web]\nport = true\n")
    proc = subprocess.run([sys.executable, "-m", "mazebot", "run", "--config", str(bad)],
                          capture_output=True, text=True, check=False, timeout=60)
    assert proc.returncode == 78
    assert proc.stderr == f"mazebot: {bad}: web.port: True is not allowed: Input should be a valid integer\n"


def test_cheap_robot_preset_fills_the_keys_the_file_left_unset() -> None:
    cheap = parse_config({"sim": {"robot_build": "cheap"}})
    assert cheap.encoders.counts_per_rev == 20
    assert cheap.sim.turn_slip == 0.05 and cheap.sim.backlash_deg == 3.0
    assert cheap.sim.wheel_diameter_right_scale / cheap.sim.wheel_diameter_left_scale == pytest.approx(1.0305, abs=1e-4)
    mine = parse_config({"encoders": {"counts_per_rev": 48}, "sim": {"robot_build": "cheap", "turn_slip": 0.1}})
    assert mine.encoders.counts_per_rev == 48 and mine.sim.turn_slip == 0.1 and mine.sim.backlash_deg == 3.0
    assert parse_config({}).sim.turn_slip == 0.0 and parse_config({}).encoders.counts_per_rev == 210


def _old_layout_file() -> dict[str, object]:
    """Every key of the flat ``[slam]`` layout, at its default."""
    from mazebot.slam_config import FLAT_KEYS

    defaults = Config().slam
    flat: dict[str, object] = {}
    for old, new in FLAT_KEYS.items():
        section, key = new.split(".")
        value = getattr(getattr(defaults, section), key)
        flat[old] = list(value) if isinstance(value, tuple) else value
    return {"slam": flat}


def test_a_flat_slam_key_still_loads_with_one_warning_naming_old_and_new(tmp_path: Path) -> None:
    from mazebot.config import DeprecatedKeyWarning

    path = tmp_path / "old.toml"
    path.write_text("[slam]\nmax_range_m = 7.0\nicp_max_iterations = 40\n")
    with pytest.warns(DeprecatedKeyWarning) as caught:
        config = load_config(path)
    assert config.slam.prepare.max_range_m == 7.0 and config.slam.icp.max_iterations == 40
    assert sorted(str(w.message).split(" (")[0] for w in caught) == [
        f"{path}: slam.icp_max_iterations is now slam.icp.max_iterations",
        f"{path}: slam.max_range_m is now slam.prepare.max_range_m",
    ]


def test_every_old_slam_key_has_a_new_place() -> None:
    from mazebot.config import DeprecatedKeyWarning
    from mazebot.slam_config import FLAT_KEYS

    assert len(FLAT_KEYS) + 9 == 94  # the flat layout had 94 keys; nine kept their place in [slam]
    with pytest.warns(DeprecatedKeyWarning) as caught:
        assert parse_config(_old_layout_file()) == Config()
    assert len(caught) == len(FLAT_KEYS)


def test_an_old_key_and_its_new_one_together_are_an_error() -> None:
    with pytest.raises(ConfigError, match=r"slam.max_range_m and slam.prepare.max_range_m"):
        parse_config({"slam": {"max_range_m": 7.0, "prepare": {"max_range_m": 6.0}}})


def test_bad_keys_in_nested_sections_name_their_dotted_path() -> None:
    with pytest.raises(ConfigError) as info:
        parse_config({"slam": {"icp": {"max_iterationz": 3, "max_iterations": "3"}, "loop": {"min_fitness": 2.0}}})
    problems = info.value.problems
    assert len(problems) == 3
    assert any("slam.icp.max_iterationz: unknown key" in p for p in problems)
    assert any("slam.icp.max_iterations: '3' is not allowed" in p for p in problems)
    assert any("slam.loop.min_fitness: 2.0 is not allowed" in p for p in problems)


def test_defaults_print_the_nested_slam_sections(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["config", "defaults"]) == 0
    out = capsys.readouterr().out
    for section in ("prepare", "icp", "loop", "grid", "keyframes", "search", "lattice"):
        assert f"\n[slam.{section}]\n" in out
    assert "icp_max_iterations" not in out


def test_config_check_shows_the_renamed_key_on_one_line(tmp_path: Path) -> None:
    path = tmp_path / "old.toml"
    path.write_text("[slam]\ngrid_resolution_m = 0.03\n")
    proc = subprocess.run([sys.executable, "-m", "mazebot", "config", "check", str(path)],
                          capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 0 and proc.stdout == "ok\n"
    assert proc.stderr == (f"mazebot: warning: {path}: slam.grid_resolution_m is now slam.grid.resolution_m "
                           "(the old name still works; `mazebot config defaults` shows the new layout)\n")


def test_a_recorded_config_of_the_old_layout_loads_without_warnings() -> None:
    import json
    import warnings

    from mazebot.config import config_from_json

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert config_from_json(json.dumps(_old_layout_file())) == Config()


def test_the_maze_pitch_is_one_key() -> None:
    """``[planner] cell_size_m`` is the maze's pitch; the simulated maze and the loop closures' shift follow it."""
    config = parse_config({"planner": {"cell_size_m": 0.25}})
    assert config.sim.cell_size_m == 0.25 and config.slam.loop.ambiguity_shift_m == 0.25
    config = parse_config({"planner": {"cell_size_m": 0.25}, "sim": {"cell_size_m": 0.3},
                           "slam": {"loop": {"ambiguity_shift_m": 0.0}}})
    assert config.sim.cell_size_m == 0.3 and config.slam.loop.ambiguity_shift_m == 0.0
    assert Config().sim.cell_size_m == Config().planner.cell_size_m == Config().slam.loop.ambiguity_shift_m
