"""Sum a py-spy profile of a simulated run into the parts of the system it went through.

py-spy samples the running process without slowing it down much (cProfile inflates
many-small-call paths such as the per-edge encoder callbacks several times over). Record
a raw (collapsed) profile of one benchmark run, then sum it here::

    python3 -m venv /tmp/spy && /tmp/spy/bin/pip install py-spy
    /tmp/spy/bin/py-spy record -r 250 -f raw -o /tmp/run.txt -- \\
        .venv/bin/mazebot bench --suite smoke --drive scripted --out /tmp/b
    .venv/bin/python tools/pyspy_categories.py /tmp/run.txt

Each main-thread sample goes to the first part found walking from the innermost frame
outwards, so ray casting inside the lidar emulator counts as ray casting and numpy
inside SLAM counts as SLAM; samples whose innermost project-level frame is the event
loop count as event-loop overhead. Executor threads (SLAM's loop-closure jobs) are
reported apart, as a share of all samples.
"""

from __future__ import annotations

import sys
from collections import Counter

#: (part, substrings of a frame), tried in this order on each frame.
PARTS: list[tuple[str, tuple[str, ...]]] = [
    ("lidar emulator: ray casting", ("sim/raycast.py",)),
    ("lidar emulator: sample times, poses, noise", ("sim/lidar_samples.py",)),
    ("lidar emulator: byte encoding", ("encode_standard_samples", "encode_express")),
    ("lidar driver: protocol decoding", ("io/rplidar_protocol.py",)),
    ("encoder edges: signal, gpiozero mock pins, decoder", ("sim/encoder_signals.py", "io/encoders.py", "gpiozero/")),
    ("physics", ("sim/physics.py",)),
    ("SLAM (per-scan update, publishing)", ("mazebot/slam/", "tasks/slam_task.py")),
    ("lidar driver: reads, stamping, revolutions", ("io/rplidar.py", "io/serial_link.py")),
    ("lidar emulator: serving", ("sim/lidar_emulator.py",)),
    ("odometry task", ("tasks/odometry_task.py",)),
    ("benchmark recorder and scripted driver", ("bench/",)),
    ("other project code", ("mazebot/",)),
    ("imports", ("importlib", "<module>")),
]
LOOP = "event loop (select, timers, task switches)"
EXECUTOR_BUSY = "executor thread: SLAM loop-closure jobs"
EXECUTOR_IDLE = "executor thread: waiting"


def part_of(stack: list[str]) -> str:
    """The part of the system one sampled stack (outermost frame first) belongs to."""
    if stack[0].startswith("Thread._bootstrap"):
        leaf = stack[-1]
        return EXECUTOR_IDLE if leaf.startswith("_worker") or "wait (threading" in leaf else EXECUTOR_BUSY
    for frame in reversed(stack):
        if "asyncio/" in frame or "selectors.py" in frame or "virtual_time.py" in frame:
            return LOOP
        for name, keys in PARTS:
            if any(k in frame for k in keys):
                return name
    return "other"


def main(path: str) -> None:
    counts: Counter[str] = Counter()
    with open(path) as lines:
        for line in lines:
            stack, _, n = line.rstrip().rpartition(" ")
            if stack:
                counts[part_of(stack.split(";"))] += int(n)
    total = sum(counts.values())
    main_thread = sum(n for k, n in counts.items() if not k.startswith("executor"))
    print(f"{'% main thread':>14} {'% all':>6}  part")
    for name, n in counts.most_common():
        share = "" if name.startswith("executor") else f"{100 * n / main_thread:.1f}"
        print(f"{share:>14} {100 * n / total:6.1f}  {name}")
    print(f"{total} samples")


if __name__ == "__main__":
    main(sys.argv[1])
