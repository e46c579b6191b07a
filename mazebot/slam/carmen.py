"""CARMEN laser logs: ``FLASER``, ``RLASER``, ``ROBOTLASER1`` and ``ODOM`` lines.

The format of the CARMEN robot toolkit's ``logger`` (carmen/src/logger, "CARMEN Logfile"
header), one message per line, fields separated by blanks::

    FLASER num_readings [range_readings] x y theta odom_x odom_y odom_theta
           ipc_timestamp ipc_hostname logger_timestamp
    ROBOTLASER1 laser_type start_angle field_of_view angular_resolution maximum_range
           accuracy remission_mode num_readings [range_readings] num_remissions
           [remission values] laser_pose_x laser_pose_y laser_pose_theta robot_pose_x
           robot_pose_y robot_pose_theta laser_tv laser_rv forward_safety_dist
           side_safety_dist turn_axis ipc_timestamp ipc_hostname logger_timestamp
    ODOM x y theta tv rv accel ipc_timestamp ipc_hostname logger_timestamp

Old-style ``FLASER``/``RLASER`` lines do not carry their geometry: the front laser is a
SICK LMS covering 180° from the right (−90°) counter-clockwise, ``fov / num_readings``
apart (1° for the 180 beams of the Intel lab log), or ``fov / (num_readings − 1)`` when
the count is odd: a SICK LMS reports 181 beams at 1° or 361 at 0.5° when it includes both
ends of its 180° (the Seattle log's 361 beams: read as 180°/361 apart, every scan's
points sit up to 0.5° off towards the right, and the consecutive scans placed at the
corrected poses agree better read at 0.5°, 17.20 against 17.46 mm median distance
between neighbouring points). Their pose ``x y theta`` is the
laser's pose; in a ``*.gfs.log`` it is the pose GMapping corrected, which is why the
Intel log serves as ground truth for scan matching. Other messages (``PARAM``,
``NEFF``, ``#`` comments, ...) are skipped.
"""

from __future__ import annotations

import gzip
import math
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from mazebot.errors import UsageError
from mazebot.io.scan import Scan


class CarmenLogError(UsageError):
    """A CARMEN log is missing or has a malformed line; the message names the file and line."""


@dataclass(frozen=True)
class LaserRecord:
    """One laser message: beams in the laser frame (CCW, 0 ahead) and the poses it carries.

    ``pose`` (3,) is the laser's pose ``(x_m, y_m, theta_rad)`` (corrected in GMapping
    logs), ``odom_pose`` (3,) the raw odometry. Ranges at or beyond ``max_range_m`` are
    no-return beams.
    """

    angle_rad: np.ndarray
    range_m: np.ndarray
    pose: np.ndarray
    odom_pose: np.ndarray
    timestamp_s: float
    max_range_m: float
    line_number: int
    kind: str = "FLASER"

    def points_xy(self, max_range_m: float | None = None) -> np.ndarray:
        """Returns (N, 2) in the laser frame, metres, for beams closer than ``max_range_m``."""
        limit = self.max_range_m if max_range_m is None else min(max_range_m, self.max_range_m)
        ok = (self.range_m > 0) & (self.range_m < limit)
        r, a = self.range_m[ok], self.angle_rad[ok]
        return np.column_stack((r * np.cos(a), r * np.sin(a)))

    def to_scan(self) -> Scan:
        """The message as a :class:`~mazebot.io.scan.Scan` (all samples at the message time).

        Samples at or beyond the sensor's maximum (a SICK LMS reports 81.83 m when no echo
        came back) are not ``valid``: a missing echo comes from glass, a black or glancing
        surface as well as from open space, so it says nothing about how far the space is
        free, and as a no-return beam of :func:`mazebot.slam.preprocess.prepare_scan` it
        would clear a fan of free cells through walls and out of the building (2.5 % of
        the Intel log's beams). Returns beyond ``prepare_scan``'s ``max_range_m`` still
        become no-return beams that clear space up to their hit.
        """
        n = self.range_m.shape[0]
        return Scan(
            angle_rad=self.angle_rad.copy(),
            range_m=self.range_m.copy(),
            quality=np.full(n, 47, dtype=np.uint8),
            time_s=np.full(n, self.timestamp_s),
            valid=(self.range_m > 0) & (self.range_m < self.max_range_m),
        )


