"""The CPU-quota cgroup's file writing, against temporary directories laid out like each hierarchy.

The kernel's own files are not there, so these tests check what is written where and
what is read back; ``tests/bench/test_quota_run.py`` runs the real thing (as root).
"""

from __future__ import annotations

import errno
from pathlib import Path

import pytest

from mazebot.bench import cgroup
from mazebot.bench.cgroup import PERIOD_US, CpuQuota, quota_us
from mazebot.errors import HardwareUnavailable


def v2_root(tmp_path: Path, subtree: str = "") -> Path:
    root = tmp_path / "cgroup2"
    root.mkdir()
    (root / "cgroup.controllers").write_text("cpuset cpu io memory pids\n")
    (root / "cgroup.subtree_control").write_text(subtree)
    return root


def v1_root(tmp_path: Path, comounted: bool = False) -> Path:
    root = tmp_path / "cgroup1"
    cpu = root / ("cpu,cpuacct" if comounted else "cpu")
    cpu.mkdir(parents=True)
    (cpu / "cpu.cfs_quota_us").write_text("-1\n")
    (cpu / "cpu.cfs_period_us").write_text("100000\n")
    if comounted:
        (root / "cpu").symlink_to(cpu)
        (cpu / "cpuacct.usage").write_text("0\n")
    else:
        (root / "cpuacct").mkdir()
        (root / "cpuacct" / "cpuacct.usage").write_text("0\n")
    return root


def test_a_quota_is_a_share_of_the_10_ms_period_and_never_below_the_kernels_1_ms() -> None:
    assert PERIOD_US == 10_000
    assert quota_us(25.0) == 2500
    assert quota_us(50.0) == 5000
    assert quota_us(150.0) == 15000  # one and a half cores
    assert quota_us(5.0) == 1000  # 500 us would be refused by the kernel
    assert quota_us(None) is None
    with pytest.raises(ValueError, match="above 0"):
        quota_us(0.0)


def test_v2_writes_cpu_max_enables_the_controller_and_reads_usage_and_throttling(tmp_path: Path) -> None:
    root = v2_root(tmp_path)
    group = CpuQuota.create("mazebot-test", 25.0, root=root)
    d = root / "mazebot-test"
    assert group.version == 2 and group.dirs == [d]
    assert (d / "cpu.max").read_text() == "2500 10000"
    assert (root / "cgroup.subtree_control").read_text() == "+cpu"
    group.add(4242)
    assert (d / "cgroup.procs").read_text() == "4242"
    assert group.pids() == [4242]
    (d / "cpu.stat").write_text(
        "usage_usec 1500000\nuser_usec 1000000\nsystem_usec 500000\n"
        "nr_periods 300\nnr_throttled 120\nthrottled_usec 250000\n"
    )
    stat = group.stat()
    assert stat.usage_s == pytest.approx(1.5)
    assert (stat.nr_periods, stat.nr_throttled) == (300, 120)
    assert stat.throttled_s == pytest.approx(0.25)
    group.close()
    assert not d.exists()
    group.close()  # twice is harmless


def test_v2_without_a_limit_writes_max_and_leaves_an_enabled_controller_alone(tmp_path: Path) -> None:
    root = v2_root(tmp_path, subtree="cpu memory\n")
    with CpuQuota.create("unlimited", None, root=root) as group:
        assert (root / "unlimited" / "cpu.max").read_text() == "max 10000"
        assert group.usage_s() is None  # no cpu.stat yet: unknown, not zero
    assert (root / "cgroup.subtree_control").read_text() == "cpu memory\n"
    assert not (root / "unlimited").exists()


def test_v1_writes_period_then_quota_and_joins_cpu_and_a_separate_cpuacct(tmp_path: Path) -> None:
    root = v1_root(tmp_path)
    group = CpuQuota.create("mazebot-test", 15.0, root=root)
    cpu, acct = root / "cpu" / "mazebot-test", root / "cpuacct" / "mazebot-test"
    assert group.version == 1 and group.dirs == [cpu, acct]
    assert (cpu / "cpu.cfs_period_us").read_text() == "10000"
    assert (cpu / "cpu.cfs_quota_us").read_text() == "1500"
    group.add(777)
    assert (cpu / "cgroup.procs").read_text() == "777" and (acct / "cgroup.procs").read_text() == "777"
    (acct / "cpuacct.usage").write_text("2500000000\n")
    (cpu / "cpu.stat").write_text("nr_periods 50\nnr_throttled 7\nthrottled_time 30000000\n")
    stat = group.stat()
    assert stat.usage_s == pytest.approx(2.5)
    assert (stat.nr_periods, stat.nr_throttled) == (50, 7)
    assert stat.throttled_s == pytest.approx(0.03)
    group.close()
    assert not cpu.exists() and not acct.exists()


