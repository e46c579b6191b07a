"""The fork server forked from the daemon: children come from it, it holds none of the daemon's
descriptors, it leaves when the daemon does (even a killed one), and a busy daemon is left to
multiprocessing's own server."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="forks, and reads /proc")

START = r"""
import json, multiprocessing, os, signal, sys, threading
from multiprocessing import forkserver
from mazebot.fork_server import start_fork_server_here


def child_writes():  # in a child: write to stderr, then open a file; the number it gets
    print("from the child", file=sys.stderr, flush=True)
    fd = os.open(os.devnull, os.O_RDONLY)
    os.close(fd)
    return fd


def sigint_in_child():  # in a child: what Ctrl-C does to it
    handler = signal.getsignal(signal.SIGINT)
    return "ignored" if handler == signal.SIG_IGN else getattr(handler, "__name__", str(handler))


def main():
    # as the quota bench's daemon (Ctrl-C left to whoever started it), or as a terminal's foreground
    # job (a test run as a shell's background job starts with it ignored)
    signal.signal(signal.SIGINT, signal.SIG_IGN if sys.argv[4] == "ignore" else signal.default_int_handler)
    if sys.argv[1] == "thread":
        threading.Thread(target=threading.Event().wait, daemon=True).start()
    r, w = os.pipe()  # a pipe of the daemon's own: the server must not hold an end of it
    log = open(sys.argv[3], "w")  # as a test runner's capture or a log file: stderr on a descriptor > 2
    real_stderr, sys.stderr = sys.stderr, log
    forked = start_fork_server_here(["json"])
    sys.stderr = real_stderr
    again = start_fork_server_here(["json"])
    ctx = multiprocessing.get_context("forkserver")
    with ctx.Pool(1) as pool:
        worker_parent = pool.apply(os.getppid)
        child_fd = pool.apply(child_writes)
        child_sigint = pool.apply(sigint_in_child)
    server = forkserver._forkserver._forkserver_pid
    held = sorted(os.readlink(f"/proc/{server}/fd/{fd}") for fd in os.listdir(f"/proc/{server}/fd"))
    with open(f"/proc/{server}/cmdline", "rb") as f:
        server_cmd = f.read().replace(b"\0", b" ").decode()
    log.flush()
    print(json.dumps({"forked": forked, "again": again, "stale_fd": log.fileno(), "child_fd": child_fd,
                      "server": server, "worker_parent": worker_parent, "held": held,
                      "pipe": os.readlink(f"/proc/self/fd/{r}"), "server_cmd": server_cmd,
                      "child_sigint": child_sigint}), flush=True)
    if sys.argv[2] == "kill":
        os.kill(os.getpid(), signal.SIGKILL)


if __name__ == "__main__":
    main()
"""


def _run(tmp_path: Path, threads: str, end: str, sigint: str = "default") -> dict[str, object]:
    script = tmp_path / "daemon.py"
    script.write_text(START)
    out = subprocess.run([sys.executable, str(script), threads, end, str(tmp_path / "daemon.log"), sigint],
                         capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert out.stdout, out.stderr
    result: dict[str, object] = json.loads(out.stdout.splitlines()[0])
    result["stderr"] = out.stderr
    return result


def _gone_soon(pid: int, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            with open(f"/proc/{pid}/stat") as f:
                if f.read().rsplit(")", 1)[1].split()[0] == "Z":  # ended, not yet reaped
                    return True
        except OSError:
            return True
        time.sleep(0.05)
    return False


def test_children_come_from_a_server_forked_from_the_daemon(tmp_path: Path) -> None:
    seen = _run(tmp_path, "alone", "exit")
    assert seen["forked"] is True and seen["again"] is False  # one server per daemon
    assert seen["worker_parent"] == seen["server"]
    assert "multiprocessing.forkserver" not in str(seen["server_cmd"])  # the daemon's own image
    assert seen["pipe"] not in seen["held"]  # the daemon's descriptors are not kept open by the server
    # a stale object of the daemon's (its stderr on a log file) neither gets the child's output, nor does
    # its descriptor's number go to the next file the child opens (which the object would write into)
    assert (tmp_path / "daemon.log").read_text() == ""
    assert seen["child_fd"] != seen["stale_fd"]
    assert "from the child" in str(seen["stderr"])
    assert _gone_soon(int(str(seen["server"])))  # the daemon exited: so did its server


def test_children_take_ctrl_c_as_the_daemon_does(tmp_path: Path) -> None:
    # a daemon that takes Ctrl-C: its children get a KeyboardInterrupt (the control process brakes on it)
    assert _run(tmp_path, "alone", "exit")["child_sigint"] == "default_int_handler"
    # a daemon that ignores it (the quota bench's, stopped by its parent): the server and its children
    # ignore it too, from the server's first instruction; neither dies under the daemon's feet
    assert _run(tmp_path, "alone", "exit", "ignore")["child_sigint"] == "ignored"


def test_the_server_leaves_when_the_daemon_is_killed(tmp_path: Path) -> None:
    seen = _run(tmp_path, "alone", "kill")
    assert seen["forked"] is True
    assert _gone_soon(int(str(seen["server"])))


def test_a_daemon_with_threads_is_left_to_multiprocessing(tmp_path: Path) -> None:
    seen = _run(tmp_path, "thread", "exit")
    assert seen["forked"] is False
    assert "multiprocessing.forkserver" in str(seen["server_cmd"])
    assert seen["worker_parent"] == seen["server"]


def test_the_server_preloads_the_daemons_children() -> None:
    from mazebot.fork_server import FORKSERVER_PRELOAD

    assert "mazebot.slam.loop_worker" in FORKSERVER_PRELOAD
    assert "mazebot.tasks.control_process" in FORKSERVER_PRELOAD