@dataclass(frozen=True)
class OdometryRecord:
    """One ``ODOM`` message: pose (3,), translational/rotational velocity, acceleration."""

    pose: np.ndarray
    tv_mps: float
    rv_radps: float
    accel_mps2: float
    timestamp_s: float
    line_number: int


@dataclass
class CarmenLog:
    """The laser and odometry messages of a log, in file order."""

    lasers: list[LaserRecord] = field(default_factory=list)
    odometry: list[OdometryRecord] = field(default_factory=list)


def parse_carmen(
    lines: Iterable[str],
    source: str = "<text>",
    flaser_fov_rad: float = math.pi,
    flaser_max_range_m: float = 81.0,
) -> CarmenLog:
    """Parse the lines of a CARMEN log.

    ``flaser_fov_rad`` and ``flaser_max_range_m`` describe the laser behind old-style
    ``FLASER``/``RLASER`` lines (a SICK LMS by default: 180°, no return reported as
    81.83 m). A malformed line raises :class:`CarmenLogError` naming ``source`` and
    the line number.
    """
    log = CarmenLog()
    for number, line in enumerate(lines, start=1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        kind = tokens[0]
        try:
            if kind in ("FLASER", "RLASER"):
                log.lasers.append(_parse_flaser(tokens, number, flaser_fov_rad, flaser_max_range_m))
            elif kind == "ROBOTLASER1":
                log.lasers.append(_parse_robotlaser(tokens, number))
            elif kind == "ODOM":
                log.odometry.append(_parse_odom(tokens, number))
        except (ValueError, IndexError) as error:
            raise CarmenLogError(f"{source} line {number}: bad {kind} message ({error})") from None
    return with_no_echo_code(log, flaser_max_range_m)


#: a log's largest range is its code for a beam without an echo when at least this share of its
#: old-style laser messages hold it (and :data:`NO_ECHO_MIN_SCANS` of them): a surface at exactly the
#: log's farthest distance is seen from one place, a code from everywhere (ACES: 50.0 m in 239 of
#: its 440 scans, the reading below it once)
NO_ECHO_SCAN_SHARE = 0.01
NO_ECHO_MIN_SCANS = 3


def no_echo_code(records: list[LaserRecord]) -> float | None:
    """The range ``records`` write for a beam without an echo, if they write one: their largest, held widely.

    A SICK LMS reports its maximum (81.83 m; 81.87-81.91 m on the Seattle and Freiburg 101
    logs), but a log may have been written with another (the ACES log's 50.0 m) and a
    short-range laser has its own (a Hokuyo URG's 4 or 5.6 m). Taken as a return, the code
    is a wall at that distance in every direction without an echo. None when the largest
    range is not repeated over :data:`NO_ECHO_SCAN_SHARE` of the messages.
    """
    maxima = np.array([float(np.max(r.range_m)) for r in records if r.range_m.size])
    if maxima.size == 0:
        return None
    largest = float(np.max(maxima))
    holding = int(np.count_nonzero(maxima == largest))
    return largest if holding >= max(NO_ECHO_MIN_SCANS, NO_ECHO_SCAN_SHARE * maxima.size) else None


def with_no_echo_code(log: CarmenLog, flaser_max_range_m: float) -> CarmenLog:
    """``log`` with its old-style laser messages' maximum range lowered to the code they use, if lower.

    ``FLASER``/``RLASER`` lines carry no maximum range; the default (a SICK's 81 m) holds
    for the logs a SICK wrote, and the log's own code (:func:`no_echo_code`) for those written
    with another. ``ROBOTLASER1`` messages carry theirs in their header.
    """
    for kind in ("FLASER", "RLASER"):
        records = [r for r in log.lasers if r.kind == kind]
        code = no_echo_code(records)
        if code is None or code >= flaser_max_range_m:
            continue
        log.lasers = [replace(r, max_range_m=code) if r.kind == kind else r for r in log.lasers]
    return log


def one_laser(log: CarmenLog) -> CarmenLog:
    """The log with the messages of one laser only: the front one's, as ``ROBOTLASER1`` if it has them.

    A robot with a front and a rear laser logs both (``FLASER`` and ``RLASER``), and a
    converted log may hold the front laser twice (``ROBOTLASER1`` and ``FLASER``). Taken
    together they would be one sensor seen from two places, or each scan twice; the SLAM
    tracks one laser. ``ROBOTLASER1`` carries its own geometry and the laser's mounting,
    so it wins over ``FLASER``; ``RLASER`` is used only when the log has nothing else.
    """
    for kind in ("ROBOTLASER1", "FLASER", "RLASER"):
        chosen = [r for r in log.lasers if r.kind == kind]
        if chosen:
            return CarmenLog(lasers=chosen, odometry=log.odometry)
    return log


#: The first two bytes of every gzip member (RFC 1952, section 2.3.1).
GZIP_MAGIC = b"\x1f\x8b"


def read_carmen(path: str | Path, **kwargs: float) -> CarmenLog:
    """Read a CARMEN log file, plain or gzip-compressed; see :func:`parse_carmen`.

    A log is gzip when its name ends in ``.gz`` or its first bytes are gzip's magic
    number (the Radish logs are distributed as ``*.log.gz``).
    """
    path = Path(path)
    try:
        with path.open("rb") as raw:
            compressed = path.suffix == ".gz" or raw.read(2) == GZIP_MAGIC
        if compressed:
            with gzip.open(path, "rt", encoding="utf-8", errors="replace") as f:
                return parse_carmen(f, source=str(path), **kwargs)
        with path.open(encoding="utf-8", errors="replace") as f:
            return parse_carmen(f, source=str(path), **kwargs)
    except FileNotFoundError:
        raise CarmenLogError(f"CARMEN log {path} not found") from None
    except (OSError, EOFError) as error:  # gzip.BadGzipFile is an OSError; a cut-off member an EOFError
        raise CarmenLogError(f"CARMEN log {path} cannot be read ({error})") from None


def _floats(tokens: list[str], start: int, count: int, what: str) -> np.ndarray:
    if start + count > len(tokens):
        raise ValueError(f"expected {count} {what} from field {start}, the line has {len(tokens)} fields")
    values = np.array([float(t) for t in tokens[start : start + count]])
    if not np.all(np.isfinite(values)):
        raise ValueError(f"{what} must be finite numbers")
    return values


def _count(tokens: list[str], index: int, what: str) -> int:
    n = int(tokens[index])
    if n < 0:
        raise ValueError(f"{what} must not be negative, got {n}")
    return n


def _parse_flaser(tokens: list[str], number: int, fov_rad: float, max_range_m: float) -> LaserRecord:
    n = _count(tokens, 1, "num_readings")
    expected = 2 + n + 6 + 3
    if len(tokens) != expected:
        raise ValueError(f"{n} readings need {expected} fields, found {len(tokens)}")
    ranges = _floats(tokens, 2, n, "ranges")
    poses = _floats(tokens, 2 + n, 6, "poses")
    timestamp = float(tokens[2 + n + 6])
    spans = n - 1 if n % 2 == 1 and n > 1 else n  # an odd count includes both ends of the field of view
    angles = -fov_rad / 2.0 + np.arange(n) * (fov_rad / max(spans, 1))
    return LaserRecord(angles, ranges, poses[:3], poses[3:], timestamp, max_range_m, number, tokens[0])


def _parse_robotlaser(tokens: list[str], number: int) -> LaserRecord:
    head = _floats(tokens, 2, 6, "laser header")  # start_angle fov resolution max_range accuracy remission_mode
    start_angle, _fov, resolution, max_range = head[:4]
    n = _count(tokens, 8, "num_readings")
    ranges = _floats(tokens, 9, n, "ranges")
    n_rem = _count(tokens, 9 + n, "num_remissions")
    tail = 10 + n + n_rem
    expected = tail + 11 + 3
    if len(tokens) != expected:
        raise ValueError(f"{n} readings and {n_rem} remissions need {expected} fields, found {len(tokens)}")
    poses = _floats(tokens, tail, 6, "poses")
    timestamp = float(tokens[tail + 11])
    angles = start_angle + np.arange(n) * resolution
    return LaserRecord(angles, ranges, poses[:3], poses[3:], timestamp, float(max_range), number, tokens[0])


def _parse_odom(tokens: list[str], number: int) -> OdometryRecord:
    if len(tokens) != 10:
        raise ValueError(f"ODOM needs 10 fields, found {len(tokens)}")
    v = _floats(tokens, 1, 7, "values")
    return OdometryRecord(v[:3], float(v[3]), float(v[4]), float(v[5]), float(v[6]), number)
