"""Memory of each mazebot process through a run: PSS every few seconds, by role, and the peaks.

``mazebot bench --cpu-quota`` reports the peak of the daemon's processes added up
(``daemon_pss_mb_peak``); this says which process holds what, and when. It follows the
process tree under ``ROOT`` (the bench's pid, or the daemon's) and reads
``/proc/PID/smaps_rollup`` of each process (Pss: each shared page split between the processes
that map it; kernel documentation, ``Documentation/filesystems/proc.rst``). Roles: the
process whose child is multiprocessing's fork server (its own, or one forked from the daemon)
is the daemon's main process; the fork server's children are the control process
(``SCHED_FIFO``, where permitted) and the loop-closure worker (the others).

    mazebot bench --cpu-quota 25 --drive explore --seeds 1 --maze MAZE --out DIR &
    python tools/pss_by_process.py $! --period 10 --out DIR/pss.jsonl
    python tools/pss_by_process.py --summary DIR/pss.jsonl

Linux only.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

SCHED_FIFO = 1


def _children() -> dict[int, list[int]]:
    out: dict[int, list[int]] = {}
    for name in os.listdir("/proc"):
        if name.isdigit():
            try:
                fields = Path(f"/proc/{name}/stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            out.setdefault(int(fields[1]), []).append(int(name))
    return out


def _sample(pid: int) -> dict[str, Any] | None:
    try:
        rollup = {}
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            parts = line.split()
            if len(parts) >= 2 and parts[1].isdigit():
                rollup[parts[0].rstrip(":")] = int(parts[1])
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")[:120]
    except OSError:
        return None  # ended meanwhile
    private_kb = rollup.get("Private_Clean", 0) + rollup.get("Private_Dirty", 0)
    return {"pid": pid, "ppid": int(fields[1]), "policy": int(fields[38]), "cmd": cmd,
            "pss_kb": rollup.get("Pss", 0), "private_kb": private_kb}


def roles(rows: list[dict[str, Any]]) -> dict[int, str]:
    """pid -> role for the daemon's processes among ``rows``.

    The fork server is either multiprocessing's own (a fresh interpreter whose command line
    names ``multiprocessing.forkserver``) or forked from the daemon (``mazebot.fork_server``:
    the daemon's command line, under a parent with the same one whose own parent's differs).
    """
    out: dict[int, str] = {}
    by_pid = {r["pid"]: r for r in rows}
    servers_and_children = {x["pid"] for x in rows if "multiprocessing.forkserver" in x["cmd"]}
    for r in rows:
        if r["pid"] in servers_and_children and r["ppid"] not in servers_and_children:
            out[r["pid"]] = "fork server"
            out[r["ppid"]] = "main"
    if not out:
        for r in rows:
            parent = by_pid.get(r["ppid"])
            if parent is None or parent["cmd"] != r["cmd"]:
                continue
            grandparent = by_pid.get(parent["ppid"])
            if grandparent is None or grandparent["cmd"] != parent["cmd"]:
                out[r["pid"]] = "fork server"
                out[parent["pid"]] = "main"
    for r in rows:
        if out.get(r["ppid"]) == "fork server":
            out[r["pid"]] = "control process" if r["policy"] == SCHED_FIFO else "loop-closure worker"
    return out


def watch(root: int, period_s: float, out: Path) -> None:
    start = time.monotonic()
    with out.open("a") as f:
        while os.path.exists(f"/proc/{root}"):
            children, rows, todo = _children(), [], [root]
            while todo:
                pid = todo.pop()
                row = _sample(pid)
                if row is not None:
                    rows.append(row)
                todo += children.get(pid, [])
            f.write(json.dumps({"t_s": round(time.monotonic() - start, 1), "rows": rows}) + "\n")
            f.flush()
            time.sleep(period_s)


def summary(path: Path) -> str:
    peaks: dict[str, float] = {}
    sums = []
    for line in path.read_text().splitlines():
        sample = json.loads(line)
        role = roles(sample["rows"])
        parts = {role[r["pid"]]: r["pss_kb"] / 1024 for r in sample["rows"] if r["pid"] in role}
        for name, mb in parts.items():
            peaks[name] = max(peaks.get(name, 0.0), mb)
        sums.append((sample["t_s"], sum(parts.values()), parts))
    if not sums:
        return "no samples"
    t_s, total, parts = max(sums, key=lambda s: s[1])
    lines = ["peak per process (MB PSS): " + ", ".join(f"{k} {v:.1f}" for k, v in peaks.items()),
             f"the daemon's processes added up: peak {total:.1f} MB at {t_s:.0f} s ("
             + ", ".join(f"{k} {v:.1f}" for k, v in parts.items()) + ")"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("root", nargs="?", type=int, help="pid whose process tree to watch")
    parser.add_argument("--period", type=float, default=10.0, help="seconds between samples")
    parser.add_argument("--out", type=Path, help="JSON lines to append the samples to")
    parser.add_argument("--summary", type=Path, help="print the peaks of a file written before, and exit")
    args = parser.parse_args(argv)
    if args.summary is not None:
        print(summary(args.summary))
        return 0
    if args.root is None or args.out is None:
        parser.error("give the pid to watch and --out FILE (or --summary FILE)")
    watch(args.root, args.period, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
