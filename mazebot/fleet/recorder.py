"""``mazebot watch --record DIR``: each robot's Zenoh stream to an MCAP file of its own.

Written with the daemon's own recorder (:class:`mazebot.record.writer.McapRecorder`, a
thread behind a bounded queue) and channels (:mod:`mazebot.record.schemas`), so the file
opens in Foxglove like a robot's recording: ``/scan`` and ``/mazebot/scan_raw`` (every
revolution the robot published), ``/pose``, ``/map`` (every ``map_period_s`` when it
changed), ``/mazebot/run_state``. It holds what the robot published, not its encoder
readings, so ``mazebot replay`` cannot run it through SLAM again.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from mazebot.fleet.watcher import RobotMirror
from mazebot.record.schemas import scan_from_json
from mazebot.record.writer import McapRecorder


class FleetRecorder:
    """A Fleet listener that records the robots named in ``only`` (all when empty) to ``folder/<name>.mcap``."""

    def __init__(self, folder: Path, only: frozenset[str] = frozenset(), map_period_s: float = 2.0) -> None:
        self.folder = Path(folder)
        self.only = only
        self.map_period_s = map_period_s
        self.recorders: dict[str, McapRecorder] = {}
        self._map_sent: dict[str, tuple[float, int]] = {}

    def _recorder(self, name: str) -> McapRecorder | None:
        if self.only and name not in self.only:
            return None
        rec = self.recorders.get(name)
        if rec is None:
            rec = self.recorders[name] = McapRecorder(self.folder / f"{name}.mcap", metadata={"robot": name})
            rec.start()
        return rec

    def __call__(self, name: str, topic: str, message: Any) -> None:
        rec = self._recorder(name)
        if rec is None:
            return
        now_ns = time.time_ns()
        t_ns = round(message["t_ms"] * 1e6) if isinstance(message, dict) and "t_ms" in message else now_ns
        if topic == "scan":
            scan = scan_from_json(message)
            rec.put("/scan", t_ns, scan)
            rec.put("/mazebot/scan_raw", t_ns, scan)
        elif topic == "pose":
            rec.put("/pose", t_ns, (message["x_m"], message["y_m"], message["theta_rad"]))
        elif topic == "state":
            rec.put("/mazebot/run_state", t_ns, message)
        elif topic == "packet" and isinstance(message, RobotMirror):
            self._map(rec, message, now_ns)

    def _map(self, rec: McapRecorder, robot: RobotMirror, now_ns: int) -> None:
        grid = robot.grid
        if grid is None:
            return
        last = self._map_sent.get(robot.name)
        now_s = time.monotonic()
        if last is not None and now_s - last[0] < self.map_period_s:
            return
        three_state = robot.three_state()
        assert three_state is not None
        self._map_sent[robot.name] = (now_s, robot.seq)
        rec.put("/map", now_ns, (three_state, grid.resolution_m, grid.origin_m))

    def close(self) -> None:
        for rec in self.recorders.values():
            rec.close()
        self.recorders.clear()
