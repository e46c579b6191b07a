"""A calibration's result as a new config, its diff against the old one, and the report (JSON + PNG)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from mazebot.calibration.geometry import Run
from mazebot.calibration.routine import CalibrationResult
from mazebot.config import Config, render_toml
from mazebot.files import write_atomic
from mazebot.png import encode_png


def calibrated_config(config: Config, result: CalibrationResult) -> Config:
    """``config`` with the measured wiring, wheel sizes, track width, lidar yaw and deadband."""
    new = config.model_copy(deep=True)
    w, m, e = result.wiring, config.motors, config.encoders
    motors: dict[str, Any] = {}
    encoders: dict[str, Any] = {}
    for output, wheel in w.wheel_of_output.items():
        motors[f"{wheel}_channel"] = getattr(m, f"{output}_channel")
        motors[f"{wheel}_invert"] = getattr(m, f"{output}_invert") != w.output_reversed[output]
    for encoder, wheel in w.wheel_of_encoder.items():
        encoders[f"{wheel}_a_pin"] = getattr(e, f"{encoder}_a_pin")
        encoders[f"{wheel}_b_pin"] = getattr(e, f"{encoder}_b_pin")
        encoders[f"{wheel}_invert"] = getattr(e, f"{encoder}_invert") != w.encoder_reversed[encoder]
    new.motors = type(m).model_validate({**m.model_dump(), **motors})
    new.encoders = type(e).model_validate({**e.model_dump(), **encoders})
    g = result.geometry
    ticks = config.encoders.ticks_per_rev
    left_d, right_d = g.left_m_per_count * ticks / math.pi, g.right_m_per_count * ticks / math.pi
    new.drive.wheel_diameter_m = round(0.5 * (left_d + right_d), 6)
    new.drive.wheel_diameter_ratio = round(right_d / left_d, 5)
    new.drive.track_width_m = round(g.track_width_m, 5)
    yaw = math.remainder(config.lidar.mount_yaw_deg + result.yaw_error_deg, 360.0)
    new.lidar.mount_yaw_deg = round(yaw, 3)
    new.control.motor_deadband = round(0.5 * (result.deadband["left"] + result.deadband["right"]), 4)
    return new


def config_diff(old: Config, new: Config) -> list[tuple[str, Any, Any]]:
    """``(section.key, old, new)`` for every value that differs, in file order."""
    changes = []
    for section in Config.model_fields:
        a, b = getattr(old, section).model_dump(), getattr(new, section).model_dump()
        changes += [(f"{section}.{k}", a[k], b[k]) for k in a if a[k] != b[k]]
    return changes


def config_to_write(old: Config, new: Config, *, sim: bool) -> Config:
    """The calibrated config as it is written: for the simulated robot, ``[sim]`` rewritten to
    describe the same true robot against the new values (:func:`mazebot.calibration.sim_section.same_true_robot`),
    so the next run drives the robot that was calibrated."""
    if not sim:
        return new
    from mazebot.calibration.sim_section import same_true_robot

    return same_true_robot(old, new)


def write_calibrated_config(target: Path, old: Config, new: Config, *, sim: bool) -> Path | None:
    """Write ``new`` (:func:`config_to_write`) over ``target`` atomically, the file it replaces kept
    as ``target.bak`` first; returns the backup's path (None when there was no file to keep)."""
    new = config_to_write(old, new, sim=sim)
    backup = target.with_name(target.name + ".bak")
    kept = None
    if target.is_file():
        write_atomic(backup, target.read_bytes())
        kept = backup
    write_atomic(target, render_toml(new).encode())
    return kept


def report_json(result: CalibrationResult, diff: list[tuple[str, Any, Any]], steps: list[dict[str, Any]]) -> bytes:
    g = result.geometry
    doc = {
        "steps": steps,
        "wiring": {
            "wheel_of_output": result.wiring.wheel_of_output,
            "output_reversed": result.wiring.output_reversed,
            "wheel_of_encoder": result.wiring.wheel_of_encoder,
            "encoder_reversed": result.wiring.encoder_reversed,
        },
        "left_m_per_count": g.left_m_per_count,
        "right_m_per_count": g.right_m_per_count,
        "track_width_m": g.track_width_m,
        "worst_arc_residual": g.worst_arc_residual,
        "lidar_yaw_error_deg": result.yaw_error_deg,
        "deadband": result.deadband,
        "pulses": [vars(p) for p in result.pulses],
        "runs": [vars(r) for r in result.runs],
        "diff": [{"key": k, "old": a, "new": b} for k, a, b in diff],
    }
    return (json.dumps(doc, indent=2) + "\n").encode()


def run_ends(runs: list[Run]) -> np.ndarray:
    """Each run's end pose ``(x_m, y_m, theta_rad)`` in the frame of the first run's start.

    A run's displacement is measured by scan matching in the frame of its own start, so the
    runs are chained (each end composed onto the previous one) to draw them where the robot was.
    """
    x_m = y_m = theta_rad = 0.0
    ends = np.zeros((len(runs), 3))
    for i, run in enumerate(runs):
        c, s = math.cos(theta_rad), math.sin(theta_rad)
        x_m, y_m = x_m + c * run.x_m - s * run.y_m, y_m + s * run.x_m + c * run.y_m
        theta_rad += run.theta_rad
        ends[i] = x_m, y_m, theta_rad
    return ends


def report_png(result: CalibrationResult, size_px: int = 480, extent_m: float = 4.0) -> bytes:
    """The still scan before the runs (grey), the start (green), and where each straight run
    (red) and each turn in place (blue) ended, the runs chained from the start."""
    img = np.full((size_px, size_px, 3), 255, np.uint8)
    scale = size_px / extent_m
    centre = size_px // 2

    def plot(points: np.ndarray, colour: tuple[int, int, int], radius: int = 0) -> None:
        cols = np.round(centre + points[:, 0] * scale).astype(int)
        rows = np.round(centre - points[:, 1] * scale).astype(int)
        for dr in range(-radius, radius + 1):
            for dc in range(-radius, radius + 1):
                r, c = rows + dr, cols + dc
                ok = (r >= 0) & (r < size_px) & (c >= 0) & (c < size_px)
                img[r[ok], c[ok]] = colour

    for points in result.scans[:1]:
        plot(points, (90, 90, 90))
    plot(np.zeros((1, 2)), (0, 150, 0), radius=4)
    for run, end in zip(result.runs, run_ends(result.runs), strict=True):
        plot(end[None, :2], (200, 30, 30) if run.kind == "straight" else (30, 60, 200), radius=3)
    return encode_png(img)
