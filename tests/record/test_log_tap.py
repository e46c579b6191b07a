"""The recording's /log channel takes the daemon's log lines, but never one carrying a secret."""

from __future__ import annotations

import logging

from mazebot.tasks.record_task import LogTap


class _Recorder:
    def __init__(self) -> None:
        self.entries: list[tuple] = []

    def put(self, topic: str, time_ns: int, entry: tuple) -> None:
        self.entries.append((topic, entry))


class _Tap:
    def __init__(self) -> None:
        self.recorder = _Recorder()


def test_the_first_start_pin_notice_is_not_recorded_but_other_lines_are() -> None:
    tap = _Tap()
    handler = LogTap(tap)  # type: ignore[arg-type]
    logger = logging.getLogger("mazebot.web.server")
    logger.addHandler(handler)
    try:
        logger.warning("control PIN for start/stop: %s (generated once)", "123456", extra={"secret": True})
        logger.warning("lidar data flows again")
    finally:
        logger.removeHandler(handler)
    messages = [entry[2] for topic, entry in tap.recorder.entries if topic == "/log"]
    assert messages == ["lidar data flows again"]
    assert not any("123456" in str(entry) for _, entry in tap.recorder.entries)