def test_v1_unlimited_is_quota_minus_one_and_a_comounted_cpuacct_is_one_directory(tmp_path: Path) -> None:
    root = v1_root(tmp_path, comounted=True)
    with CpuQuota.create("g", None, root=root) as group:
        d = root / "cpu" / "g"
        assert group.dirs == [d]
        assert (d / "cpu.cfs_quota_us").read_text() == "-1"
        (d / "cpuacct.usage").write_text("1000000000")
        assert group.usage_s() == pytest.approx(1.0)


def test_no_cpu_controller_is_one_clear_line(tmp_path: Path) -> None:
    (tmp_path / "cgroup.controllers").write_text("memory pids\n")  # v2 without cpu, and no v1 cpu
    with pytest.raises(HardwareUnavailable, match="no cgroup CPU controller") as info:
        CpuQuota.create("g", 25.0, root=tmp_path)
    assert "\n" not in str(info.value)


def test_a_cgroup_that_cannot_be_made_says_so_and_leaves_nothing_behind(tmp_path: Path) -> None:
    root = v1_root(tmp_path)
    (root / "cpu" / "taken").mkdir()  # mkdir fails (exists), as it fails with EACCES for a non-root user
    with pytest.raises(HardwareUnavailable, match="cannot set up the CPU quota cgroup"):
        CpuQuota.create("taken", 25.0, root=root)
    assert (root / "cpu" / "taken").is_dir()  # not ours: left alone
    assert not (root / "cpuacct" / "taken").exists()


@pytest.mark.parametrize(("percent", "fair_us", "rt_us"), [
    (50.0, 4500, 5000),  # a tenth of the quota: 0.5 ms per 10 ms = 5 ms per 100 ms real-time
    (25.0, 2200, 3000),  # a tenth would be 2.5 % of a core: the 3 % floor
    (15.0, 1200, 3000),
])
def test_v1_with_real_time_groups_sets_part_of_the_quota_aside_as_real_time_runtime(
    tmp_path: Path, percent: float, fair_us: int, rt_us: int
) -> None:
    root = v1_root(tmp_path)
    (root / "cpu" / "cpu.rt_runtime_us").write_text("950000\n")  # the kernel has real-time group scheduling
    with CpuQuota.create("rt", percent, root=root) as group:
        d = root / "cpu" / "rt"
        assert (d / "cpu.cfs_quota_us").read_text() == str(fair_us)
        assert (d / "cpu.rt_period_us").read_text() == "100000"
        assert (d / "cpu.rt_runtime_us").read_text() == str(rt_us)
        assert group.rt_runtime_us == rt_us
        fair_share = int((d / "cpu.cfs_quota_us").read_text()) / 10_000
        assert fair_share + group.rt_runtime_us / 100_000 == pytest.approx(percent / 100)  # never more than the quota


def test_v1_without_real_time_groups_keeps_the_whole_quota_fair(tmp_path: Path) -> None:
    root = v1_root(tmp_path)
    with CpuQuota.create("fair", 25.0, root=root) as group:
        d = root / "cpu" / "fair"
        assert (d / "cpu.cfs_quota_us").read_text() == "2500"
        assert not (d / "cpu.rt_runtime_us").exists()
        assert group.rt_runtime_us == 0


def test_a_refused_real_time_runtime_leaves_the_whole_quota_fair(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    root = v1_root(tmp_path)
    (root / "cpu" / "cpu.rt_runtime_us").write_text("950000\n")
    real_write = cgroup._write

    def write(path: Path, text: str) -> None:
        if path.name == "cpu.rt_runtime_us":  # the parent's real-time runtime is all given away
            raise OSError(errno.EBUSY, "Device or resource busy")
        real_write(path, text)

    monkeypatch.setattr(cgroup, "_write", write)
    with CpuQuota.create("busy", 25.0, root=root) as group:
        assert (root / "cpu" / "busy" / "cpu.cfs_quota_us").read_text() == "2500"
        assert group.rt_runtime_us == 0
