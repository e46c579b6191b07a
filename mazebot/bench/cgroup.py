"""A CPU quota for the daemon: a cgroup that makes this machine's core act like a slower one.

The kernel's CFS bandwidth control gives a group of processes ``quota`` microseconds of
CPU time in every ``period`` (Linux kernel documentation, "CFS Bandwidth Control",
``Documentation/scheduler/sched-bwc.rst``). With a short period (10 ms) a group limited
to 25 % runs 2.5 ms of every 10 ms: a control loop of 50 ms sees a CPU a quarter as fast,
not a CPU that stops for 75 ms at a time (the default period of 100 ms would).

Two hierarchies, one interface:

- cgroup v2 (``cgroup.controllers`` lists ``cpu``): one directory, ``cpu.max`` holds
  ``"QUOTA PERIOD"`` (``"max PERIOD"`` for no limit), ``cpu.stat`` holds ``usage_usec``,
  ``nr_periods``, ``nr_throttled`` and ``throttled_usec`` (kernel documentation,
  ``Documentation/admin-guide/cgroup-v2.rst``, "CPU Interface Files");
- cgroup v1: ``cpu/NAME/cpu.cfs_period_us`` and ``cpu.cfs_quota_us`` (``-1`` for no
  limit), ``cpu.stat`` with ``nr_periods``, ``nr_throttled`` and ``throttled_time`` (ns);
  the CPU time used is ``cpuacct.usage`` (ns), in ``cpuacct/NAME`` when that controller
  is mounted on its own (as on this machine) or in the same directory when co-mounted.

A process is moved by writing its pid to ``cgroup.procs``; its later threads and
children (the loop-closure worker, the thread pools) are born inside. Creating a
cgroup needs root (or a delegated subtree).

Example::

    with CpuQuota.create("mazebot-bench-1", percent=25.0) as group:
        group.add(pid)
        ...
        group.usage_s(), group.stat()
"""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Self

from mazebot.errors import HardwareUnavailable

#: The CFS period of the quota: short, so the limit acts like a slower CPU, not like pauses.
PERIOD_US = 10_000
#: The kernel refuses a quota below 1 ms (sched-bwc.rst: "the minimum quota allowed is 1ms").
MIN_QUOTA_US = 1_000
#: The share of the quota set aside as real-time runtime on a v1 hierarchy with real-time
#: group scheduling (the control process's ``SCHED_FIFO``); the fair share is the rest, so the
#: two together never exceed the quota.
RT_SHARE = 0.1
#: At least this share of one core becomes real-time runtime (the control process needs ~1.2 %
#: of a core here, in bursts: at 15 % a tenth of the quota, 1.5 %, left its ticks waiting for the
#: next real-time period).
RT_MIN_OF_CORE = 0.03
#: The real-time period: long enough that a control tick (under a millisecond) fits in one
#: period's runtime at any quota the benchmark is run at.
RT_PERIOD_US = 100_000
#: How long removing the cgroup waits for its last processes to exit before killing them.
DRAIN_TIMEOUT_S = 3.0

CGROUP_ROOT = Path("/sys/fs/cgroup")


@dataclass(frozen=True)
class CpuStat:
    """Throttling counters of the group (``cpu.stat``), and its CPU time so far."""

    usage_s: float | None
    nr_periods: int | None
    nr_throttled: int | None
    throttled_s: float | None


def quota_us(percent: float | None, period_us: int = PERIOD_US) -> int | None:
    """Microseconds of CPU per period for ``percent`` of one core; None is no limit.

    >>> quota_us(25.0)
    2500
    """
    if percent is None:
        return None
    if percent <= 0:
        raise ValueError(f"a CPU quota must be above 0 % of one core, got {percent:g} %")
    return max(MIN_QUOTA_US, round(period_us * percent / 100.0))


