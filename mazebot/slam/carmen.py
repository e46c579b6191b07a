"""CARMEN laser logs: ``FLASER``, ``RLASER``, ``ROBOTLASER1``/``2``, ``RAWLASER1``-``4``, ``ODOM`` and ``PARAM`` lines.

The format of the CARMEN robot toolkit's ``logger`` (carmen/src/logger, "CARMEN Logfile"
header), one message per line, fields separated by blanks::

    FLASER num_readings [range_readings] x y theta odom_x odom_y odom_theta
           ipc_timestamp ipc_hostname logger_timestamp
    ROBOTLASER1 laser_type start_angle field_of_view angular_resolution maximum_range
           accuracy remission_mode num_readings [range_readings] num_remissions
           [remission values] laser_pose_x laser_pose_y laser_pose_theta robot_pose_x
           robot_pose_y robot_pose_theta laser_tv laser_rv forward_safety_dist
           side_safety_dist turn_axis ipc_timestamp ipc_hostname logger_timestamp
    RAWLASER1 laser_type start_angle field_of_view angular_resolution maximum_range
           accuracy remission_mode num_readings [range_readings] num_remissions
           [remission values] ipc_timestamp ipc_hostname logger_timestamp
    ODOM x y theta tv rv accel ipc_timestamp ipc_hostname logger_timestamp
    PARAM param_name param_value ipc_timestamp ipc_hostname logger_timestamp

(CARMEN 0.7's ``src/logger/writelog.c``: its header and ``carmen_logwrite_write_laser_laser``,
``carmen_logwrite_write_robot_laser``, ``carmen_logwrite_write_param``.) ``ROBOTLASER2`` is
``ROBOTLASER1``'s format for the rear laser; ``RAWLASER2``-``4`` are ``RAWLASER1``'s for the
laser driver's lasers 2-4. A ``RAWLASERn`` is the laser driver's message: its own geometry
(angles in radians), no pose. CARMEN's robot module gives each scan the pose of the odometry
interpolated at its time, moved by the laser's mounting (``robot_frontlaser_offset`` ahead,
``robot_frontlaser_side_offset`` to the left, in metres, ``robot_frontlaser_angular_offset``
added to the heading, radians; ``rearlaser`` for the rear laser, whose ``RAWLASERn`` is
``robot_frontlaser_id`` / ``robot_rearlaser_id``, 1 and 2 by default: ``src/robot/robot_laser.c``,
``construct_laser_message``); the reader does the same (:func:`with_odometry_poses`). The laser
driver's ``PARAM laser_front_laser_fov`` (``laser_rear_laser_fov`` for the rear one) is the field
of view in degrees, 180 or 100 for a SICK (``src/laser/laser_main.c``, ``interpret_params``, which
refuses radians), and its scan starts at minus half of it (``set_laser_config_structure``): the
geometry of the ``FLASER``/``RLASER`` lines of a log that has the parameter.

Old-style ``FLASER``/``RLASER`` lines do not carry their geometry: the front laser is a
SICK LMS covering 180° from the right (−90°) counter-clockwise, ``fov / num_readings``
apart (1° for the 180 beams of the Intel lab log), or ``fov / (num_readings − 1)`` when
the count is odd: a SICK LMS reports 181 beams at 1° or 361 at 0.5° when it includes both
ends of its 180° (the Seattle log's 361 beams: read as 180°/361 apart, every scan's
points sit up to 0.5° off towards the right, and the consecutive scans placed at the
corrected poses agree better read at 0.5°, 17.20 against 17.46 mm median distance
between neighbouring points). Their pose ``x y theta`` is the
laser's pose; in a ``*.gfs.log`` it is the pose GMapping corrected, which is why the
Intel log serves as ground truth for scan matching. Other messages (``NEFF``, ``SYNC``,
``#`` comments, ...) are skipped.
"""

from __future__ import annotations

import gzip
import math
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from mazebot.errors import UsageError
from mazebot.geometry import compose, wrap_angle
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
    """The laser and odometry messages of a log, in file order, and its ``PARAM`` values by name."""

    lasers: list[LaserRecord] = field(default_factory=list)
    odometry: list[OdometryRecord] = field(default_factory=list)
    params: dict[str, str] = field(default_factory=dict)


