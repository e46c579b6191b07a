"""A laser log made to look as another robot would have recorded it: coarser beams, a short-range laser,
a slower scan rate, a wider field of view, worse wheels.

The SLAM is judged on a log of another building taken by another robot, whose laser and
odometry nobody here has seen. The logs we have are all SICK LMS scans of 180° (1° or 0.5°
beams, 50-82 m range) from Pioneer-class robots; these transformations make from each of
them the log a different robot would have given of the same run, so that anything in the
pipeline that assumes *our* lasers shows up as a run that breaks:

- :func:`coarser_beams`: every ``keep_every``-th beam, a 1° SICK LMS from a 0.5° one (the
  LMS 200 scans 180° at 1°, 0.5° or 0.25°: SICK, *LMS 200 / 211 / 221 / 291 Laser Measurement
  Systems, Technical Description*, 2006, section 8.1);
- :func:`short_range`: a Hokuyo URG-04LX's 4 m (its datasheet: 20-4095 mm guaranteed to 4 m)
  or the URG-04LX-UG01's 5.6 m (20-5600 mm), beams beyond coded as the log codes a beam
  without an echo (:func:`no_echo_range_m`);
- :func:`fewer_scans`: every ``keep_every``-th scan, the odometry between them kept, a laser
  (or a logger) at a fraction of the rate;
- :func:`wider_field`: the same beams in a ``ROBOTLASER1`` of a wider field of view (a URG's
  240°, a UTM-30LX's 270°), the beams outside the SICK's 180° without an echo: a format the
  old ``FLASER`` line cannot carry (it has no geometry);
- :func:`narrower_field`: the beams of a SICK LMS set to 100°, for ``FLASER`` lines whose field of
  view only the log's ``PARAM laser_front_laser_fov`` says;
- :func:`as_rawlaser`: the same beams as CARMEN's laser driver logs them, a ``RAWLASER1`` with its
  own geometry and no pose (the reader places it on the ``ODOM`` readings), the format of a log
  from CARMEN's logger that only the laser driver and the base wrote;
- :func:`worse_wheels`: the robot's own odometry with a scale error per wheel, a track-width
  error and a heading bias that drifts (:mod:`mazebot.slam.odometry_errors` applied to the
  odometry's own increments rather than to the reference's).

:func:`write_log` writes the result as CARMEN text, the corrected poses in the laser
messages' pose fields and the odometry either in the ``FLASER`` odometry fields or, for
``ROBOTLASER1`` and ``RAWLASER1``, in an ``ODOM`` line before each laser message (the robot pose
fields of a ``ROBOTLASER1`` then hold the corrected robot pose, as CARMEN's logger writes them; a
``RAWLASER1`` has none, and its log no corrected poses): ``mazebot slam run``
reads it as any other log, and main's code can read it too. Values are written with
Python's shortest round-trip ``repr``: a log rewritten without a transformation gives
the same run to the digit.
"""

from __future__ import annotations

import gzip
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from mazebot.geometry import compose, relative_pose
from mazebot.slam.carmen import CarmenLog, LaserRecord, OdometryRecord, no_echo_code
from mazebot.slam.odometry_errors import SystematicOdometryModel, systematic_odometry

#: the Hokuyo URG-04LX's guaranteed range (its datasheet: 20-4095 mm, accuracy ±1 % beyond 1 m)
URG_04LX_MAX_RANGE_M = 4.0
#: the URG-04LX-UG01's (its datasheet: 20-5600 mm)
URG_04LX_UG01_MAX_RANGE_M = 5.6


def no_echo_range_m(lasers: Sequence[LaserRecord]) -> float:
    """The range the log writes for a beam without an echo (:func:`mazebot.slam.carmen.no_echo_code`), else
    its largest reading: the degraded beams are written as the log writes its own."""
    code = no_echo_code(list(lasers))
    return code if code is not None else float(max(float(np.max(r.range_m)) for r in lasers if r.range_m.size))


def coarser_beams(record: LaserRecord, keep_every: int) -> LaserRecord:
    """Every ``keep_every``-th beam from the first (the right-hand end of the field of view)."""
    return replace(record, angle_rad=record.angle_rad[::keep_every], range_m=record.range_m[::keep_every])


def short_range(record: LaserRecord, max_range_m: float, code_m: float) -> LaserRecord:
    """Ranges beyond ``max_range_m`` written as ``code_m``, the log's own code of a beam without an echo."""
    ranges = np.where(record.range_m > max_range_m, code_m, record.range_m)
    return replace(record, range_m=ranges)


