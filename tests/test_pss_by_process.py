"""tools/pss_by_process.py: the daemon's processes told apart by their place in the tree, the peaks read back."""

from __future__ import annotations

import importlib.util
import json
import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("pss_by_process", REPO / "tools" / "pss_by_process.py")
assert spec is not None and spec.loader is not None
pss_by_process = importlib.util.module_from_spec(spec)
spec.loader.exec_module(pss_by_process)

SERVER = "python -B -c from multiprocessing.forkserver import main; main(14, 15, ['mazebot.slam.loop_worker'])"


def _row(pid: int, ppid: int, cmd: str, pss_mb: float, policy: int = 0) -> dict[str, object]:
    return {"pid": pid, "ppid": ppid, "policy": policy, "cmd": cmd, "pss_kb": int(pss_mb * 1024), "private_kb": 0}


def _tree(main_mb: float, worker_mb: float) -> list[dict[str, object]]:
    return [
        _row(10, 1, "mazebot bench --cpu-quota 25", 60.0),
        _row(11, 10, "python -B -c from multiprocessing.spawn import spawn_main", main_mb),  # the daemon
        _row(12, 10, "python -B -c from multiprocessing.spawn import spawn_main", 40.0),  # the world
        _row(13, 11, SERVER, 30.0),
        _row(14, 13, SERVER, 25.0, policy=1),  # SCHED_FIFO: the control process
        _row(15, 13, SERVER, worker_mb),
    ]


def test_roles_follow_the_fork_server() -> None:
    assert pss_by_process.roles(_tree(70.0, 35.0)) == {
        11: "main", 13: "fork server", 14: "control process", 15: "loop-closure worker"}


def test_roles_of_a_fork_server_forked_from_the_daemon() -> None:
    daemon = "python -B -c from multiprocessing.spawn import spawn_main; spawn_main(tracker_fd=5, pipe_handle=9)"
    rows = [
        _row(10, 1, "mazebot bench --cpu-quota 25", 60.0),
        _row(11, 10, daemon, 70.0),
        _row(12, 10, "python -B -c from multiprocessing.spawn import spawn_main; spawn_main(pipe_handle=7)", 40.0),
        _row(16, 10, "python -B -c from multiprocessing.resource_tracker import main;main(6)", 6.0),
        _row(13, 11, daemon, 20.0),  # the fork server: the daemon's command line
        _row(14, 13, daemon, 15.0, policy=1),
        _row(15, 13, daemon, 30.0),
    ]
    assert pss_by_process.roles(rows) == {
        11: "main", 13: "fork server", 14: "control process", 15: "loop-closure worker"}


def test_summary_gives_each_peak_and_the_sums_peak(tmp_path: Path) -> None:
    path = tmp_path / "pss.jsonl"
    samples = [(0.0, 70.0, 35.0), (10.0, 90.0, 30.0), (20.0, 80.0, 50.0)]
    path.write_text("".join(json.dumps({"t_s": t, "rows": _tree(m, w)}) + "\n" for t, m, w in samples))
    text = pss_by_process.summary(path)
    assert "main 90.0" in text and "loop-closure worker 50.0" in text
    assert "peak 185.0 MB at 20 s" in text  # 80 + 30 + 25 + 50: the world and the bench are not counted


def test_a_live_process_is_read(tmp_path: Path, capsys) -> None:
    row = pss_by_process._sample(os.getpid())
    assert row is not None and row["pss_kb"] > 0 and row["ppid"] == os.getppid()
    empty = tmp_path / "none.jsonl"
    empty.write_text("")
    assert pss_by_process.main(["--summary", str(empty)]) == 0
    assert "no samples" in capsys.readouterr().out