#: the laser driver's messages: their geometry in their header, no pose (the reader places them on the odometry)
RAWLASER_KINDS = ("RAWLASER1", "RAWLASER2", "RAWLASER3", "RAWLASER4")
#: messages in the ``ROBOTLASER1`` format
ROBOTLASER_KINDS = ("ROBOTLASER1", "ROBOTLASER2")
#: messages whose ``pose`` is the laser's and ``odom_pose`` the robot's: the one relative to the other is the
#: laser's mounting on the robot (a ``FLASER``'s two poses are both the laser's)
MOUNTED_KINDS = ROBOTLASER_KINDS + RAWLASER_KINDS
#: ``PARAM`` names of the field of view (degrees) behind ``FLASER`` and ``RLASER`` lines
FOV_PARAMS_DEG = {"FLASER": "laser_front_laser_fov", "RLASER": "laser_rear_laser_fov"}
#: a field of view ``PARAM`` at most this many degrees is a value in radians, which CARMEN's driver refuses
FOV_RADIANS_BELOW_DEG = 2.0 * math.pi


def parse_carmen(
    lines: Iterable[str],
    source: str = "<text>",
    flaser_fov_rad: float | None = None,
    flaser_max_range_m: float = 81.0,
) -> CarmenLog:
    """Parse the lines of a CARMEN log.

    ``flaser_fov_rad`` and ``flaser_max_range_m`` describe the laser behind old-style
    ``FLASER``/``RLASER`` lines (a SICK LMS by default: no return reported as 81.83 m);
    without ``flaser_fov_rad`` the field of view is the log's ``PARAM`` (:data:`FOV_PARAMS_DEG`),
    else 180°. A malformed line raises :class:`CarmenLogError` naming ``source`` and the
    line number.
    """
    log = CarmenLog()
    param_lines: dict[str, int] = {}
    for number, line in enumerate(lines, start=1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        kind = tokens[0]
        try:
            if kind in ("FLASER", "RLASER"):
                log.lasers.append(_parse_flaser(tokens, number, math.pi, flaser_max_range_m))
            elif kind in ROBOTLASER_KINDS:
                log.lasers.append(_parse_robotlaser(tokens, number))
            elif kind in RAWLASER_KINDS:
                log.lasers.append(_parse_rawlaser(tokens, number))
            elif kind == "ODOM":
                log.odometry.append(_parse_odom(tokens, number))
            elif kind == "PARAM":
                name, value = _parse_param(tokens)
                log.params[name] = value
                param_lines[name] = number
        except (ValueError, IndexError) as error:
            raise CarmenLogError(f"{source} line {number}: bad {kind} message ({error})") from None
    try:
        log = with_field_of_view(log, flaser_fov_rad)
        log = with_odometry_poses(log)
    except _BadParam as error:
        number = param_lines[error.name]
        raise CarmenLogError(f"{source} line {number}: bad PARAM message ({error})") from None
    return with_no_echo_code(log, flaser_max_range_m)


class _BadParam(ValueError):
    """A ``PARAM`` the reader uses whose value is not what it should be; names the parameter."""

    def __init__(self, name: str, value: str, why: str) -> None:
        super().__init__(f"{name} {value!r}: {why}")
        self.name = name


def _param_float(params: dict[str, str], name: str, default: float) -> float:
    """The parameter ``name`` as a finite number, ``default`` when the log does not set it."""
    if name not in params:
        return default
    try:
        value = float(params[name])
    except ValueError:
        raise _BadParam(name, params[name], "not a number") from None
    if not math.isfinite(value):
        raise _BadParam(name, params[name], "not a finite number")
    return value


def with_field_of_view(log: CarmenLog, fov_rad: float | None) -> CarmenLog:
    """``log`` with its ``FLASER``/``RLASER`` beams spread over ``fov_rad``, else the log's ``PARAM``, else 180°.

    Such lines carry no geometry; CARMEN's laser driver took it from its parameters (a SICK
    LMS of 180° or 100°, the scan starting at minus half of it), and its logger writes the
    parameters into the log. A field of view outside (2π°, 360°] is refused: the driver takes
    degrees and refuses one in radians (π or 100° in radians, ``interpret_params``); so does the reader,
    which refuses any value up to 2π.
    """
    for kind, name in FOV_PARAMS_DEG.items():
        fov = fov_rad
        if fov is None:
            fov_deg = _param_float(log.params, name, 180.0)
            if not FOV_RADIANS_BELOW_DEG < fov_deg <= 360.0:
                raise _BadParam(name, log.params[name], "not a field of view in degrees (over 2π, at most 360)")
            fov = math.radians(fov_deg)
        if fov == math.pi:
            continue  # as parsed
        log.lasers = [
            replace(r, angle_rad=flaser_angles_rad(r.range_m.size, fov)) if r.kind == kind else r for r in log.lasers
        ]
    return log


def laser_mounts(params: dict[str, str]) -> dict[str, np.ndarray]:
    """The pose (x_m ahead, y_m left, theta_rad) of the front and rear lasers on the robot, by ``RAWLASERn`` kind.

    CARMEN's robot module reads the front laser from ``RAWLASER<robot_frontlaser_id>`` (1 by
    default) and the rear one from ``RAWLASER<robot_rearlaser_id>`` (2), and places each at
    ``robot_<front|rear>laser_offset``, ``..._side_offset`` and ``..._angular_offset`` on
    the robot; a log without them has its lasers at the robot's origin.
    """
    mounts = {}
    for which, default_id in (("rear", 2), ("front", 1)):  # the front laser wins where both name one RAWLASER
        prefix = f"robot_{which}laser"
        laser_id = _param_float(params, f"{prefix}_id", float(default_id))
        mount = np.array([_param_float(params, f"{prefix}_{part}", 0.0)
                          for part in ("offset", "side_offset", "angular_offset")])
        mounts[f"RAWLASER{int(laser_id)}"] = mount
    return mounts


def odometry_at(
    odometry: list[OdometryRecord], times_s: np.ndarray, line_numbers: np.ndarray
) -> np.ndarray | None:
    """The robot's odometry pose (N, 3) at each of the given messages, or None without two ``ODOM`` readings.

    ``ODOM`` poses are interpolated in time between the readings around each message (the
    heading unwrapped), as CARMEN's robot module does for each laser message; where the
    stamps do not increase (logs whose stamps were rounded), time says nothing, and each
    message takes the last reading before it in the file.
    """
    if len(odometry) < 2:
        return None
    t = np.array([o.timestamp_s for o in odometry])
    p = np.array([o.pose for o in odometry])
    if np.all(np.diff(t) > 0):
        th = np.unwrap(p[:, 2])
        return np.column_stack(
            (np.interp(times_s, t, p[:, 0]), np.interp(times_s, t, p[:, 1]), wrap_angle(np.interp(times_s, t, th)))
        )
    lines = np.array([o.line_number for o in odometry])
    before = np.searchsorted(lines, line_numbers) - 1
    return p[np.maximum(before, 0)]


def with_odometry_poses(log: CarmenLog) -> CarmenLog:
    """``log`` with each ``RAWLASERn`` message placed on the odometry at its time: ``odom_pose`` the robot's,
    ``pose`` the laser's (the robot's moved by the laser's mounting in the log's ``PARAM`` lines, :func:`laser_mounts`).

    The laser driver's messages carry no pose; CARMEN's robot module gives each the odometry
    interpolated at its time (:func:`odometry_at`). Without two ``ODOM`` readings they stay
    at the origin (a log without odometry). The laser's pose is the odometry's, not a
    corrected one: such a log has no reference of its own.
    """
    raw = [k for k, r in enumerate(log.lasers) if r.kind in RAWLASER_KINDS]
    if not raw:
        return log
    mounts = laser_mounts(log.params)
    moving = any(np.any(o.pose) for o in log.odometry)  # all zero: the log has no odometry
    readings = log.odometry if moving else []
    times = np.array([log.lasers[k].timestamp_s for k in raw])
    lines = np.array([log.lasers[k].line_number for k in raw])
    robot = odometry_at(readings, times, lines)
    if robot is None:
        return log
    lasers = list(log.lasers)
    for row, k in enumerate(raw):
        mount = mounts.get(lasers[k].kind, np.zeros(3))
        lasers[k] = replace(lasers[k], pose=compose(robot[row], mount), odom_pose=robot[row])
    log.lasers = lasers
    return log


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
    with another. ``RAWLASERn`` messages carry the laser's nominal maximum, which CARMEN's
    driver sets above a SICK's no-echo reading (81.90 m against 81.83 m: ``src/laser/laser_main.c``,
    ``set_laser_config_structure``), so theirs is lowered to the code the same way.
    ``ROBOTLASER1`` messages are taken as their header says.
    """
    for kind in ("FLASER", "RLASER", *RAWLASER_KINDS):
        records = [r for r in log.lasers if r.kind == kind]
        code = no_echo_code(records)
        if code is None:
            continue
        log.lasers = [
            replace(r, max_range_m=code) if r.kind == kind and code < r.max_range_m else r for r in log.lasers
        ]
    return log


#: the laser messages in the order :func:`one_laser` chooses them: the front laser's first
LASER_PREFERENCE = (
    "ROBOTLASER1", "FLASER", "RAWLASER1", "ROBOTLASER2", "RLASER", "RAWLASER2", "RAWLASER3", "RAWLASER4",
)


def one_laser(log: CarmenLog) -> CarmenLog:
    """The log with the messages of one laser only: the front one's, as ``ROBOTLASER1`` if it has them.

    A robot with a front and a rear laser logs both (``FLASER`` and ``RLASER``), and a
    converted log may hold the front laser twice (``ROBOTLASER1`` and ``FLASER``); CARMEN's
    logger writes each scan as the driver's ``RAWLASERn`` and again as the robot module's
    ``ROBOTLASERn`` or ``FLASER``. Taken together they would be one sensor seen from two
    places, or each scan twice; the SLAM tracks one laser. ``ROBOTLASER1`` carries its own
    geometry and the laser's mounting, so it wins over ``FLASER``, whose pose may be a
    corrected one, over ``RAWLASER1``, which has none; the rear laser (``ROBOTLASER2``,
    ``RLASER``, ``RAWLASER2``) and the driver's lasers 3-4 are used only when the log has
    nothing else (:data:`LASER_PREFERENCE`).
    """
    for kind in LASER_PREFERENCE:
        chosen = [r for r in log.lasers if r.kind == kind]
        if chosen:
            return CarmenLog(lasers=chosen, odometry=log.odometry, params=log.params)
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


def flaser_angles_rad(n: int, fov_rad: float) -> np.ndarray:
    """The angles of ``n`` beams over ``fov_rad`` from its right-hand end, as CARMEN's SICK driver spreads them.

    An odd count includes both ends of the field of view (181 beams over 180° at 1°), an even
    one leaves the last end out (180 at 1°): ``src/laser/laser_main.c``, ``set_laser_config_structure``.
    """
    spans = n - 1 if n % 2 == 1 and n > 1 else n
    return -fov_rad / 2.0 + np.arange(n) * (fov_rad / max(spans, 1))


def _parse_flaser(tokens: list[str], number: int, fov_rad: float, max_range_m: float) -> LaserRecord:
    n = _count(tokens, 1, "num_readings")
    expected = 2 + n + 6 + 3
    if len(tokens) != expected:
        raise ValueError(f"{n} readings need {expected} fields, found {len(tokens)}")
    ranges = _floats(tokens, 2, n, "ranges")
    poses = _floats(tokens, 2 + n, 6, "poses")
    timestamp = float(tokens[2 + n + 6])
    angles = flaser_angles_rad(n, fov_rad)
    return LaserRecord(angles, ranges, poses[:3], poses[3:], timestamp, max_range_m, number, tokens[0])


def _laser_block(tokens: list[str], trailing: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The laser part ``RAWLASERn`` and ``ROBOTLASERn`` lines share, and where what follows it starts.

    ``laser_type start_angle field_of_view angular_resolution maximum_range accuracy remission_mode
    num_readings [ranges] num_remissions [remissions]``, then ``trailing`` fields. Returns the
    header's six numbers, the ranges and the index after the remissions.
    """
    head = _floats(tokens, 2, 6, "laser header")  # start_angle fov resolution max_range accuracy remission_mode
    n = _count(tokens, 8, "num_readings")
    ranges = _floats(tokens, 9, n, "ranges")
    n_rem = _count(tokens, 9 + n, "num_remissions")
    after = 10 + n + n_rem
    if len(tokens) != after + trailing:
        raise ValueError(f"{n} readings and {n_rem} remissions need {after + trailing} fields, found {len(tokens)}")
    return head, ranges, after