def fewer_scans(lasers: Sequence[LaserRecord], odometry: np.ndarray, keep_every: int) -> tuple[
    list[LaserRecord], np.ndarray
]:
    """Every ``keep_every``-th scan from the first, with the odometry at each kept scan."""
    return list(lasers[::keep_every]), np.asarray(odometry)[::keep_every]


def wider_field(record: LaserRecord, field_rad: float, code_m: float) -> LaserRecord:
    """The scan padded on both sides to ``field_rad`` at its own angular step, the added beams ``code_m``.

    The beams are the SICK's (nothing is known outside its 180°); only the message's geometry is
    a wider scanner's: its start angle, field of view and count. Returned as a ``ROBOTLASER1``.
    """
    angles = record.angle_rad
    step = float(angles[1] - angles[0])
    span = float(angles[-1] - angles[0])
    extra = max(0, round((field_rad - span) / step / 2.0))
    pad = np.arange(1, extra + 1) * step
    angles = np.concatenate((angles[0] - pad[::-1], angles, angles[-1] + pad))
    ranges = np.concatenate((np.full(extra, code_m), record.range_m, np.full(extra, code_m)))
    return replace(record, angle_rad=angles, range_m=ranges, kind="ROBOTLASER1", max_range_m=code_m)


def narrower_field(record: LaserRecord, field_rad: float) -> LaserRecord:
    """The beams within ``field_rad`` centred ahead: a SICK LMS set to 100° (``laser_front_laser_fov 100``)."""
    keep = np.abs(record.angle_rad) <= field_rad / 2.0 + 1e-9
    return replace(record, angle_rad=record.angle_rad[keep], range_m=record.range_m[keep])


def as_rawlaser(record: LaserRecord) -> LaserRecord:
    """The scan as a ``RAWLASER1``: its own beams, angles and maximum range; its poses are not written."""
    return replace(record, kind="RAWLASER1")


def worse_wheels(odometry: np.ndarray, model: SystematicOdometryModel, seed: int) -> np.ndarray:
    """The odometry (N, 3) with ``model``'s wheel, track and heading-bias errors on top of its own, from ``seed``.

    Each increment of the odometry is split into the two wheels' arcs and measured again by
    wheels and a track width that are off (:func:`mazebot.slam.odometry_errors.systematic_odometry`);
    no white noise is added (the robot's own wheels have their own).
    """
    odometry = np.asarray(odometry, dtype=np.float64).reshape(-1, 3)
    worse, _, _ = systematic_odometry(odometry, model, (0.0, 0.0), np.random.default_rng(seed))
    return compose(odometry[0], worse)


def _number(value: float) -> str:
    return repr(float(value))


def _numbers(values: np.ndarray) -> str:
    return " ".join(_number(v) for v in values)


def flaser_line(record: LaserRecord, odometry_pose: np.ndarray) -> str:
    """A ``FLASER`` line: the ranges, the corrected pose, ``odometry_pose`` in the odometry fields."""
    stamp = _number(record.timestamp_s)
    return (f"FLASER {record.range_m.size} {_numbers(record.range_m)} {_numbers(record.pose)} "
            f"{_numbers(odometry_pose)} {stamp} degraded {stamp}")


def robotlaser_line(record: LaserRecord) -> str:
    """A ``ROBOTLASER1`` line with the record's own geometry; laser and robot pose both the corrected pose."""
    step = float(record.angle_rad[1] - record.angle_rad[0]) if record.angle_rad.size > 1 else 0.0
    field = step * (record.angle_rad.size - 1)
    head = f"0 {_number(record.angle_rad[0])} {_number(field)} {_number(step)} {_number(record.max_range_m)} 0.01 0"
    stamp = _number(record.timestamp_s)
    pose = _numbers(record.pose)
    return (f"ROBOTLASER1 {head} {record.range_m.size} {_numbers(record.range_m)} 0 {pose} {pose} "
            f"0 0 0 0 0 {stamp} degraded {stamp}")


