"""Opening a Zenoh session: the one place that imports ``zenoh`` (the optional extra).

Zenoh's configuration keys are those of its reference config (``DEFAULT_CONFIG.json5`` in
eclipse-zenoh/zenoh): ``mode``, ``connect/endpoints``, ``listen/endpoints``,
``scouting/multicast/enabled``.
"""

from __future__ import annotations

import json
from types import ModuleType
from typing import Any

from mazebot.errors import ConfigError, HardwareUnavailable

INSTALL_HINT = "pip install 'mazebot[zenoh]'"


def import_zenoh(why: str) -> ModuleType:
    """The ``zenoh`` module, or one line saying how to install it."""
    try:
        import zenoh
    except ImportError:
        raise HardwareUnavailable(f"{why} needs the Zenoh package, which is not installed: {INSTALL_HINT}") from None
    return zenoh


def zenoh_config(zenoh: ModuleType, mode: str, connect: list[str], listen: list[str],
                 multicast_scouting: bool) -> Any:
    config = zenoh.Config()
    try:
        config.insert_json5("mode", json.dumps(mode))
        if connect:
            config.insert_json5("connect/endpoints", json.dumps(list(connect)))
        if listen:
            config.insert_json5("listen/endpoints", json.dumps(list(listen)))
        config.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast_scouting)))
    except zenoh.ZError as exc:
        raise ConfigError(f"zenoh: {exc}; check [zenoh] mode, connect and listen") from None
    return config


def open_session(why: str, mode: str = "peer", connect: list[str] | None = None, listen: list[str] | None = None,
                 multicast_scouting: bool = True) -> Any:
    """An open ``zenoh.Session``; the caller closes it. A bad endpoint is one line naming it."""
    zenoh = import_zenoh(why)
    config = zenoh_config(zenoh, mode, connect or [], listen or [], multicast_scouting)
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        raise HardwareUnavailable(
            f"cannot open the Zenoh session ({str(exc).splitlines()[0] if str(exc) else exc}); "
            f"check the endpoints (connect {connect or []}, listen {listen or []})"
        ) from None
