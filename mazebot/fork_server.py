"""The daemon's fork server forked from the daemon itself, so the modules both import are in memory once.

The loop-closure worker and the control process are started by multiprocessing's fork
server, a single-threaded process that a child is forked from (never from the daemon, whose
threads a fork could catch holding a lock, nor from a fresh interpreter for each: numpy and
scipy would be imported, at a second or more on a Pi, for every start). Multiprocessing starts
that server as a fresh interpreter, which imports numpy, pydantic and the configuration's
models a second time: about 25 MB of Python objects (``/proc/PID/smaps_rollup``'s
``Anonymous``, measured with ``tools/pss_by_process.py``) that the daemon's process already
holds, counted twice in the robot's memory.

:func:`start_fork_server_here` forks the server from the daemon instead, early, while the
daemon is still one thread with no device open: the server and every child it forks then share
the daemon's pages of those modules until someone writes to them (copy on write). Two things keep
the pages shared: ``gc.freeze`` first, so that neither the daemon's full garbage collections nor
the children's touch those objects' headers (the Python documentation's advice for a process
that forks without exec, :func:`gc.freeze`), and nothing of the daemon's but its memory goes
into the server: every inherited file descriptor is let go of (the daemon's pipes must see their
ends close when the daemon's do; each becomes /dev/null rather than closed, so that no number a
stale object of the daemon's still names is handed to a child's next file), stdout and stderr
are made afresh on descriptors 1 and 2, signal handlers go back to an interpreter's defaults (Ctrl-C
ignored where the daemon ignores it), and the server leaves through ``os._exit`` (the daemon's exit
handlers are not the server's).

The server is then multiprocessing's own (:func:`multiprocessing.forkserver.main`), registered
as the one this process's ``forkserver`` context uses: the rest of multiprocessing (the
process pool, ``Process.start``, the resource tracker, a server that died and is started again
the usual way) is unchanged. Where the conditions do not hold (another thread is running, a
fork server is running already, not Linux, a multiprocessing whose server this module does not
know) nothing happens and multiprocessing starts its
server as before.

Example::

    start_fork_server_here(["mazebot.slam.loop_worker"])   # True: forked, preloading the worker
"""

from __future__ import annotations

import contextlib
import gc
import inspect
import io
import logging
import os
import signal
import socket
import sys
import threading
from collections.abc import Sequence
from multiprocessing import connection, forkserver, resource_tracker, util
from typing import Any

log = logging.getLogger(__name__)

#: What the daemon's fork server imports once, before it forks anything: the loop-closure
#: worker's SLAM (numpy, scipy) and the daemon's real-time control process
#: (``mazebot.tasks.control_process``; named, not imported: the server is started before them).
#: Whoever starts the server first sets this same list (a second setting would come too
#: late). Every process forked from the server shares these pages instead of importing its
#: own copies: the control process imported ~7 MB of its own (measured with
#: ``/proc/PID/smaps_rollup``, a forked child's private memory before and after its imports).
FORKSERVER_PRELOAD = ("mazebot.slam.loop_worker", "mazebot.tasks.control_process", "mazebot.tasks.control_task",
                      "mazebot.logs")


def _let_go_of_the_daemons_files(keep: set[int]) -> None:
    """Every inherited descriptor but ``keep`` and 0-2 made /dev/null; stdout and stderr fresh on 1 and 2.

    Not closed: an object of the daemon's still names its number (a log file's stream, a test
    runner's capture file), and a number closed here would be given to the next file a child
    opens (its motors' shared memory), which that object would then write into. On /dev/null the
    daemon's pipes and sockets are let go of all the same (their ends close when the daemon's do).
    """
    devnull = os.open(os.devnull, os.O_RDWR)
    for name in os.listdir("/proc/self/fd"):
        fd = int(name)
        if fd > 2 and fd not in keep and fd != devnull:
            with contextlib.suppress(OSError):  # the listing's own descriptor, closed meanwhile
                os.dup2(devnull, fd)
    os.close(devnull)
    sys.stdout = io.TextIOWrapper(io.FileIO(1, "w", closefd=False), line_buffering=True)
    sys.stderr = io.TextIOWrapper(io.FileIO(2, "w", closefd=False), line_buffering=True, errors="backslashreplace")


