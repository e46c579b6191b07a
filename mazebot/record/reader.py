"""Reading a mazebot recording back with the ``mcap`` library.

Messages come back in the order they were written (``log_time_order=False``), which is
the order the daemon's event loop produced them: a SLAM step always follows the scan and
the encoder readings it used, whatever their time stamps say.

A file that is not MCAP, or an MCAP file mazebot did not write, is a
:class:`RecordingError` (one line naming the file; exit code 2, like every bad input file).
"""

from __future__ import annotations

import json
import os
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from mcap.reader import make_reader

from mazebot.errors import UsageError
from mazebot.record.writer import METADATA_NAME, STATS_NAME


class RecordingError(UsageError):
    """A recording cannot be read: missing, not MCAP, truncated, or not written by mazebot."""




@dataclass(frozen=True)
class RecordedMessage:
    topic: str
    schema: str
    log_time_ns: int
    data: dict[str, Any]


class Recording:
    """One MCAP file written by :class:`mazebot.record.writer.McapRecorder`.

    Example::

        rec = Recording.open("run.mcap")
        rec.metadata["config"]            # the effective configuration, JSON
        for msg in rec.messages(["/mazebot/scan_raw"]):
            ...
    """

    def __init__(self, path: Path, metadata: dict[str, str], counts: dict[str, int], schemas: dict[str, str]) -> None:
        self.path = path
        self.metadata = metadata
        self.message_counts = counts  # by topic, from the summary
        self.schemas = schemas  # schema name by topic
        self.recorder_stats: dict[str, str] = {}  # the recorder's final counters ("written", "dropped")

    @classmethod
    def open(cls, path: str | os.PathLike[str]) -> Recording:
        path = Path(path)
        try:
            with path.open("rb") as stream:
                reader = make_reader(stream)
                reader.get_header()
                summary = reader.get_summary()
                metadata: dict[str, str] = {}
                recorder_stats: dict[str, str] = {}
                for record in reader.iter_metadata():
                    if record.name == METADATA_NAME:
                        metadata = dict(record.metadata)
                    elif record.name == STATS_NAME:
                        recorder_stats = dict(record.metadata)
        except FileNotFoundError:
            raise RecordingError(f"recording {path} not found") from None
        except IsADirectoryError:
            raise RecordingError(f"recording {path} is a directory; expected an .mcap file") from None
        except OSError as exc:
            raise RecordingError(f"recording {path} cannot be read ({exc.strerror or exc})") from None
        except (McapError, ValueError, EOFError, KeyError, struct.error) as exc:  # struct: a file shorter than a record
            raise RecordingError(f"{path} is not a readable MCAP file ({type(exc).__name__}: {exc})") from None
        if summary is None:
            raise RecordingError(f"{path} has no MCAP summary (the recording was cut off); it cannot be replayed")
        if not metadata:
            raise RecordingError(f"{path} is an MCAP file without mazebot's metadata; it was not recorded by mazebot")
        counts: dict[str, int] = {}
        schemas: dict[str, str] = {}
        stats = summary.statistics
        for channel_id, channel in summary.channels.items():
            counts[channel.topic] = stats.channel_message_counts.get(channel_id, 0) if stats else 0
            schema = summary.schemas.get(channel.schema_id)
            schemas[channel.topic] = schema.name if schema else ""
        recording = cls(path, metadata, counts, schemas)
        recording.recorder_stats = recorder_stats
        return recording

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[RecordedMessage]:
        """The messages (of ``topics``) in the order they were written, JSON decoded."""
        wanted = None if topics is None else list(topics)
        try:
            with self.path.open("rb") as stream:
                reader = make_reader(stream)
                for schema, channel, message in reader.iter_messages(topics=wanted, log_time_order=False):
                    yield RecordedMessage(
                        channel.topic, schema.name if schema else "", message.log_time, json.loads(message.data)
                    )
        except (McapError, ValueError, EOFError, struct.error) as exc:
            raise RecordingError(f"{self.path}: damaged MCAP data ({type(exc).__name__}: {exc})") from None
