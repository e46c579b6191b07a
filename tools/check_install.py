"""Installs mazebot the ways a user would, outside this checkout, and checks the page is served.

1. builds the wheel (``pip wheel``, the ``pyproject.toml`` build);
2. installs it into a fresh virtualenv in a scratch folder, and
3. with ``pip install --user`` into a scratch home (``$HOME/.local``, the user scheme of
   https://docs.python.org/3/library/sysconfig.html#user-scheme);
4. for each: from a folder with no ``config.toml``, checks ``mazebot`` is imported from that
   install (not from the checkout), starts ``mazebot run --sim``, fetches ``/`` and every
   asset the page references (``/static/app.js``, ``/static/style.css``,
   ``/static/vendor/d3.min.js``, the web-app manifest and the icons it lists, ...), compares
   them with ``static/``, and stops it with SIGTERM (exit 0).

Run by ``.ci/run`` (``make check-install``); standard library only::

    python3.11 tools/check_install.py [--python python3.11] [--keep]

Dependencies come from PyPI through pip's cache (the real one, also under the scratch home).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SERVE_TIMEOUT_S = 60.0


def _run(cmd: list[str], **kwargs: object) -> subprocess.CompletedProcess[str]:
    print("+", " ".join(cmd), flush=True)
    return subprocess.run(cmd, check=True, text=True, **kwargs)  # type: ignore[call-overload]


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _get(url: str) -> bytes:
    with urllib.request.urlopen(url, timeout=SERVE_TIMEOUT_S) as resp:
        if resp.status != 200:
            raise SystemExit(f"{url}: HTTP {resp.status}")
        return resp.read()


def check_serves(mazebot: Path, python: Path, env: dict[str, str], scratch: Path) -> None:
    """``mazebot run --sim`` of one install serves the page and its assets, byte for byte."""
    where = scratch / "cwd"  # no config.toml, not the checkout
    where.mkdir(parents=True, exist_ok=True)
    env = {**env, "XDG_STATE_HOME": str(scratch / "state"), "XDG_CONFIG_HOME": str(scratch / "config")}
    env.pop("MAZEBOT_CONFIG", None)
    env.pop("PYTHONPATH", None)
    origin = _run([str(python), "-c", "import mazebot.web.app as a; print(a.__file__); print(a.find_static_dir())"],
                  cwd=where, env=env, capture_output=True).stdout.split()
    print("  imported from", origin[0], "page in", origin[1])
    if any(Path(p).resolve().is_relative_to(REPO) for p in origin):
        raise SystemExit(f"{mazebot}: imported from the checkout ({origin}), not from its install")
    port = _free_port()
    base = f"http://127.0.0.1:{port}"
    proc = subprocess.Popen([str(mazebot), "run", "--sim", "--host", "127.0.0.1", "--port", str(port)],
                            cwd=where, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline_s = time.monotonic() + SERVE_TIMEOUT_S
        while True:
            if proc.poll() is not None or time.monotonic() > deadline_s:
                raise SystemExit(f"{mazebot} run --sim did not serve {base}/ (exit {proc.poll()})")
            try:
                page = _get(f"{base}/").decode()
                break
            except (urllib.error.URLError, ConnectionError):
                time.sleep(0.1)
        assets = re.findall(r'(?:src|href)="/static/([^"]+)"', page)
        for manifest in [a for a in assets if a.endswith(".webmanifest")]:  # its icons are assets too
            icons = json.loads(_get(f"{base}/static/{manifest}"))["icons"]
            assets += [icon["src"].removeprefix("/static/") for icon in icons]
        for asset in ("app.js", "progress.js", "style.css", "manifest.webmanifest", "vendor/d3.min.js"):
            if asset not in assets:
                raise SystemExit(f"the page no longer references /static/{asset}")
        if page.encode() != (REPO / "static" / "index.html").read_bytes():
            raise SystemExit(f"{base}/ is not static/index.html")
        for asset in assets:
            if _get(f"{base}/static/{asset}") != (REPO / "static" / asset).read_bytes():
                raise SystemExit(f"{base}/static/{asset} differs from static/{asset}")
            print(f"  {base}/static/{asset}: ok")
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        code = proc.wait(timeout=30)
        assert proc.stderr is not None
        stderr = proc.stderr.read()
        proc.stderr.close()
    if code != 0 or "Traceback" in stderr:
        raise SystemExit(f"{mazebot} run --sim exited {code} on SIGTERM:\n{stderr}")
    print(f"  {mazebot}: page and assets served, exit 0 on SIGTERM")


def main() -> int:
    parser = argparse.ArgumentParser(description="Install the wheel outside the checkout and check the page.")
    parser.add_argument("--python", default=shutil.which("python3.11") or sys.executable,
                        help="the Python to build and install with (default python3.11)")
    parser.add_argument("--keep", action="store_true", help="keep the scratch folder (its path is printed)")
    args = parser.parse_args()
    python = args.python
    cache = _run([python, "-m", "pip", "cache", "dir"], capture_output=True).stdout.strip()
    scratch = Path(tempfile.mkdtemp(prefix="mazebot-install-"))
    env = {**os.environ, "PIP_CACHE_DIR": cache, "PIP_DISABLE_PIP_VERSION_CHECK": "1"}
    env.pop("VIRTUAL_ENV", None)
    try:
        _run([python, "-m", "pip", "wheel", "--quiet", "--no-deps", "-w", str(scratch / "dist"), str(REPO)], env=env)
        (wheel,) = (scratch / "dist").glob("mazebot-*.whl")
        print("built", wheel.name)

        venv = scratch / "venv"
        _run([python, "-m", "venv", str(venv)], env=env)
        _run([str(venv / "bin" / "python"), "-m", "pip", "install", "--quiet", str(wheel)], env=env)
        check_serves(venv / "bin" / "mazebot", venv / "bin" / "python", env, scratch / "venv-run")

        home = scratch / "home"
        home.mkdir()
        user_env = {**env, "HOME": str(home)}
        user_env.pop("PYTHONUSERBASE", None)
        base_python = _run([python, "-c", "import sys; print(sys.base_prefix)"], capture_output=True).stdout.strip()
        extra = []
        stdlib = _run([python, "-c", "import sysconfig; print(sysconfig.get_path('stdlib'))"],
                      capture_output=True).stdout.strip()
        if (Path(stdlib) / "EXTERNALLY-MANAGED").exists():  # Debian's python3 (PEP 668)
            extra = ["--break-system-packages"]
        interpreter = str(Path(base_python) / "bin" / Path(python).name)
        if not Path(interpreter).exists():
            interpreter = python
        _run([interpreter, "-m", "pip", "install", "--quiet", "--user", *extra, str(wheel)], env=user_env)
        check_serves(home / ".local" / "bin" / "mazebot", Path(interpreter), user_env, scratch / "user-run")
    finally:
        if args.keep:
            print("kept", scratch)
        else:
            shutil.rmtree(scratch, ignore_errors=True)
    print("install check: ok (venv and --user)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
