"""Control tokens (generated, stored, compared in constant time), lockout, and the Origin check."""

from __future__ import annotations

import stat
from pathlib import Path

import pytest

from mazebot.web import auth
from mazebot.web.auth import ControlAuth, load_or_create_token, origin_allowed, resolve_state_dir, token_matches


def test_a_token_is_generated_once_stored_owner_only_and_reused(tmp_path: Path) -> None:
    state_dir = tmp_path / "state"
    token, created = load_or_create_token("", state_dir)
    assert created and token.isdigit() and len(token) == auth.PIN_DIGITS
    path = state_dir / "control_token"
    assert path.read_text().strip() == token
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert load_or_create_token("", state_dir) == (token, False)


def test_a_configured_token_wins_and_writes_nothing(tmp_path: Path) -> None:
    assert load_or_create_token("correct horse", tmp_path / "state") == ("correct horse", False)
    assert not (tmp_path / "state").exists()


def test_state_dir_comes_from_config_then_systemd_then_xdg(tmp_path: Path) -> None:
    assert resolve_state_dir("/srv/robot", {}) == Path("/srv/robot")
    assert resolve_state_dir("", {"STATE_DIRECTORY": "/var/lib/mazebot:/var/lib/other"}) == Path("/var/lib/mazebot")
    assert resolve_state_dir("", {"XDG_STATE_HOME": str(tmp_path)}) == tmp_path / "mazebot"


def test_token_comparison_uses_hmac_compare_digest(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = []
    real = auth.hmac.compare_digest

    def spy(a, b):
        calls.append((a, b))
        return real(a, b)

    monkeypatch.setattr(auth.hmac, "compare_digest", spy)
    assert token_matches("1234", "1234") and not token_matches("1234", "1235") and not token_matches("1234", None)
    assert calls == [(b"1234", b"1234"), (b"1234", b"1235")]


def test_missing_wrong_right_and_lockout_after_repeated_guesses() -> None:
    now = [0.0]
    guard = ControlAuth("2468", free_failures=3, first_delay_s=1, max_delay_s=8, now_s=lambda: now[0])
    assert guard.check(None, "a") == 401 and guard.check("", "a") == 401
    assert guard.check("1111", "a") == 403
    assert guard.check("2468", "a") == 200  # a right PIN forgives the typo
    for _ in range(3):
        assert guard.check("0000", "a") == 403
    assert guard.check("2468", "a") == 429  # locked out, even with the right PIN
    assert guard.retry_after_s("a") == 1.0 and guard.locked_out == 1
    assert guard.check("2468", "b") == 200  # others are not
    now[0] = 1.0
    assert guard.check("2468", "a") == 200


def test_the_lockout_doubles_with_every_further_wrong_pin_up_to_the_cap() -> None:
    now = [0.0]
    guard = ControlAuth("246810", now_s=lambda: now[0])  # the defaults: 5 free, 1 s doubling to 60 s
    delays = []
    for _ in range(13):
        assert guard.check("000000", "10.0.0.7") == 403
        delays.append(guard.retry_after_s("10.0.0.7"))
        if delays[-1]:
            assert guard.check("246810", "10.0.0.7") == 429  # refused unseen: a guess now teaches nothing
        now[0] += delays[-1]  # a patient attacker waits exactly as long as it must
    assert delays == [0, 0, 0, 0, 1, 2, 4, 8, 16, 32, 60, 60, 60]
    assert guard.lockouts == 9
    # from here on one guess a minute: a year of guessing covers about half of the 10**6 six-digit PINs
    # an hour of quiet and the address starts afresh; a right PIN clears it at once
    now[0] += 3601
    assert guard.check("000000", "10.0.0.7") == 403 and guard.retry_after_s("10.0.0.7") == 0


def test_ipv6_guesses_count_against_the_whole_slash_64() -> None:
    now = [0.0]
    guard = ControlAuth("246810", now_s=lambda: now[0])
    for i in range(5):  # five privacy addresses of one phone
        assert guard.check("000000", f"2001:db8:1:2::{i + 1}") == 403
    assert guard.check("246810", "2001:db8:1:2:abcd::9") == 429
    assert guard.check("246810", "2001:db8:1:3::1") == 200  # another network
    assert auth.client_key("::ffff:10.0.0.7") == "10.0.0.7"
    assert auth.client_key("?") == "?"


def test_the_table_of_addresses_stays_bounded() -> None:
    guard = ControlAuth("246810", max_clients=100, now_s=lambda: 0.0)
    for i in range(1000):
        guard.check("000000", f"10.0.{i // 256}.{i % 256}")
    assert len(guard._clients) == 100


@pytest.mark.parametrize(
    ("origin", "host", "allowed", "ok"),
    [
        (None, "robot:8080", [], True),  # not a browser
        ("http://robot:8080", "robot:8080", [], True),
        ("http://ROBOT:8080", "robot:8080", [], True),
        ("http://192.168.4.1", "192.168.4.1:80", [], True),
        ("http://evil.example", "robot:8080", [], False),
        ("http://robot:9999", "robot:8080", [], False),
        ("null", "robot:8080", [], False),
        ("file://", "robot:8080", [], False),
        ("http://phone-app.local:3000", "robot:8080", ["http://phone-app.local:3000"], True),
        ("http://anything", "robot:8080", ["*"], True),
    ],
)
def test_origin_check(origin, host, allowed, ok) -> None:
    assert origin_allowed(origin, host, allowed) is ok


def test_the_daemon_logs_a_generated_pin_once(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    from mazebot.config import Config
    from mazebot.web.server import control_token

    config = Config()
    config.daemon.state_dir = str(tmp_path / "state")
    with caplog.at_level("WARNING", logger="mazebot.web.server"):
        pin = control_token(config)
    assert [r.getMessage() for r in caplog.records] == [
        f"control PIN for start/stop: {pin} (generated once, kept in {tmp_path / 'state' / 'control_token'})"
    ]
    caplog.clear()
    with caplog.at_level("WARNING", logger="mazebot.web.server"):
        assert control_token(config) == pin
    assert caplog.records == []


def test_an_unwritable_state_dir_is_a_config_error(tmp_path: Path) -> None:
    from mazebot.config import Config
    from mazebot.errors import ConfigError
    from mazebot.web.server import control_token

    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    config = Config()
    config.daemon.state_dir = str(blocker / "state")
    with pytest.raises(ConfigError, match="cannot keep the control token"):
        control_token(config)
