"""What ``mazebot run`` adds around the robot: a run folder, a recording, a resumed map.

``run_daemon`` takes one optional :class:`RunSession` and calls it at three points:
:meth:`RunSession.open` right after the devices are open (the recording taps go in
front of them), :meth:`RunSession.make_slam` for the SLAM task's Slam, and
:meth:`RunSession.start_tasks` once the core tasks run. Without a session (tests, the
benchmark) the daemon records and saves nothing.

Example::

    session = RunSession.from_options(config, record="run.mcap", resume="latest")
    await run_daemon(config, builder, session=session)
"""

from __future__ import annotations

import json
import logging
from contextlib import AsyncExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mazebot.clock import Clock
from mazebot.config import Config
from mazebot.errors import UsageError
from mazebot.hardware import Hardware
from mazebot.persist.runs import find_run, new_run_dir, runs_root
from mazebot.state import SharedState

if TYPE_CHECKING:  # the SLAM (numpy, scipy) is imported when it is built, after the page is served

    from mazebot.persist.snapshot import SavedRun
    from mazebot.slam.slam import Slam, SlamParams

log = logging.getLogger(__name__)

RECORDING_NAME = "recording.mcap"


@dataclass
class RunSession:
    """The options of one run and what they opened."""

    run_dir: Path | None = None  # where the run is saved (None: not saved)
    record_path: Path | None = None  # the MCAP file (None: not recorded)
    resume: SavedRun | None = None  # the saved run to continue
    tap: Any = None  # mazebot.tasks.record_task.RecordingTap once open
    meta: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_options(
        cls, config: Config, *, record: str | None = None, resume: str | None = None, persist: bool | None = None
    ) -> RunSession:
        """Resolve ``--record``/``--resume`` and the config switches into paths (no file is written yet)."""
        root = runs_root(config.daemon.state_dir)
        saved: SavedRun | None = None
        if resume:
            from mazebot.persist.snapshot import load_run

            saved = load_run(find_run(root, resume))
        persist = config.persist.enabled if persist is None else persist
        run_dir = new_run_dir(root) if persist else None
        record_path: Path | None = None
        if record:
            record_path = Path(record).expanduser()
        elif config.record.enabled:
            if config.record.path:
                record_path = Path(config.record.path).expanduser()
            elif run_dir is not None:
                record_path = run_dir / RECORDING_NAME
            else:
                raise UsageError("[record] enabled needs [record] path when [persist] enabled is false")
        if record_path is not None and record_path.suffix != ".mcap":
            raise UsageError(f"--record expects a file name ending in .mcap, got {str(record_path)!r}")
        meta = {"resumed_from": str(saved.path) if saved else None}
        return cls(run_dir=run_dir, record_path=record_path, resume=saved, meta=meta)

    def open(
        self, config: Config, clock: Clock, state: SharedState, hardware: Hardware, stack: AsyncExitStack
    ) -> Hardware:
        """Start the recorder (if any) and return the hardware with its recording taps."""
        if self.record_path is None:
            return hardware
        from mazebot.record.writer import McapRecorder
        from mazebot.tasks import record_task

        rc = config.record
        recorder = McapRecorder(
            self.record_path,
            metadata={
                "config": config.model_dump_json(),
                "hardware": getattr(hardware, "description", ""),
                "run_dir": str(self.run_dir or ""),
                "resumed_from": str(self.resume.path) if self.resume else "",
            },
            max_bytes=int(rc.max_file_mb * 1024 * 1024),
            keep_files=rc.keep_files,
            queue_messages=rc.queue_messages,
            compression=rc.compression,
        )
        try:
            recorder.start()
        except OSError as exc:
            raise UsageError(f"cannot write the recording {self.record_path}: {exc.strerror or exc}") from None
        state.cpu.adopt(recorder.meter)
        tap = record_task.RecordingTap(recorder, clock)
        handler = record_task.LogTap(tap)
        logging.getLogger("mazebot").addHandler(handler)

        record_encoders = record_task.encoder_recorder(tap)
        state.odometry_listeners += (record_encoders,)

        def close() -> None:
            logging.getLogger("mazebot").removeHandler(handler)
            state.odometry_listeners = tuple(f for f in state.odometry_listeners if f is not record_encoders)
            recorder.close()
            record_task.publish_stats(state, recorder)
            stats = recorder.stats
            log.info("recorded %d messages to %s (%d dropped)", stats.written, self.record_path, stats.dropped)

        stack.callback(close)
        self.tap = tap
        record_task.publish_stats(state, recorder)
        return record_task.tap_hardware(hardware, tap)

    def make_slam(self, params: SlamParams) -> Slam:
        """The daemon's Slam: resumed from the saved run, or fresh; watched by the recorder."""
        from mazebot.slam.slam import Slam

        if self.resume is not None:
            from mazebot.persist.resume import resume_slam

            slam = resume_slam(params, self.resume, background=True, record_trajectory=False)
        else:
            slam = Slam(params, background=True, record_trajectory=False)
        if self.tap is not None:
            self.tap.watch_slam(slam)
        return slam

    def start_tasks(self, config: Config, clock: Clock, state: SharedState, supervisor: Any, slam: Any) -> None:
        """The recording and saving tasks."""
        from mazebot.tasks import persist_task, record_task

        if self.tap is not None:
            rc = config.record
            mount_xy_m = config.lidar.mount_xy_m
            supervisor.start(
                "record", lambda: record_task.run(state, self.tap, rc.pose_hz, rc.map_period_s, mount_xy_m)
            )
        if self.run_dir is not None:
            run_dir = self.run_dir
            config_json = json.loads(config.model_dump_json())

            def extra() -> dict[str, Any]:
                return {
                    **self.meta,
                    "run": run_dir.name,
                    "recording": str(self.record_path) if self.record_path else None,
                    "run_state": state.run_state.value,
                    "config": config_json,
                }

            supervisor.start(
                "persist", lambda: persist_task.run(state, slam, run_dir, clock, config.persist.save_period_s, extra)
            )
            log.info("this run is saved in %s", run_dir)
