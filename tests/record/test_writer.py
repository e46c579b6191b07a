"""The MCAP writer: a full queue drops and counts (and never waits), the size cap rotates
complete files, and what was queued before ``close`` is all in the file; read back with
the ``mcap`` library's own reader."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from mcap.reader import make_reader

from mazebot.io.scan import Scan
from mazebot.record.reader import Recording
from mazebot.record.writer import McapRecorder, rotated_path

T0_NS = 1_700_000_000_000_000_000


def _scan(i: int, n: int = 360) -> Scan:
    angle = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    rng = np.random.default_rng(i)
    return Scan(angle, rng.uniform(0.2, 3.0, n), np.full(n, 40, np.uint8), i + np.arange(n) / n, np.ones(n, bool), i)


def _encoders(i: int) -> dict[str, float | int]:
    return {"time_s": i * 0.02, "left_ticks": 3 * i, "right_ticks": 4 * i, "invalid_transitions": 0}


def _messages(path: Path) -> list[tuple[str, int, int]]:
    """(topic, sequence, log time) of every message, read with the mcap library."""
    with path.open("rb") as stream:
        found = make_reader(stream).iter_messages(log_time_order=False)
        return [(channel.topic, msg.sequence, msg.log_time) for _, channel, msg in found]


def test_a_full_queue_drops_and_counts_without_waiting(tmp_path: Path) -> None:
    recorder = McapRecorder(tmp_path / "run.mcap", queue_messages=10)
    # the writer thread is not started: nothing drains the queue, and a put that waited would hang here
    accepted = [recorder.put("/mazebot/encoders", T0_NS + i, _encoders(i)) for i in range(25)]
    assert accepted == [True] * 10 + [False] * 15
    assert recorder.stats.dropped == 15 and recorder.stats.queued == 10
    recorder.start()
    recorder.close()
    messages = _messages(tmp_path / "run.mcap")
    assert [seq for _, seq, _ in messages] == list(range(10))  # the first ten, in order
    rec = Recording.open(tmp_path / "run.mcap")
    assert rec.message_counts["/mazebot/encoders"] == 10
    assert rec.recorder_stats == {"written": "10", "dropped": "15"}
    assert recorder.put("/mazebot/encoders", T0_NS, _encoders(0)) is False  # closed: counted too
    assert recorder.stats.dropped == 16


def test_everything_queued_before_close_is_written(tmp_path: Path) -> None:
    with McapRecorder(tmp_path / "run.mcap", flush_period_s=60.0) as recorder:  # no timed flush at all
        for i in range(300):
            assert recorder.put("/mazebot/encoders", T0_NS + i, _encoders(i))
            if i % 30 == 0:
                assert recorder.put("/scan", T0_NS + i, _scan(i))
    counts = Recording.open(tmp_path / "run.mcap").message_counts
    assert counts["/mazebot/encoders"] == 300 and counts["/scan"] == 10
    assert recorder.stats.dropped == 0 and recorder.stats.written == 310
    assert recorder.stats.batches >= 1 and recorder.stats.writer_cpu_s > 0


def test_the_size_cap_rotates_complete_files_and_keeps_the_newest(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    recorder = McapRecorder(path, max_bytes=200_000, keep_files=2, compression="none", queue_messages=100_000)
    recorder.start()
    total = 600
    for i in range(total):
        recorder.put("/mazebot/scan_raw", T0_NS + i * 180_000_000, _scan(i))
    recorder.close()
    assert recorder.stats.dropped == 0 and recorder.stats.written == total
    files = recorder.stats.files
    assert files >= 4  # ~13 KB a revolution: several files of 200 KB (and a 1 MB mcap chunk)
    kept = [rotated_path(path, k) for k in range(files)]
    assert [p.exists() for p in kept] == [False] * (files - 2) + [True, True]
    assert kept[-2].name == f"run.{files - 2:03d}.mcap"
    sequences: list[int] = []
    for k, p in zip(range(files - 2, files), kept[-2:], strict=True):
        rec = Recording.open(p)  # each a complete MCAP file with its summary and mazebot's metadata
        assert rec.metadata["file_index"] == str(k) and "version" in rec.metadata
        assert rec.schemas["/mazebot/scan_raw"] == "mazebot.Scan"
        sequences += [seq for _, seq, _ in _messages(p)]
    assert sequences == list(range(sequences[0], total))  # the newest messages, none missing
    assert kept[-2].stat().st_size >= 200_000