def _parse_rawlaser(tokens: list[str], number: int) -> LaserRecord:
    """A ``RAWLASERn`` line; its poses are left at zero for :func:`with_odometry_poses` to fill."""
    head, ranges, after = _laser_block(tokens, 3)
    start_angle, fov, resolution, max_range = head[:4]
    if max_range <= 0.0:
        raise ValueError(f"maximum_range must be positive, got {max_range}")
    timestamp = float(tokens[after])
    angles = start_angle + np.arange(ranges.size) * beam_step_rad(float(fov), float(resolution), ranges.size)
    return LaserRecord(angles, ranges, np.zeros(3), np.zeros(3), timestamp, float(max_range), number, tokens[0])


#: how far a laser header's ``angular_resolution`` may be from ``field_of_view / (num_readings - 1)`` and still
#: be the same step: CARMEN's logger prints both with six decimals (``%f``), half a unit of the last is 5e-7 rad
HEADER_STEP_TOLERANCE_RAD = 1e-6


def beam_step_rad(fov_rad: float, resolution_rad: float, n: int) -> float:
    """The angle between a laser header's beams: ``fov_rad / (n - 1)`` where that is its ``resolution_rad``.

    CARMEN's driver sets the field of view to span the beams exactly (``(n - 1)`` steps: π over
    181 or 361 beams, π minus a step over 180 or 360: ``src/laser/laser_main.c``,
    ``set_laser_config_structure``), and its logger prints both with six decimals: 0.5° as
    0.008727 rad, 4e-4 of the step off, 1.3e-4 rad (0.007°) by the last of 361 beams, while
    the field of view's rounding spreads over all of them. A header whose two disagree by
    more than the printing (a field of view written as ``n`` steps) is read by its resolution.
    """
    if n < 2:
        return resolution_rad
    spread = fov_rad / (n - 1)
    return spread if abs(spread - resolution_rad) <= HEADER_STEP_TOLERANCE_RAD else resolution_rad


