"""``mazebot bench --cpu-quota``: the daemon and the world in two processes, on the real clock.

A short run with nothing throttled shows the boundary works both ways: the daemon's serial
driver reads revolutions from the emulator's pty, its encoders count the world's edges on
the GPIO thread, and its throttles turn the world's wheels. The same run inside a real
cgroup (root only) shows the cgroup holds every process of the daemon and is gone after.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mazebot.bench.cgroup import CGROUP_ROOT, CpuQuota
from mazebot.bench.cli import parse_quota
from mazebot.bench.quota_run import QuotaRecord, quota_metrics, run_two_process
from mazebot.bench.runner import RunSpec
from mazebot.cli import main
from mazebot.config import Config
from mazebot.errors import UsageError

#: Long enough for SLAM's anchor (~3.6 s of revolutions at rest) and a few seconds of driving.
SHORT_RUN_S = 12.0


def short_run(quota: CpuQuota | None = None) -> tuple[QuotaRecord, dict]:
    config = Config()
    config.daemon.exit_on_fault = True
    spec = RunSpec(None, (4, 4), 1, "explore", clock="real", max_sim_s=SHORT_RUN_S)
    record = run_two_process(config, None, 1, (4, 4), SHORT_RUN_S, quota)
    return record, quota_metrics(config, spec, record)


def gone(pid: int | None) -> bool:
    assert pid is not None
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def assert_the_boundary_carried_everything(record: QuotaRecord, m: dict) -> None:
    assert record.errors == [], record.errors
    assert record.daemon is not None and record.world is not None
    assert m["exit_code"] == 0 and m["fault"] is None
    # lidar: bytes from the emulator's pty through pyserial-asyncio, decoded into revolutions that SLAM used
    assert m["lidar_revolutions"] > 10 and m["slam_scans"] > 10
    assert m["lidar_bytes_sent"] > 10_000
    # encoders: the edges the world sent were driven on the daemon's pins and counted without a glitch;
    # a few may still be in the pipe when the daemon's pins stop listening at shutdown (the wheels
    # coast on in the world for a moment), on a loaded machine more than on a quiet one
    assert 0 < m["gpio_edges"] <= m["world_edges_sent"] <= m["gpio_edges"] * 1.01 + 8
    left, right = m["encoder_ticks"]
    assert abs(left) > 0 and abs(right) > 0
    assert m["encoder_invalid_transitions"] == 0
    # motors: every throttle the daemon wrote reached the world, and the robot moved there
    assert m["world_motor_writes"] == m["motor_writes"] > 0
    assert m["path_m"] > 0.02
    assert m["collisions"] == 0
    assert m["coverage"] is not None and m["coverage"] > 0
    assert m["daemon_rss_mb_peak"] > 20 and m["world_rss_mb_peak"] > 20
    assert m["daemon_pss_mb_peak"] <= m["daemon_rss_mb_peak"]  # shared pages count once
    assert m["world_cpu_percent"] > 0  # the world's own share, outside any quota
    assert m["host_steal_s"] is not None and m["host_steal_s"] >= 0  # what the host took meanwhile
    assert 0 <= m["control_ticks_late_over_50ms"] <= m["control_ticks"]
    assert any("cell" in text for _, text in m["planner_events"])  # the planner chose where to look
    assert all(0 <= t_s <= 2 * SHORT_RUN_S for t_s, _ in m["planner_events"])
    assert gone(record.daemon_pid) and gone(record.world_pid)


@pytest.mark.slow
def test_a_short_two_process_run_reads_the_pty_lidar_counts_the_edges_and_moves_the_wheels() -> None:
    record, m = short_run()
    assert_the_boundary_carried_everything(record, m)
    # no cgroup: its accounting is missing, so are the figures made from it
    assert m["daemon_cpu_percent"] is None and m["cfs_throttled"] is None and m["cgroup_version"] is None
    assert m["daemon_cpu_percent_sim_out"] is None  # nothing to take the simulator's share out of
    assert m["gpio_thread_cpu_percent"] > 0 and m["gpio_pi_path_us_per_edge"] > 0 and m["gpio_sim_path_us_per_edge"] > 0
    # the event loop's thread and the daemon's process are read in the daemon: there without a cgroup
    assert m["loop_thread_ms_per_s"] > 0 and m["loop_thread_outside_parts_ms_per_s"] is not None
    assert m["process_other_threads_ms_per_s"] is not None and m["other_processes_ms_per_s"] is None


def _cgroup_unusable() -> str | None:
    if os.geteuid() != 0:
        return "making a cgroup needs root"
    if CpuQuota.hierarchy() is None:
        return "no cgroup CPU controller on this machine"
    return None


@pytest.mark.slow
@pytest.mark.skipif(_cgroup_unusable() is not None, reason=str(_cgroup_unusable()))
def test_inside_a_real_cgroup_the_daemon_is_accounted_throttled_and_the_cgroup_removed() -> None:
    quota = CpuQuota.create(f"mazebot-test-{os.getpid()}", 50.0)
    try:
        record, m = short_run(quota)
        assert quota.pids() == []  # the daemon, its fork server and its worker have all ended
    finally:
        quota.close()
    assert not any(d.exists() for d in quota.dirs)
    assert_the_boundary_carried_everything(record, m)
    assert m["cgroup_version"] in (1, 2) and m["cpu_quota_percent"] == 50.0
    assert 0 < m["daemon_cpu_percent"] <= 50.0 * 1.1  # the kernel's accounting; the quota holds it
    assert m["daemon_cpu_percent_of_quota"] == pytest.approx(2 * m["daemon_cpu_percent"], abs=0.2)
    assert m["cfs_periods"] > 0 and m["cfs_throttled"] is not None
    assert m["daemon_cpu_s_total"] >= m["daemon_cpu_s"] > 0
    # the simulator's share: what its GPIO stand-in does per edge beyond the Pi's path, at most the edge
    # thread's own CPU, which is part of the cgroup's
    assert 0 < m["gpio_thread_cpu_percent"] < m["daemon_cpu_percent"]
    assert 0 <= m["gpio_sim_share_percent"] <= m["gpio_thread_cpu_percent"]
    excess_us = max(m["gpio_sim_path_us_per_edge"] - m["gpio_pi_path_us_per_edge"], 0.0)
    share = min(m["gpio_edges_per_s"] * excess_us * 1e-4, m["gpio_thread_cpu_percent"])
    assert m["gpio_sim_share_percent"] == pytest.approx(share, abs=0.01)
    assert m["daemon_cpu_percent_sim_out"] == pytest.approx(m["daemon_cpu_percent"] - share, abs=0.1)


def test_the_simulators_gpio_share_is_its_edges_times_what_its_stand_in_does_beyond_the_pi_path() -> None:
    from mazebot.bench.quota_run import gpio_share

    costs = {"decode": 0.4e-6, "mock_noop": 0.8e-6, "mock_decode": 1.2e-6, "mock_alone": 0.45e-6,
             "lgpio_loop": 0.4e-6, "sim_path": 1.65e-6}
    # 10 s of CPU over 100 s; the thread took 1.5 s for 160 000 edges (9.4 µs each); the Pi's path
    # 0.75 + 0.4 µs an edge, the stand-in's 1.65: 0.5 µs an edge is the simulator's
    share = gpio_share(10.0, 100.0, 1.5, 160_000, costs)
    assert share["gpio_pi_path_us_per_edge"] == pytest.approx(1.15)
    assert share["gpio_sim_path_us_per_edge"] == pytest.approx(1.65)
    assert share["gpio_thread_cpu_percent"] == pytest.approx(1.5)
    assert share["gpio_thread_us_per_edge"] == pytest.approx(9.375)
    assert share["gpio_edges_per_s"] == pytest.approx(1600.0)
    assert share["gpio_sim_share_percent"] == pytest.approx(0.08)
    assert share["daemon_cpu_percent_sim_out"] == pytest.approx(10.0 - 0.08)
    # a stand-in no dearer than the Pi's path takes nothing out; the share never exceeds the thread's CPU
    cheap = gpio_share(10.0, 100.0, 1.5, 160_000, costs | {"sim_path": 1.0e-6})
    assert cheap["gpio_sim_share_percent"] == 0.0 and cheap["daemon_cpu_percent_sim_out"] == pytest.approx(10.0)
    dear = gpio_share(10.0, 100.0, 0.01, 160_000, costs)
    assert dear["gpio_sim_share_percent"] == pytest.approx(0.01)
    # a missing part leaves the figure out rather than guessing it
    assert gpio_share(None, 100.0, 1.5, 160_000, costs)["daemon_cpu_percent_sim_out"] is None
    assert gpio_share(10.0, 100.0, 1.5, 160_000, None)["daemon_cpu_percent_sim_out"] is None
    assert gpio_share(10.0, 100.0, None, 160_000, costs)["gpio_thread_cpu_percent"] is None


def test_the_cgroups_cpu_is_split_into_the_loops_thread_the_processs_other_threads_and_the_other_processes() -> None:
    from mazebot.bench.quota_run import cpu_by_thread

    budget = {name: {"cpu_ms_per_s": 10.0} for name in
              ("lidar decoding", "odometry", "slam per revolution", "planner tick", "health check")}
    # 100 robot-seconds: the cgroup 12 s, the daemon's process 9 s, of it the loop's thread 7 s and the GPIO thread 1 s
    where = cpu_by_thread(12.0, 100.0, 7.0, 9.0, 1.0, budget)
    assert where == pytest.approx({"loop_thread_ms_per_s": 70.0, "loop_thread_outside_parts_ms_per_s": 20.0,
                                   "process_other_threads_ms_per_s": 10.0, "other_processes_ms_per_s": 30.0})
    missing = cpu_by_thread(None, 100.0, 7.0, 9.0, None, {"odometry": {"cpu_ms_per_s": None}})
    assert missing["other_processes_ms_per_s"] is None and missing["loop_thread_outside_parts_ms_per_s"] is None
    assert cpu_by_thread(12.0, None, 7.0, 9.0, 1.0, budget) == dict.fromkeys(where)


def test_the_hosts_steal_is_the_eighth_value_of_the_cpu_line_in_user_hz_ticks() -> None:
    from mazebot.bench.quota_run import host_steal_s

    tick_s = 1.0 / os.sysconf("SC_CLK_TCK")
    stat = "cpu  4705 356 584 3699 23 23 0 1234 0 0\ncpu0 1393 280 290 1828 12 11 0 600 0 0\n"
    assert host_steal_s(stat) == pytest.approx(1234 * tick_s)
    assert host_steal_s("cpu0 1 2 3 4 5 6 7 8\n") is None  # not the machine's line
    assert host_steal_s("cpu  1 2 3 4\n") is None  # a kernel too old to count steal
    assert host_steal_s() is not None  # this machine's own


def test_the_quota_is_a_percentage_of_one_core_or_max() -> None:
    assert parse_quota("25") == 25.0
    assert parse_quota("12.5%") == 12.5
    assert parse_quota("max") is None
    for bad in ("0", "-5", "abc", str(100 * (os.cpu_count() or 1) + 1)):
        with pytest.raises(UsageError):
            parse_quota(bad)


@pytest.mark.parametrize("extra", [["--cpu-quota", "0"], ["--cpu-quota", "25", "--drive", "scripted"],
                                   ["--cpu-quota", "25", "--clock", "virtual"],
                                   ["--cpu-quota", "25", "--faults", "kidnap"]])
def test_what_a_quota_run_cannot_do_is_a_usage_error(extra: list[str], tmp_path: Path, capsys) -> None:
    assert main(["bench", "--size", "4x4", "--seeds", "1", "--out", str(tmp_path), *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith("mazebot: ") and err.count("\n") == 1


def session_processes(sid: int) -> list[int]:
    """Every process whose session is ``sid`` (field 6 of ``/proc/PID/stat``), zombies included."""
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rpartition(")")[2].split()
            except OSError:
                continue
            if int(fields[3]) == sid:
                out.append(int(entry.name))
    return out


@pytest.mark.slow
@pytest.mark.skipif(_cgroup_unusable() is not None, reason=str(_cgroup_unusable()))
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_or_sigterm_to_every_process_ends_them_all_and_removes_the_cgroup(sig: int, tmp_path: Path) -> None:
    """As a terminal's Ctrl-C does: the signal goes to every process of the group at once."""
    log = tmp_path / "stderr.txt"
    with open(log, "wb") as stderr:
        bench = subprocess.Popen(
            [sys.executable, "-m", "mazebot", "bench", "--cpu-quota", "50", "--size", "4x4", "--seeds", "1",
             "--out", str(tmp_path)],
            start_new_session=True, stdout=subprocess.DEVNULL, stderr=stderr,
            # as a terminal's foreground job: a shell's background job (a CI script run with `&`)
            # starts with Ctrl-C ignored, which Python, and so the bench, would keep
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        )
    try:
        names = [f"mazebot-bench-{bench.pid}-1"]
        dirs = [d / name for name in names for d in (CGROUP_ROOT, CGROUP_ROOT / "cpu", CGROUP_ROOT / "cpuacct")]
        procs = [d / "cgroup.procs" for d in dirs]
        deadline = time.monotonic() + 60
        # the daemon is up once its loop-closure fork server has joined it in the cgroup
        while time.monotonic() < deadline and max((len(p.read_text().split()) for p in procs if p.exists()),
                                                  default=0) < 2:
            time.sleep(0.2)
        assert bench.poll() is None, log.read_text()
        os.killpg(bench.pid, sig)
        code = bench.wait(60)
    finally:
        if bench.poll() is None:
            os.killpg(bench.pid, signal.SIGKILL)
            bench.wait()
    assert code == 130, log.read_text()
    assert "Traceback" not in log.read_text()
    deadline = time.monotonic() + 10  # the kernel reaps the last of them (the resource tracker) on its own
    while session_processes(bench.pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert session_processes(bench.pid) == []
    assert not any(d.exists() for d in dirs)


def test_the_report_has_a_row_per_run_nulls_for_missing_parts_and_the_planner_log_beside_it(tmp_path: Path) -> None:
    import json

    from mazebot.bench.report import QUOTA_COLUMNS, write_quota_report

    run = {key: None for key, _ in QUOTA_COLUMNS} | {
        "maze": "generated-4x4", "seed": 1, "done": True, "collisions": 0, "time_s": 12.5,
        "planner_events": [(1.25, "look at its E side of cell (2, -1)")],
    }
    results = write_quota_report(tmp_path, [run], "mazebot bench --cpu-quota max")
    saved = json.loads((tmp_path / "results.json").read_text())
    assert saved == results and "planner_events" not in saved["runs"][0]
    log = tmp_path / saved["runs"][0]["planner_log"]
    assert log.read_text() == "    1.25  look at its E side of cell (2, -1)\n"
    report = (tmp_path / "report.md").read_text()
    row = next(line for line in report.splitlines() if line.startswith("| generated-4x4"))
    assert row.count("|") == len(QUOTA_COLUMNS) + 1
    assert "no limit" in row and "null" in row  # no quota; no cgroup accounting
    assert "Where the daemon's CPU went" not in report  # no thread clocks read: no such section


def test_the_report_says_what_held_slam_up_at_each_dropped_revolution(tmp_path: Path) -> None:
    from mazebot.bench.report import QUOTA_COLUMNS, write_quota_report

    note = ("SLAM is 8 revolutions behind: the revolution ending at 53083.28 s dropped; in the 1.30 s it waited: "
            "4 revolutions matched in 0.78 s (0.03 s CPU)")
    quiet = {key: None for key, _ in QUOTA_COLUMNS} | {"maze": "shi2", "seed": 1, "done": True, "collisions": 0}
    dropped = quiet | {"seed": 2, "slam_scans_dropped": 1, "slam_drop_notes": [note]}
    write_quota_report(tmp_path, [quiet], "mazebot bench --cpu-quota 25")
    assert "Revolutions dropped" not in (tmp_path / "report.md").read_text()
    write_quota_report(tmp_path, [quiet, dropped], "mazebot bench --cpu-quota 25")
    report = (tmp_path / "report.md").read_text()
    assert "## Revolutions dropped, and what held SLAM up" in report
    assert f"- shi2 seed 2: {note}" in report.splitlines()
