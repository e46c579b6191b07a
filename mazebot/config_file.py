"""Where ``config.toml`` is found and how it is read, before any section is validated.

Apart from :mod:`mazebot.config` so that ``mazebot motors stop`` (the safety net systemd runs
after every exit of the daemon) reads its one section without building the whole
configuration's models: the search path, the TOML reading and the one-line errors are the
same for both.
"""

from __future__ import annotations

import os
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mazebot.errors import ConfigError

if TYPE_CHECKING:
    from pydantic import ValidationError

ENV_CONFIG = "MAZEBOT_CONFIG"

#: The system-wide config file, the one the systemd unit names (``systemd/mazebot.service``).
SYSTEM_CONFIG = Path("/etc/mazebot/config.toml")


def config_search_path() -> list[Path]:
    """Where a config file is looked for when no ``--config`` is given, first match wins:
    ``$MAZEBOT_CONFIG``, ``./config.toml``, ``$XDG_CONFIG_HOME/mazebot/config.toml``
    (``~/.config`` when unset, per the XDG Base Directory Specification), ``/etc/mazebot/config.toml``."""
    env = os.environ.get(ENV_CONFIG)
    if env:
        return [Path(env)]  # named explicitly: must exist, no falling through to another file
    xdg = os.environ.get("XDG_CONFIG_HOME") or os.path.join(os.path.expanduser("~"), ".config")
    return [Path("config.toml"), Path(xdg) / "mazebot" / "config.toml", SYSTEM_CONFIG]


def default_config_path() -> Path | None:
    """The config file used without ``--config`` (:func:`config_search_path`), or None: the defaults."""
    env = os.environ.get(ENV_CONFIG)
    if env:
        return Path(env)
    return next((p for p in config_search_path() if p.is_file()), None)


def read_config_file(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The TOML document of a config file, not yet validated; ConfigError naming the file if unreadable."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{p}: config file not found") from None
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read config file ({exc.strerror or exc})") from None
    try:
        return tomllib.loads(raw.decode("utf-8"))  # decoding here: a UnicodeDecodeError is no OSError
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{p}: not valid TOML: the file is not UTF-8 text") from None


def describe_validation_error(err: Mapping[str, Any]) -> str:
    path = ".".join(str(p) for p in err["loc"]) or "(top level)"
    kind = err["type"]
    value = err.get("input")
    if kind in ("extra_forbidden", "unexpected_keyword_argument"):
        return f"{path}: unknown key (value {value!r}); check the spelling against `mazebot config defaults`"
    if kind == "missing":
        return f"{path}: required key is missing"
    msg = err["msg"]
    if msg.startswith("Value error, "):
        msg = msg[len("Value error, ") :]
    return f"{path}: {value!r} is not allowed: {msg}"


def validation_problems(exc: ValidationError, source: str, prefix: str = "") -> ConfigError:
    problems = [f"{source}: {prefix}{describe_validation_error(e)}" for e in exc.errors()]
    more = len(problems) - 1
    first = problems[0] + (f" (and {more} more: `mazebot config check` lists them)" if more else "")
    return ConfigError(first, problems)