def _parse_param(tokens: list[str]) -> tuple[str, str]:
    """``PARAM name value [ipc_timestamp ipc_hostname logger_timestamp]``: the name and the value.

    CARMEN's logger writes the three trailing fields; the value is everything between the
    name and them (a parameter may be a string with blanks). A line shorter than that (a
    log written by hand or by another tool) gives the field after the name.
    """
    if len(tokens) < 3:
        raise ValueError(f"PARAM needs a name and a value, found {len(tokens)} fields")
    value = " ".join(tokens[2:-3]) if len(tokens) >= 6 else tokens[2]
    return tokens[1], value


def _parse_robotlaser(tokens: list[str], number: int) -> LaserRecord:
    head, ranges, tail = _laser_block(tokens, 11 + 3)
    start_angle, _fov, resolution, max_range = head[:4]
    poses = _floats(tokens, tail, 6, "poses")
    timestamp = float(tokens[tail + 11])
    angles = start_angle + np.arange(ranges.size) * resolution
    return LaserRecord(angles, ranges, poses[:3], poses[3:], timestamp, float(max_range), number, tokens[0])


def _parse_odom(tokens: list[str], number: int) -> OdometryRecord:
    if len(tokens) != 10:
        raise ValueError(f"ODOM needs 10 fields, found {len(tokens)}")
    v = _floats(tokens, 1, 7, "values")
    return OdometryRecord(v[:3], float(v[3]), float(v[4]), float(v[5]), float(v[6]), number)
