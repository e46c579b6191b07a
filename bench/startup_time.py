"""How fast the ``mazebot`` command starts: the safety net and the page.

Two figures, each the median of ``--repeat`` fresh processes, in wall time and in the CPU
time the process used (less sensitive to what else the shared machine is doing):

* ``motors stop``: from starting ``mazebot motors stop`` to its exit. systemd runs it as the
  unit's ``ExecStopPost`` after every exit of the daemon, so it is the time the HAT may keep
  its last PWM after a crash. Off a Pi it ends with exit 69 (no HAT) after the same imports
  and config load that it does on the robot, which is what is measured here.
* ``run --sim`` serving ``/``: from starting ``mazebot run --sim`` to the first ``200`` on
  ``GET /`` (polled every 10 ms); then SIGTERM, and the exit code must be 0.

Standard library only, so it can time any installed ``mazebot``::

    .venv/bin/python bench/startup_time.py [--repeat 5] [--mazebot .venv/bin/mazebot]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path

POLL_PERIOD_S = 0.01
SERVE_TIMEOUT_S = 30.0


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _process_cpu_s(pid: int) -> float:
    """CPU seconds (user + system) a running process has used so far, from /proc (proc(5))."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def time_motors_stop(mazebot: str, env: dict[str, str]) -> tuple[float, float]:
    """Wall seconds from start to exit of one ``mazebot motors stop``, and the CPU seconds it used."""
    cpu0 = _children_cpu_s()
    t0 = time.perf_counter()
    proc = subprocess.run([mazebot, "motors", "stop"], capture_output=True, text=True, env=env, check=False)
    elapsed_s = time.perf_counter() - t0
    if proc.returncode not in (0, 69):  # 69: no HAT on this machine, after the same work
        raise SystemExit(f"motors stop exited {proc.returncode}: {proc.stderr.strip()}")
    return elapsed_s, _children_cpu_s() - cpu0


def time_run_sim_serving(mazebot: str, env: dict[str, str]) -> tuple[float, float]:
    """Wall seconds from starting ``mazebot run --sim`` to its first 200 on ``/``, and the CPU
    seconds the daemon had used by then (its main process; a wrapper script's ``exec`` keeps the pid)."""
    port = _free_port()
    url = f"http://127.0.0.1:{port}/"
    t0 = time.perf_counter()
    proc = subprocess.Popen([mazebot, "run", "--sim", "--host", "127.0.0.1", "--port", str(port)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    try:
        while True:
            elapsed_s = time.perf_counter() - t0
            if elapsed_s > SERVE_TIMEOUT_S or proc.poll() is not None:
                raise SystemExit(f"run --sim did not serve {url} (exit {proc.poll()}): {proc.stderr.read()}")
            try:
                with urllib.request.urlopen(url, timeout=SERVE_TIMEOUT_S) as resp:
                    if resp.status == 200:
                        return time.perf_counter() - t0, _process_cpu_s(proc.pid)
            except (urllib.error.URLError, ConnectionError):
                time.sleep(POLL_PERIOD_S)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            code = proc.wait(timeout=20)
            if code != 0:
                print(f"warning: run --sim exited {code} on SIGTERM", file=sys.stderr)
        assert proc.stderr is not None
        proc.stderr.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5, help="processes per figure (default 5)")
    parser.add_argument("--mazebot", default=str(Path(sys.executable).with_name("mazebot")),
                        help="the mazebot command to time (default: next to this Python)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        # the generated PIN and the saved runs go to a scratch state directory, not to ~
        env = {**os.environ, "XDG_STATE_HOME": tmp}
        stops = [time_motors_stop(args.mazebot, env) for _ in range(args.repeat)]
        serves = [time_run_sim_serving(args.mazebot, env) for _ in range(args.repeat)]
    result = {}
    for name, runs in (("motors_stop", stops), ("run_sim_serving", serves)):
        walls, cpus = [r[0] for r in runs], [r[1] for r in runs]
        result[name] = {"wall_s": round(statistics.median(walls), 3), "cpu_s": round(statistics.median(cpus), 3),
                        "wall_runs_s": [round(w, 3) for w in walls]}
    result["load_average"] = os.getloadavg()[0]
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