def split_quota_us(quota: int | None, period_us: int = PERIOD_US,
                   rt_share: float = RT_SHARE) -> tuple[int | None, int]:
    """``(fair quota per period_us, real-time runtime per RT_PERIOD_US)`` for a group whose tasks may be real-time.

    With real-time group scheduling (``CONFIG_RT_GROUP_SCHED``; kernel documentation,
    ``scheduler/sched-rt-group.rst``) a real-time task in a group with no real-time runtime
    may not be made real-time at all, and one in a group with runtime is limited by it and
    not by the fair quota. So the quota is split: ``rt_share`` of it becomes real-time
    runtime, the rest stays the fair quota, and the group can never use more than the
    quota. Without a limit (``quota`` None) the real-time runtime is ``rt_share`` of the
    real-time period.

    At least ``RT_MIN_OF_CORE`` of one core is set aside, and at most half the quota.

    >>> split_quota_us(5000)
    (4500, 5000)
    >>> split_quota_us(2500)
    (2200, 3000)
    """
    if quota is None:
        return None, round(RT_PERIOD_US * rt_share)
    rt_per_period = min(max(round(quota * rt_share), round(period_us * RT_MIN_OF_CORE)), quota // 2)
    return max(MIN_QUOTA_US, quota - rt_per_period), round(rt_per_period * RT_PERIOD_US / period_us)


def _read_keyed(path: Path) -> dict[str, int]:
    """A flat-keyed cgroup file (``key value`` per line) as a dict."""
    out: dict[str, int] = {}
    with contextlib.suppress(OSError):
        for line in path.read_text().splitlines():
            key, _, value = line.partition(" ")
            with contextlib.suppress(ValueError):
                out[key] = int(value)
    return out


def _write(path: Path, text: str) -> None:
    """One write to a cgroup control file (the kernel takes each write as one command)."""
    with open(path, "w") as f:
        f.write(text)


class CpuQuota:
    """One cgroup with a CPU quota, v2 or v1; :meth:`create` picks the hierarchy.

    ``version`` is 2 or 1, ``dirs`` the directories created (v1 may need two: ``cpu``
    and ``cpuacct``), ``percent`` the quota (None: no limit, only the accounting).
    """

    def __init__(self, version: int, cpu_dir: Path, acct_dir: Path, percent: float | None) -> None:
        self.version = version
        self.rt_runtime_us = 0  # real-time runtime per RT_PERIOD_US set aside (v1 with real-time groups)
        self.cpu_dir = cpu_dir
        self.acct_dir = acct_dir
        self.percent = percent
        self.dirs = [cpu_dir] if acct_dir == cpu_dir else [cpu_dir, acct_dir]
        self._made: list[Path] = []  # the directories this object created (and only those it removes)
        self._closed = False

    @staticmethod
    def hierarchy(root: Path = CGROUP_ROOT) -> tuple[int, Path, Path] | None:
        """``(version, cpu parent, cpuacct parent)`` of the usable CPU controller, or None."""
        controllers = root / "cgroup.controllers"
        if controllers.is_file() and "cpu" in controllers.read_text().split():
            return 2, root, root
        cpu = root / "cpu"
        if (cpu / "cpu.cfs_quota_us").is_file():
            acct = cpu if (cpu / "cpuacct.usage").is_file() else root / "cpuacct"
            return 1, cpu, acct
        return None

    @classmethod
    def create(cls, name: str, percent: float | None, root: Path = CGROUP_ROOT,
               period_us: int = PERIOD_US) -> CpuQuota:
        """Make the cgroup ``name`` with ``percent`` of one core (None: unlimited, accounting only).

        Raises :class:`HardwareUnavailable` (one line, what to do) when no CPU controller is
        mounted or the cgroup cannot be made (not root).
        """
        found = cls.hierarchy(root)
        quota = quota_us(percent, period_us)
        if found is None:
            raise HardwareUnavailable(
                f"no cgroup CPU controller under {root} (neither v2 cgroup.controllers with cpu nor v1 "
                "cpu/cpu.cfs_quota_us); --cpu-quota needs one"
            )
        version, cpu_parent, acct_parent = found
        group = cls(version, cpu_parent / name, acct_parent / name, percent)
        try:
            if version == 2:
                subtree = root / "cgroup.subtree_control"
                if subtree.is_file() and "cpu" not in subtree.read_text().split():
                    _write(subtree, "+cpu")  # children of the root get the cpu controller
                group._mkdir(group.cpu_dir)
                _write(group.cpu_dir / "cpu.max", f"{'max' if quota is None else quota} {period_us}")
            else:
                for d in group.dirs:
                    group._mkdir(d)
                if (cpu_parent / "cpu.rt_runtime_us").is_file():  # real-time group scheduling
                    quota = group._set_aside_rt(quota, period_us)
                # the period first: a quota is checked against the period in force
                _write(group.cpu_dir / "cpu.cfs_period_us", str(period_us))
                _write(group.cpu_dir / "cpu.cfs_quota_us", str(-1 if quota is None else quota))
        except OSError as exc:
            group.close()
            hint = " (run as root, e.g. with sudo)" if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS) else ""
            raise HardwareUnavailable(
                f"cannot set up the CPU quota cgroup {group.cpu_dir}: {exc.strerror or exc}{hint}"
            ) from None
        return group

    def _set_aside_rt(self, quota: int | None, period_us: int) -> int | None:
        """Give the group real-time runtime out of ``quota``; returns the fair quota left.

        Best effort: a parent whose real-time runtime is all given away refuses the write
        (``EBUSY``, ``EINVAL``), and then the group keeps the whole quota as fair share and
        its tasks stay under the fair scheduler (the control process says so in its log).
        """
        fair, rt_us = split_quota_us(quota, period_us)
        try:
            _write(self.cpu_dir / "cpu.rt_period_us", str(RT_PERIOD_US))
            _write(self.cpu_dir / "cpu.rt_runtime_us", str(rt_us))
        except OSError:
            return quota
        self.rt_runtime_us = rt_us
        return fair

    def _mkdir(self, d: Path) -> None:
        d.mkdir()
        self._made.append(d)

    @property
    def procs_files(self) -> list[Path]:
        """The ``cgroup.procs`` file of each directory: a process joins by writing its pid to all."""
        return [d / "cgroup.procs" for d in self.dirs]

    def add(self, pid: int) -> None:
        """Move process ``pid`` (and so its future threads and children) into the group."""
        join(self.procs_files, pid)

    def pids(self) -> list[int]:
        """The processes in the group now."""
        out: set[int] = set()
        for path in self.procs_files:
            with contextlib.suppress(OSError):
                out.update(int(p) for p in path.read_text().split())
        return sorted(out)

    def usage_s(self) -> float | None:
        """CPU seconds the group's processes used since it was made (the kernel's own accounting)."""
        if self.version == 2:
            usec = _read_keyed(self.cpu_dir / "cpu.stat").get("usage_usec")
            return None if usec is None else usec / 1e6
        try:
            return int((self.acct_dir / "cpuacct.usage").read_text()) / 1e9
        except (OSError, ValueError):
            return None

    def stat(self) -> CpuStat:
        """The CPU time and the throttling counters now."""
        stat = _read_keyed(self.cpu_dir / "cpu.stat")
        throttled = stat.get("throttled_usec")
        throttled_s = throttled / 1e6 if throttled is not None else None
        if self.version == 1 and "throttled_time" in stat:
            throttled_s = stat["throttled_time"] / 1e9
        return CpuStat(self.usage_s(), stat.get("nr_periods"), stat.get("nr_throttled"), throttled_s)

    def close(self) -> None:
        """Remove the group: its remaining processes (ours: we made it) are asked, then made, to exit.

        Safe to call more than once.
        """
        if self._closed:
            return
        self._closed = True
        deadline = time.monotonic() + DRAIN_TIMEOUT_S
        sent_term = False
        for d in reversed(self._made):
            while d.exists():
                try:
                    d.rmdir()
                    break
                except OSError as exc:
                    if exc.errno == errno.ENOENT:
                        break
                    if exc.errno != errno.EBUSY:  # a temporary layout in tests: files are not the kernel's
                        _remove_tree(d)
                        break
                    left = self.pids()
                    if time.monotonic() > deadline and left:
                        _signal_all(left, signal.SIGKILL)
                    elif not sent_term and left:
                        _signal_all(left, signal.SIGTERM)
                        sent_term = True
                    time.sleep(0.05)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def join(procs_files: list[Path], pid: int | None = None) -> None:
    """Write ``pid`` (default: this process) into each ``cgroup.procs`` (the caller's own way in)."""
    for path in procs_files:
        _write(path, str(os.getpid() if pid is None else pid))


def _signal_all(pids: list[int], sig: int) -> None:
    for pid in pids:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, sig)


def _remove_tree(d: Path) -> None:
    """Remove a directory laid out like a cgroup in a test (regular files the kernel would not have)."""
    for child in d.iterdir():
        child.unlink()
    d.rmdir()
