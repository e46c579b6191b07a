"""systemd's notify protocol (sd_notify(3)) and the watchdog, without a dependency.

Under ``Type=notify`` systemd passes ``$NOTIFY_SOCKET``, a unix datagram socket (a path,
or ``@name`` in the abstract namespace), and reads ``KEY=VALUE`` lines from it:
``READY=1`` once the service serves, ``STOPPING=1`` on the way out, ``STATUS=…`` for
``systemctl status``, and ``WATCHDOG=1`` at least every ``WatchdogSec`` (passed as
``$WATCHDOG_USEC``), or systemd kills and restarts the service. Outside systemd every
call is a no-op.

The watchdog is fed only while the control loop keeps ticking: the control task's clock
is wrapped in :class:`ControlHeartbeat`, which notes each of its sleeps (one per tick).
A hung event loop feeds nothing either, so both get the daemon restarted.
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
from collections.abc import Mapping

from mazebot.clock import Clock

log = logging.getLogger(__name__)


def notify(message: str, env: Mapping[str, str] = os.environ) -> bool:
    """Send ``message`` (e.g. ``"READY=1"``) to systemd; False when not run by systemd."""
    address = env.get("NOTIFY_SOCKET")
    if not address:
        return False
    if address.startswith("@"):
        address = "\0" + address[1:]
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            sock.setblocking(False)
            sock.sendto(message.encode(), address)
    except OSError as exc:
        log.warning("cannot notify systemd at %s (%s)", env.get("NOTIFY_SOCKET"), exc)
        return False
    return True


def watchdog_period_s(env: Mapping[str, str] = os.environ) -> float | None:
    """``WatchdogSec`` in seconds if systemd asked this process for watchdog pings, else None."""
    usec = env.get("WATCHDOG_USEC")
    pid = env.get("WATCHDOG_PID")
    if not usec or (pid and pid != str(os.getpid())):
        return None
    try:
        value = int(usec)
    except ValueError:
        return None
    return value / 1e6 if value > 0 else None


class ControlHeartbeat:
    """A clock for the control task that remembers when the loop last ticked.

    Example::

        heartbeat = ControlHeartbeat(clock)
        control_task.run(motors, state, heartbeat, control)   # each tick sleeps once
        heartbeat.last_tick_s                                  # clock time of the last tick
    """

    def __init__(self, clock: Clock) -> None:
        self._clock = clock
        self.last_tick_s = clock.now_s()

    def now_s(self) -> float:
        return self._clock.now_s()

    async def sleep(self, duration_s: float) -> None:
        self.last_tick_s = self._clock.now_s()
        await self._clock.sleep(duration_s)


async def feed_watchdog(heartbeat: ControlHeartbeat, period_s: float, max_silence_s: float,
                        env: Mapping[str, str] = os.environ) -> None:
    """Send ``WATCHDOG=1`` every ``period_s`` while the control loop ticked within ``max_silence_s``."""
    while True:
        silence_s = heartbeat.now_s() - heartbeat.last_tick_s
        if silence_s <= max_silence_s:
            notify("WATCHDOG=1", env)
        else:
            log.error("control loop silent for %.1f s: not feeding the systemd watchdog", silence_s)
        await asyncio.sleep(period_s)