def rawlaser_line(record: LaserRecord) -> str:
    """A ``RAWLASER1`` line with the record's own geometry (CARMEN's ``carmen_logwrite_write_laser_laser``).

    The field of view is the span of the beams as they are (first to last), so that the reader's
    step (:func:`mazebot.slam.carmen.beam_step_rad`) gives back the same angles.
    """
    n = record.angle_rad.size
    field = float(record.angle_rad[-1] - record.angle_rad[0]) if n > 1 else 0.0
    step = field / (n - 1) if n > 1 else 0.0
    head = f"0 {_number(record.angle_rad[0])} {_number(field)} {_number(step)} {_number(record.max_range_m)} 0.01 0"
    stamp = _number(record.timestamp_s)
    return f"RAWLASER1 {head} {record.range_m.size} {_numbers(record.range_m)} 0 {stamp} degraded {stamp}"


def odom_line(pose: np.ndarray, timestamp_s: float) -> str:
    """An ``ODOM`` line at ``pose``, velocities and acceleration zero."""
    stamp = _number(timestamp_s)
    return f"ODOM {_numbers(pose)} 0 0 0 {stamp} degraded {stamp}"


def odometry_stream(log: CarmenLog, odometry: np.ndarray) -> list[OdometryRecord]:
    """Every ``ODOM`` reading of a re-based log (:func:`mazebot.slam.slam_cli.rebased_odometry`) in the frame of
    ``odometry`` (N, 3), the raw odometry at each laser message: the stream a logger wrote before the poses were
    corrected, its gaps and stamps kept.

    A reading after laser message k (up to the next) is ``odometry[k]`` moved by the odometry's
    motion since the re-basing line after k; readings before the first laser message are placed
    relative to the last of them. Re-basing lines themselves (stamped 0) are left out.
    """
    odometry = np.asarray(odometry, dtype=np.float64).reshape(-1, 3)
    lines = np.array([o.line_number for o in log.odometry])
    laser_lines = np.array([r.line_number for r in log.lasers])
    owner = np.searchsorted(laser_lines, lines) - 1  # the last laser message before each reading
    stream = []
    for i, reading in enumerate(log.odometry):
        k = int(owner[i])
        if reading.timestamp_s == 0.0 and k >= 0 and i > 0 and lines[i - 1] < laser_lines[k]:
            continue  # the re-basing line right after laser message k
        if k < 0:
            first = int(np.searchsorted(lines, laser_lines[0])) - 1
            pose = relative_pose(log.odometry[first].pose, reading.pose)
        else:
            base = int(np.searchsorted(lines, laser_lines[k]))  # the re-basing line after k
            pose = compose(odometry[k], relative_pose(log.odometry[base].pose, reading.pose))
        stream.append(replace(reading, pose=pose))
    return stream


def write_log(
    path: str | Path, lasers: Sequence[LaserRecord], odometry: np.ndarray,
    stream: Sequence[OdometryRecord] = (), params: dict[str, str] | None = None,
) -> None:
    """The scans and the odometry at each as CARMEN text (gzip when ``path`` ends in ``.gz``).

    ``FLASER`` records carry the odometry in their own fields; ``ROBOTLASER1`` and ``RAWLASER1``
    records get an ``ODOM`` line just before them. With ``stream`` (:func:`odometry_stream`), its readings are
    written instead, each where it stood in the original file among the laser messages. ``params``
    are written first as ``PARAM`` lines, as CARMEN's logger writes the parameters it was started with.
    """
    lines = ["# CARMEN Logfile, degraded by mazebot.slam.log_degrade"]
    lines += [f"PARAM {name} {value} 0.0 degraded 0.0" for name, value in (params or {}).items()]
    readings = sorted(stream, key=lambda o: o.line_number)
    i = 0
    for record, pose in zip(lasers, np.asarray(odometry).reshape(-1, 3), strict=True):
        while i < len(readings) and readings[i].line_number < record.line_number:
            lines.append(odom_line(readings[i].pose, readings[i].timestamp_s))
            i += 1
        if record.kind in ("ROBOTLASER1", "RAWLASER1"):
            if not readings:
                lines.append(odom_line(pose, record.timestamp_s))
            lines.append(robotlaser_line(record) if record.kind == "ROBOTLASER1" else rawlaser_line(record))
        else:
            lines.append(flaser_line(record, pose))
    lines += [odom_line(o.pose, o.timestamp_s) for o in readings[i:]]
    text = "\n".join(lines) + "\n"
    path = Path(path)
    if path.suffix == ".gz":
        with gzip.open(path, "wt", encoding="utf-8") as f:
            f.write(text)
    else:
        path.write_text(text, encoding="utf-8")