def _become_the_server(listener_fd: int, alive_r: int, preload: list[str]) -> None:
    """In the forked child: multiprocessing's fork server loop, then ``os._exit``; never returns."""
    code = 1
    try:
        _let_go_of_the_daemons_files({listener_fd, alive_r})
        signal.set_wakeup_fd(-1)
        for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGUSR1, signal.SIGUSR2, signal.SIGALRM):
            signal.signal(sig, signal.SIG_DFL)
        # Ctrl-C as an interpreter started by the daemon would take it: ignored where the daemon
        # ignores it (Python keeps an inherited SIG_IGN for SIGINT; the quota bench's daemon is
        # stopped by its parent, and a server or worker dying at a Ctrl-C would fail under it),
        # a KeyboardInterrupt otherwise (the control process brakes on it)
        if signal.getsignal(signal.SIGINT) != signal.SIG_IGN:
            signal.signal(signal.SIGINT, signal.default_int_handler)
        forkserver.main(listener_fd, alive_r, preload)
        code = 0
    except SystemExit:  # the server's way out once every client is gone
        code = 0
    except BaseException:
        with contextlib.suppress(Exception):
            sys.stderr.write("mazebot: the fork server failed\n")
    finally:
        os._exit(code)


def _knows_this_multiprocessing(server: Any) -> bool:
    """The fork server's entry and fields are the ones this module was written against (CPython 3.11's)."""
    params = list(inspect.signature(forkserver.main).parameters)
    fields = ("_lock", "_forkserver_address", "_forkserver_alive_fd", "_forkserver_pid", "_preload_modules")
    return params == ["listener_fd", "alive_r", "preload", "main_path", "sys_path"] and all(
        hasattr(server, name) for name in fields)


def _fork(preload: list[str]) -> tuple[int, str, int]:
    """Fork the server; in this process return its pid, its socket's address and the alive pipe's write end."""
    resource_tracker.ensure_running()  # its children reach it through a descriptor sent with each start
    gc.collect()
    gc.freeze()  # the objects alive now are shared with the server: collections leave their pages alone
    address: str = connection.arbitrary_address("AF_UNIX")  # type: ignore[attr-defined]
    with socket.socket(socket.AF_UNIX) as listener:
        listener.bind(address)
        if not util.is_abstract_socket_namespace(address):
            os.chmod(address, 0o600)
        listener.listen()
        # every client holds the write end of the "alive" pipe; the server leaves at its end
        alive_r, alive_w = os.pipe()
        try:
            pid = os.fork()
        except OSError:
            os.close(alive_r)
            os.close(alive_w)
            raise
        if pid == 0:
            os.close(alive_w)
            _become_the_server(listener.fileno(), alive_r, preload)
        os.close(alive_r)
    return pid, address, alive_w


def start_fork_server_here(preload: Sequence[str]) -> bool:
    """Fork multiprocessing's fork server from this process, with ``preload`` imported in it.

    Call it once, early, while this process runs one thread and has opened no device. Returns
    whether the server was forked; False leaves multiprocessing to start its own when a child
    is first started (a thread is running, a server runs already, no ``os.fork``).
    """
    server: Any = forkserver._forkserver  # its private fields: what ensure_running() sets (CPython 3.11)
    if not hasattr(os, "fork") or sys.platform != "linux" or not _knows_this_multiprocessing(server):
        return False
    if threading.active_count() != 1:
        log.debug("fork server: %d threads run here; multiprocessing will start its own", threading.active_count())
        return False
    with server._lock:
        if server._forkserver_pid is not None:
            return False
        try:
            pid, address, alive_w = _fork(list(preload))
        except OSError as exc:  # no tracker, socket or fork to be had: multiprocessing tries its own later
            log.warning("the fork server could not be forked from the daemon (%s); multiprocessing starts its own", exc)
            return False
        server._preload_modules = list(preload)
        server._forkserver_address = address
        server._forkserver_alive_fd = alive_w
        server._forkserver_pid = pid
    log.debug("fork server %d forked from the daemon", pid)
    return True
