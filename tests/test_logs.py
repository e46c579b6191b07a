"""journald priorities: every line on the journal stream carries its ``<N>`` prefix, and only there."""

from __future__ import annotations

import io
import logging
import os
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from mazebot.logs import JournalFormatter, error_line, journal_line, setup_logging, stream_is_journal, syslog_priority


def test_python_levels_map_to_the_syslog_priorities_of_sd_daemon() -> None:
    assert [syslog_priority(level) for level in (50, 45, 40, 30, 25, 20, 10, 5)] == [2, 3, 3, 4, 6, 6, 7, 7]


def test_every_line_of_a_record_carries_the_prefix_tracebacks_included() -> None:
    try:
        raise RuntimeError("lidar gone")
    except RuntimeError:
        record = logging.LogRecord("mazebot.x", logging.ERROR, __file__, 1, "task %s crashed", ("lidar",),
                                   sys.exc_info())
    lines = JournalFormatter("%(levelname)s %(name)s: %(message)s").format(record).split("\n")
    assert lines[0] == "<3>ERROR mazebot.x: task lidar crashed"
    assert len(lines) > 3 and all(line.startswith("<3>") for line in lines)
    assert journal_line(4, "a\nb") == "<4>a\n<4>b"


@pytest.fixture
def pipe() -> Iterator[tuple[io.TextIOWrapper, str]]:
    """A pipe's write end and the ``$JOURNAL_STREAM`` value that names it."""
    read_fd, write_fd = os.pipe()
    stat = os.fstat(write_fd)
    writer = os.fdopen(write_fd, "w")
    try:
        yield writer, f"{stat.st_dev}:{stat.st_ino}"
    finally:
        writer.close()
        os.close(read_fd)


def test_only_the_stream_systemd_named_is_the_journal(pipe: tuple[io.TextIOWrapper, str],
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    writer, value = pipe
    assert stream_is_journal(writer, {"JOURNAL_STREAM": value})
    assert not stream_is_journal(writer, {})
    assert not stream_is_journal(writer, {"JOURNAL_STREAM": "1:2"})  # inherited by a child whose stderr was redirected
    assert not stream_is_journal(writer, {"JOURNAL_STREAM": "garbage"})
    assert not stream_is_journal(io.StringIO(), {"JOURNAL_STREAM": value})
    monkeypatch.setenv("JOURNAL_STREAM", value)
    assert error_line("mazebot: x", writer) == "<3>mazebot: x"
    monkeypatch.delenv("JOURNAL_STREAM")
    assert error_line("mazebot: x", writer) == "mazebot: x"


@pytest.fixture
def root_logger() -> Iterator[logging.Logger]:
    """The root logger, given back afterwards with the handlers and level it had (pytest's own among them)."""
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    try:
        yield root
    finally:
        for handler in root.handlers[:]:
            root.removeHandler(handler)
        for handler in handlers:
            root.addHandler(handler)
        root.setLevel(level)


def test_setup_logging_prefixes_on_the_journal_and_not_elsewhere(
    pipe: tuple[io.TextIOWrapper, str], monkeypatch: pytest.MonkeyPatch, root_logger: logging.Logger
) -> None:
    writer, value = pipe
    monkeypatch.setenv("JOURNAL_STREAM", value)
    setup_logging("info", writer)
    assert isinstance(root_logger.handlers[0].formatter, JournalFormatter)
    plain = io.StringIO()
    setup_logging("info", plain)
    logging.getLogger("mazebot").warning("fault: lidar")
    assert plain.getvalue() == "WARNING mazebot: fault: lidar\n"


def _read_all(fd: int, into: list[bytes]) -> None:
    while chunk := os.read(fd, 65536):
        into.append(chunk)


@pytest.mark.slow
def test_a_daemon_under_systemd_writes_each_line_with_its_priority(tmp_path: Path) -> None:
    """``mazebot run --sim`` as systemd starts it (stderr the journal stream): the generated PIN is a
    warning (<4>), start-up lines are info (<6>), and the fault that ends it (its port is taken:
    exit 69) is an error (<3>), which ``journalctl -p err`` shows."""
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    port = taken.getsockname()[1]
    read_fd, write_fd = os.pipe()
    stat = os.fstat(write_fd)
    env = {**os.environ, "JOURNAL_STREAM": f"{stat.st_dev}:{stat.st_ino}", "XDG_STATE_HOME": str(tmp_path)}
    chunks: list[bytes] = []
    reader = threading.Thread(target=_read_all, args=(read_fd, chunks))
    reader.start()
    try:
        proc = subprocess.run([sys.executable, "-m", "mazebot", "run", "--sim", "--host", "127.0.0.1", "--port",
                               str(port), "--log-level", "info"], stderr=write_fd, stdout=subprocess.DEVNULL,
                              env=env, timeout=60, check=False)
    finally:
        os.close(write_fd)
        reader.join(timeout=10)
        os.close(read_fd)
        taken.close()
    lines = b"".join(chunks).decode().splitlines()
    assert proc.returncode == 69
    assert lines and all(line[:3] in ("<3>", "<4>", "<6>", "<7>") for line in lines), lines
    assert any(line.startswith("<4>WARNING") and "control PIN" in line for line in lines)
    assert lines[-1].startswith("<3>mazebot: web server cannot listen on 127.0.0.1:")
