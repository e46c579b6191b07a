"""Does this machine itself stop? A 10 ms periodic loop with nothing of mazebot in it.

The quota bench (``mazebot bench --cpu-quota``) reports control ticks ~100 ms late when the
development machine is busy. This probe asks whether the machine, not the daemon, is where
such a delay comes from: one process, real-time priority where it is allowed, wakes every
10 ms for ``--seconds`` and measures how late each wake-up is, while ``--busy N`` processes spin
beside it (N = the number of CPUs saturates the machine). For every wake-up later than
``--late-ms`` it reads how much CPU time the hypervisor took from this machine meanwhile
(``/proc/stat``'s steal, :func:`mazebot.bench.quota_run.host_steal_s`): a virtual machine capped
on its host stops whole when it has used its host share, and a real-time process inside it
cannot run either.

    python tools/host_stall_probe.py --seconds 40 --busy 2 --out DIR/probe.json

A Raspberry Pi's cores are its own: on the robot there is no steal, and this probe tells what
part of a quota run's lateness the development machine adds.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import time
from pathlib import Path

from mazebot.bench.quota_run import host_steal_s

#: The probe's period: a fifth of the control loop's default 50 ms, so a stop of a few
#: milliseconds shows as well as one of a whole control period.
PERIOD_S = 0.01
#: The probe's real-time priority where SCHED_FIFO is allowed (the bench's control process uses one too).
FIFO_PRIORITY = 50


def _spin(seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        pass


def probe(seconds: float, late_ms: float) -> dict[str, object]:
    """Wake every ``PERIOD_S`` for ``seconds``; the lateness of each wake-up and the steal over the late ones."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(FIFO_PRIORITY))
        realtime = True
    except (AttributeError, PermissionError, OSError):
        realtime = False
    steal_start = host_steal_s()
    start = time.monotonic()
    due = start
    lateness_ms: list[float] = []
    stalls: list[dict[str, float | None]] = []
    steal_before = steal_start
    while time.monotonic() - start < seconds:
        due += PERIOD_S
        wait_s = due - time.monotonic()
        if wait_s > 0:
            time.sleep(wait_s)
        late = (time.monotonic() - due) * 1000.0
        steal_now = host_steal_s()
        lateness_ms.append(late)
        if late > late_ms:
            taken = None if steal_now is None or steal_before is None else round((steal_now - steal_before) * 1000, 1)
            stalls.append({"at_s": round(due - start, 3), "late_ms": round(late, 1), "host_steal_ms": taken})
            due = time.monotonic()  # one stall counted once, not as the catch-up ticks behind it
        steal_before = steal_now
    steal_end = host_steal_s()
    ordered = sorted(lateness_ms)
    return {
        "realtime": realtime,
        "wakeups": len(ordered),
        "late_ms_p99": round(ordered[int(0.99 * (len(ordered) - 1))], 2),
        "late_ms_max": round(ordered[-1], 1),
        "stalls": stalls,
        "host_steal_s": None if steal_start is None or steal_end is None else round(steal_end - steal_start, 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=30.0, help="how long the probe runs")
    parser.add_argument("--busy", type=int, default=0, help="processes spinning beside it")
    parser.add_argument("--late-ms", type=float, default=20.0, help="a wake-up this late is listed as a stall")
    parser.add_argument("--out", type=Path, help="write the result as JSON here too")
    args = parser.parse_args()
    spinners = [multiprocessing.Process(target=_spin, args=(args.seconds + 1.0,), daemon=True)
                for _ in range(args.busy)]
    for p in spinners:
        p.start()
    try:
        result = probe(args.seconds, args.late_ms) | {"busy": args.busy, "cpus": os.cpu_count(),
                                                       "loadavg": Path("/proc/loadavg").read_text().strip()}
    finally:
        for p in spinners:
            p.terminate()
            p.join()
    text = json.dumps(result, indent=2)
    print(text)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
