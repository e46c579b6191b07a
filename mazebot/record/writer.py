"""The MCAP writer: a bounded queue in front of a thread that encodes and writes.

The daemon's event loop must never wait for a disk (an SD card can stall for hundreds
of milliseconds), so :meth:`McapRecorder.put` only appends ``(topic, time, object)`` to a
bounded queue and returns; a writer thread turns each object into JSON
(:mod:`mazebot.record.schemas`) and hands it to the ``mcap`` library's ``Writer``. When
the queue is full the new message is dropped and counted (``dropped``, shown in
``/api/status`` through the shared state), never silently lost and never waited for.

The queue is a ``collections.deque`` that nobody is woken for: the writer thread drains
it in batches, every ``flush_period_s`` or as soon as it is half full. A
``queue.Queue`` woke the thread for every one of the ~100 messages a second, and each
wake-up took the interpreter lock from the event loop (a forced switch); that alone cost
more CPU than encoding the messages (docs/benchmarks-history.md, "Recording overhead").

Size cap and rotation: when the current file reaches ``max_bytes`` it is finished (its
summary and index written, so it is a complete MCAP file on its own) and the next one
begins: ``FILE.mcap``, ``FILE.001.mcap``, ``FILE.002.mcap`` ...; only the newest
``keep_files`` are kept. Every file carries the schemas, channels and the metadata
record ``mazebot`` (software version, the effective configuration as JSON) that replay
needs.

Example::

    rec = McapRecorder(Path("run.mcap"), metadata={"config": config.model_dump_json()})
    rec.start()
    rec.put("/mazebot/encoders", time_ns, {"time_s": 1.0, "left_ticks": 3, ...})
    rec.close()          # drains the queue and finishes the file
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

from mcap.writer import CompressionType, Writer

from mazebot import __version__
from mazebot.cpu_budget import PartMeter
from mazebot.record.schemas import CHANNELS, MESSAGE_ENCODING, SCHEMA_ENCODING, SCHEMAS, encode

log = logging.getLogger(__name__)

PROFILE = ""  # no ROS profile: JSON channels with JSON schemas
METADATA_NAME = "mazebot"
STATS_NAME = "mazebot_stats"
#: Message bytes between two looks at the file's size (the size cap is met to within a chunk).
SIZE_CHECK_BYTES = 64 * 1024
_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


@dataclass
class RecorderStats:
    """Counters of one recorder; read from the loop, written by the writer thread (plain ints)."""

    queued: int = 0
    written: int = 0
    batches: int = 0  # times the writer thread woke up and drained the queue
    dropped: int = 0  # the queue was full: the message was not recorded
    files: int = 0
    bytes_written: int = 0  # in finished files plus the current one's flushed part
    error: str | None = None  # the writer thread failed (disk full ...): nothing more is recorded
    writer_cpu_s: float = 0.0  # CPU time of the writer thread so far (encoding, compression, writes)


def rotated_path(path: Path, index: int) -> Path:
    """``FILE.mcap`` for index 0, ``FILE.001.mcap`` for 1, and so on."""
    if index == 0:
        return path
    return path.with_name(f"{path.stem}.{index:03d}{path.suffix}")


class McapRecorder:
    """Records messages to MCAP from any thread without blocking the caller."""

    def __init__(
        self,
        path: Path,
        *,
        metadata: dict[str, str] | None = None,
        max_bytes: int = 512 * 1024 * 1024,
        keep_files: int = 4,
        queue_messages: int = 2000,
        compression: str = "zstd",
        flush_period_s: float = 0.25,
    ) -> None:
        self.path = Path(path)
        self.metadata = {"version": __version__, **(metadata or {})}
        self.max_bytes = int(max_bytes)
        self.keep_files = int(keep_files)
        self.compression = _COMPRESSION[compression]
        self.stats = RecorderStats()
        #: CPU time of each batch the writer thread writes (the daemon's budget: :mod:`mazebot.cpu_budget`)
        self.meter = PartMeter("recording")
        self.queue_messages = int(queue_messages)
        self.flush_period_s = float(flush_period_s)
        # appended by the caller, popped by the writer thread: both atomic under the GIL
        self._queue: deque[tuple[str, int, Any]] = deque()
        self._wake = threading.Event()  # set when the queue is half full, and to stop
        self._stopping = False
        self._thread: threading.Thread | None = None
        self._stream: BinaryIO | None = None
        self._writer: Writer | None = None
        self._channel_ids: dict[str, int] = {}
        self._sequence = 0
        self._unchecked_bytes = 0  # message bytes since the file size was last looked at
        self._index = 0
        self._closed = False

    # -- the caller's side ---------------------------------------------------------------

    def start(self) -> None:
        """Open the first file (errors surface here, in the caller) and start the writer thread."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._open_file()
        self._thread = threading.Thread(target=self._run, name="mazebot-recorder", daemon=True)
        self._thread.start()

    def put(self, topic: str, log_time_ns: int, message: Any) -> bool:
        """Queue one message; False (and counted) when the queue is full or the writer stopped."""
        if self._closed or self.stats.error is not None:
            self.stats.dropped += 1
            return False
        waiting = len(self._queue)
        if waiting >= self.queue_messages:
            self.stats.dropped += 1
            return False
        self._queue.append((topic, max(0, int(log_time_ns)), message))
        self.stats.queued += 1
        if waiting == self.queue_messages // 2:  # a burst: drain now rather than at the next period
            self._wake.set()
        return True

    def close(self) -> None:
        """Write what is queued, finish the file and stop the thread (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if self._thread is not None:
            self._stopping = True
            self._wake.set()
            self._thread.join()
        else:
            self._finish_file()

    def __enter__(self) -> McapRecorder:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the writer thread ---------------------------------------------------------------

    def _run(self) -> None:
        try:
            while True:
                self._wake.wait(self.flush_period_s)
                self._wake.clear()
                stopping = self._stopping  # read before draining: nothing queued before close is lost
                self._drain()
                if stopping:
                    break
        except Exception as exc:  # disk full, unwritable: stop recording, never the robot
            self.stats.error = f"{type(exc).__name__}: {exc}"
            log.error("recording to %s stopped: %s", self.path, self.stats.error)
        finally:
            self.stats.dropped += len(self._queue)  # left behind by a failure: counted, not silent
            self._queue.clear()
            with contextlib.suppress(Exception):
                self._finish_file()
            self.stats.writer_cpu_s = time.thread_time()

    def _drain(self) -> None:
        """Write everything queued, oldest first."""
        pending = self._queue
        if not pending:
            return
        self.stats.batches += 1
        with self.meter.measure():
            while pending:
                topic, log_time_ns, message = pending.popleft()
                self._write(topic, log_time_ns, message)
        self.stats.writer_cpu_s = time.thread_time()

    def _write(self, topic: str, log_time_ns: int, message: Any) -> None:
        assert self._writer is not None and self._stream is not None
        data = encode(topic, message, log_time_ns)
        self._writer.add_message(
            channel_id=self._channel_ids[topic],
            log_time=log_time_ns,
            publish_time=log_time_ns,
            data=data,
            sequence=self._sequence,
        )
        self._sequence += 1
        self.stats.written += 1
        # the file grows a chunk at a time (the mcap writer buffers ~1 MB), so asking its size
        # (a system call) after every message is wasted; every SIZE_CHECK_BYTES is enough
        self._unchecked_bytes += len(data)
        if self._unchecked_bytes < SIZE_CHECK_BYTES:
            return
        self._unchecked_bytes = 0
        if self._stream.tell() >= self.max_bytes:
            self._finish_file()
            self._index += 1
            self._open_file()

    def _open_file(self) -> None:
        path = rotated_path(self.path, self._index)
        self._stream = open(path, "wb")  # noqa: SIM115 - closed in _finish_file
        writer = Writer(self._stream, compression=self.compression)
        writer.start(profile=PROFILE, library=f"mazebot {__version__}")
        schema_ids = {name: writer.register_schema(name, SCHEMA_ENCODING, data) for name, data in SCHEMAS.items()}
        self._channel_ids = {
            topic: writer.register_channel(topic, MESSAGE_ENCODING, schema_ids[channel.schema])
            for topic, channel in CHANNELS.items()
        }
        writer.add_metadata(METADATA_NAME, {**self.metadata, "file_index": str(self._index)})
        self._writer = writer
        self.stats.files += 1
        stale = self._index - self.keep_files
        if stale >= 0:
            rotated_path(self.path, stale).unlink(missing_ok=True)

    def _finish_file(self) -> None:
        if self._writer is None or self._stream is None:
            return
        writer, stream = self._writer, self._stream
        self._writer = self._stream = None
        # the drops so far, so a replay can say whether its input is complete
        writer.add_metadata(STATS_NAME, {"written": str(self.stats.written), "dropped": str(self.stats.dropped)})
        writer.finish()
        stream.flush()
        self.stats.bytes_written += stream.tell()
        stream.close()
