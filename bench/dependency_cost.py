"""What each runtime dependency costs: installed size on the Pi and import time, as a Markdown table.

Sizes are read from the ``RECORD`` of each distribution installed in ``--site`` (give it the
Pi's own wheels, installed for aarch64 into a scratch folder, see below); import times are
measured here, in fresh processes of this Python (median of ``--repeat``), for the modules
mazebot imports from that distribution, dependencies included (scipy's figure contains
numpy's). The packages ``tools/lock-pi.sh`` leaves out are listed too, marked "left out".

    uv pip install --target /tmp/pi --python-platform aarch64-manylinux_2_28 --python-version 3.11 \\
        --no-deps -r <(grep -E '^[a-z]' requirements-pi.txt | cut -d' ' -f1) \\
        pyftdi pyusb binho-host-adapter sysv-ipc adafruit-circuitpython-requests \\
        adafruit-circuitpython-connectionmanager setuptools
    .venv/bin/python bench/dependency_cost.py --site /tmp/pi
"""

from __future__ import annotations

import argparse
import re
import statistics
import subprocess
import sys
from importlib.metadata import distributions
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: What mazebot imports from each distribution (``grep -r "import" mazebot``), so the time is
#: the one the daemon pays; distributions only other packages import are timed through those.
IMPORTS = {
    "numpy": "numpy",
    "scipy": "scipy.ndimage, scipy.sparse.csgraph, scipy.sparse.linalg, scipy.spatial",
    "aiohttp": "aiohttp.web",
    "pydantic": "pydantic.main",  # BaseModel: what `from pydantic import BaseModel` loads
    "pyserial-asyncio": "serial_asyncio",
    "pyserial": "serial",
    "gpiozero": "gpiozero, gpiozero.pins.mock",
    "mcap": "mcap.reader, mcap.writer",
    "lz4": "lz4.frame",
    "zstandard": "zstandard",
    "adafruit-circuitpython-motorkit": "adafruit_motorkit",
    "gpiod": "gpiod",
    "shtab": "shtab",
}
LEFT_OUT = {"pyftdi", "pyusb", "binho-host-adapter", "sysv-ipc", "adafruit-circuitpython-requests",
            "adafruit-circuitpython-connectionmanager", "setuptools"}


def _normal(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def installed_sizes(site: Path) -> dict[str, tuple[str, int]]:
    """Distribution name -> (version, bytes of its installed files, from RECORD)."""
    sizes = {}
    for dist in distributions(path=[str(site)]):
        total = sum(f.size or 0 for f in dist.files or [])
        sizes[_normal(dist.metadata["Name"])] = (dist.version, total)
    return sizes


def import_ms(modules: str, repeat: int) -> float | None:
    """Median wall milliseconds of importing ``modules`` in a fresh process (None: not importable here)."""
    code = ("import time; t = time.perf_counter(); import " + modules +
            "; print((time.perf_counter() - t) * 1e3)")
    times = []
    for _ in range(repeat):
        proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False, cwd="/")
        if proc.returncode != 0:
            return None
        times.append(float(proc.stdout))
    return statistics.median(times)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--site", type=Path, required=True, help="folder the Pi's wheels are installed in")
    parser.add_argument("--repeat", type=int, default=5, help="fresh processes per import time (default 5)")
    args = parser.parse_args()
    sizes = installed_sizes(args.site)
    locked = {_normal(line.split("==")[0]) for line in (REPO / "requirements-pi.txt").read_text().splitlines()
              if re.match(r"^[a-z]", line)}
    print("| distribution | version | installed on the Pi (MB) | import here (ms) | |")
    print("|---|---|---:|---:|---|")
    total_kept = total_left = 0
    for name, (version, size) in sorted(sizes.items(), key=lambda kv: -kv[1][1]):
        modules = IMPORTS.get(name)
        ms = import_ms(modules, args.repeat) if modules else None
        note = "left out" if name in LEFT_OUT else ("" if name in locked else "not in the lock")
        if name in LEFT_OUT:
            total_left += size
        else:
            total_kept += size
        timing = f"{ms:.0f} (`{modules}`)" if ms is not None else ""
        print(f"| {name} | {version} | {size / 1e6:.2f} | {timing} | {note} |")
    print(f"\nkept: {total_kept / 1e6:.1f} MB; left out: {total_left / 1e6:.1f} MB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
