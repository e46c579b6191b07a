"""``make data``: the public data sets the tests and benchmarks use, from their origins, checked.

Every file is listed in ``tools/data-manifest.tsv`` (path, SHA-256, size, origin URL): the
micromouse contest and training mazes (github.com/micromouseonline/mazefiles), the g2o pose
graphs (tiny-solver-rs, SE-Sync), the CARMEN laser logs (SLAM-2D-LIDAR-SCAN; the Radish
logs as collected in acschaefer/ple). Each is downloaded into ``$MAZEBOT_DATA`` (default
``data/`` in the checkout, ignored by git), kept only if its SHA-256 matches, and written
atomically; files already there and intact are not fetched again. Offline (or when an origin
changed a file), it lists what is missing and how to get it, and exits 1.

    python3 tools/fetch_data.py [--data DIR] [--check]      # --check: no network, only verify
    python3 tools/fetch_data.py --write-manifest DIR        # maintainers: the manifest from a data folder
"""

from __future__ import annotations

import argparse
import hashlib
import os
import sys
import tempfile
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path
from typing import NamedTuple

REPO = Path(__file__).resolve().parents[1]
MANIFEST = REPO / "tools" / "data-manifest.tsv"
TIMEOUT_S = 30.0
RAW = "https://raw.githubusercontent.com"

#: Where each folder of the data set comes from. The mazes at the commit they were taken
#: from (later commits redrew the posts as "+"); the others at the origin's default branch
#: (HEAD). The SHA-256 in the manifest is what makes a download reproducible.
MAZEFILES = f"{RAW}/micromouseonline/mazefiles/a71f846"
ORIGINS = {
    "mazes/training/": f"{MAZEFILES}/training/",
    "mazes/classic/": f"{MAZEFILES}/classic/",
    "posegraphs/input_M3500_g2o.g2o": f"{RAW}/powei-lin/tiny-solver-rs/HEAD/tests/data/input_M3500_g2o.g2o",
    "posegraphs/input_MITb_g2o.g2o": f"{RAW}/david-m-rosen/SE-Sync/HEAD/data/MIT.g2o",
    "carmen/intel.gfs.log": f"{RAW}/xiaofeng419/SLAM-2D-LIDAR-SCAN/HEAD/DataSet/RawData/intel.gfs.log",
    "carmen/": f"{RAW}/acschaefer/ple/HEAD/data/carmen/",
}


class Entry(NamedTuple):
    path: str
    sha256: str
    size: int
    url: str


def default_data_dir() -> Path:
    return Path(os.environ.get("MAZEBOT_DATA") or REPO / "data")


def sha256_of(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def read_manifest(manifest: Path = MANIFEST) -> list[Entry]:
    entries = []
    for line in manifest.read_text().splitlines():
        if line and not line.startswith("#"):
            path, digest, size, url = line.split("\t")
            entries.append(Entry(path, digest, int(size), url))
    return entries


def origin_url(path: str) -> str:
    for prefix, origin in ORIGINS.items():
        if path == prefix:
            return origin
        if prefix.endswith("/") and path.startswith(prefix):
            return origin + urllib.parse.quote(path[len(prefix):])
    raise SystemExit(f"{path}: no origin known for it; add one to ORIGINS in {Path(__file__).name}")


def write_manifest(data: Path, manifest: Path = MANIFEST) -> None:
    rows = ["# path\tsha256\tbytes\torigin (written by tools/fetch_data.py --write-manifest)"]
    for file in sorted(p for p in data.rglob("*") if p.is_file() and p.name != "README.md"):
        rel = file.relative_to(data).as_posix()
        rows.append(f"{rel}\t{sha256_of(file)}\t{file.stat().st_size}\t{origin_url(rel)}")
    manifest.write_text("\n".join(rows) + "\n")
    print(f"wrote {manifest} ({len(rows) - 1} files)")


def fetch(entry: Entry, data: Path) -> str | None:
    """Download one file into ``data``; None when it is there and intact, else why it is not."""
    target = data / entry.path
    try:
        with urllib.request.urlopen(entry.url, timeout=TIMEOUT_S) as resp:
            body = resp.read()
    except (urllib.error.URLError, OSError, ValueError) as exc:
        return f"cannot download ({getattr(exc, 'reason', exc)})"
    digest = hashlib.sha256(body).hexdigest()
    if digest != entry.sha256:
        return f"the origin's file changed (SHA-256 {digest[:12]}..., expected {entry.sha256[:12]}...)"
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile(dir=target.parent, prefix=f".{target.name}.", delete=False) as tmp:
        tmp.write(body)
    os.replace(tmp.name, target)  # atomic: a half-written file is never taken for the data
    return None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Download the public data sets the tests use, SHA-256 checked.")
    parser.add_argument("--data", type=Path, default=None,
                        help="where to put them (default $MAZEBOT_DATA, else data/ in the checkout)")
    parser.add_argument("--check", action="store_true", help="only verify what is there; no network")
    parser.add_argument("--manifest", type=Path, default=MANIFEST, help=argparse.SUPPRESS)
    parser.add_argument("--write-manifest", type=Path, default=None, metavar="DIR",
                        help="write the manifest from the files in DIR (maintainers)")
    args = parser.parse_args(argv)
    if args.write_manifest is not None:
        write_manifest(args.write_manifest, args.manifest)
        return 0
    data = args.data or default_data_dir()
    problems: list[tuple[Entry, str]] = []
    fetched = 0
    for entry in read_manifest(args.manifest):
        target = data / entry.path
        if target.is_file() and sha256_of(target) == entry.sha256:
            continue
        if args.check:
            problems.append((entry, "missing" if not target.exists() else "differs from the manifest"))
            continue
        why = fetch(entry, data)
        if why is None:
            fetched += 1
        else:
            problems.append((entry, why))
    total = len(read_manifest(args.manifest))
    if not problems:
        print(f"{data}: all {total} files present and intact ({fetched} downloaded)")
        return 0
    print(f"{data}: {len(problems)} of {total} files missing or wrong:", file=sys.stderr)
    for entry, why in problems[:10]:
        print(f"  {entry.path}: {why}; from {entry.url}", file=sys.stderr)
    if len(problems) > 10:
        print(f"  ... and {len(problems) - 10} more (tools/data-manifest.tsv lists every origin)", file=sys.stderr)
    print("Without them the tests that need the data skip. Fetch them where the origins are reachable "
          "(`make data`), or copy a complete data folder here and set MAZEBOT_DATA to it.", file=sys.stderr)
    return 1


if __name__ == "__main__":
    raise SystemExit(main())
