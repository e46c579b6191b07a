"""The calibration routine: short pulses, throttle ramps, straight runs and turns in place on the real drivers.

Everything goes through the daemon's own drivers (:class:`~mazebot.io.motors.DifferentialMotors`
with its time-to-live, :class:`~mazebot.io.encoders.WheelEncoders`, :class:`~mazebot.io.rplidar.RPLidar`),
on the robot as on the simulator. Motions are measured between still scans: the robot
stops, settles, and a few revolutions are merged into one point set; ICP
(:mod:`mazebot.slam.icp`) matches the set after a motion to the set before it.
The motors are braked in ``finally`` on every path.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from mazebot.calibration.geometry import (
    CalibrationError,
    Geometry,
    Pulse,
    Run,
    Wiring,
    deduce_wiring,
    solve_geometry,
    yaw_error_rad,
)
from mazebot.calibration.progress import Progress
from mazebot.clock import Clock
from mazebot.config import Config
from mazebot.hardware import Motors
from mazebot.io.scan import Scan
from mazebot.slam.icp import IcpParams, Target, match_scan
from mazebot.slam.preprocess import PrepareParams, prepare_scan

STEPS = [
    ("wiring", "motor and encoder wiring (short pulses)"),
    ("ramp", "motor deadband and left/right gain (throttle ramp)"),
    ("straight", "wheel sizes (straight runs, scan matched)"),
    ("turns", "track width (turns in place, scan matched)"),
    ("yaw", "lidar mounting yaw (direction of travel)"),
]

TICK_S = 0.02  # motor command period (well inside the motors' time-to-live)
SETTLE_S = 0.4  # after braking, before a still scan
STILL_REVOLUTIONS = 3  # revolutions merged into one still scan
PULSE_THROTTLE = 0.4
PULSE_S = 0.3
DRIVE_THROTTLE = 0.35
STRAIGHT_M = 0.8
STRAIGHT_RUNS_EACH_WAY = 3
TURN_THROTTLE = 0.3
#: Turns in place (direction, angle): a quarter turn first, so the track width is known well
#: enough for the whole turns after it that their scan match starts close to the answer.
TURNS = ((1, math.pi / 2), (1, math.tau), (-1, math.tau), (1, 2 * math.tau), (-1, 2 * math.tau))
MIN_POINTS = 60  # a still scan with fewer points sees no walls
MIN_FITNESS = 0.6  # share of points matched: a 0.8 m run sees a good part of the room anew
MAX_RMSE_M = 0.02
MAX_DISAGREEMENT = 0.15  # encoders (configured sizes) and scans disagree by more: slipping or wrong counts
MAX_ARC_RESIDUAL = 0.01  # straight runs whose encoder arcs disagree with the scans by more: slipping


@dataclass
class CalibrationResult:
    """What the routine measured; ``runs`` and ``pulses`` for the report."""

    wiring: Wiring
    geometry: Geometry
    yaw_error_deg: float
    deadband: dict[str, float]
    speed_per_throttle_mps: dict[str, float]
    runs: list[Run] = field(default_factory=list)
    pulses: list[Pulse] = field(default_factory=list)
    scans: list[np.ndarray] = field(default_factory=list)  # still point sets, each in the frame of its run start


class _ScanFeed:
    """Keeps the lidar's latest revolutions (a task reads ``lidar.scans()`` all along)."""

    def __init__(self, lidar: Any) -> None:
        self.scans: list[Scan] = []
        self._task = asyncio.create_task(self._read(lidar), name="calibration-lidar")

    async def _read(self, lidar: Any) -> None:
        async for scan in lidar.scans():
            self.scans.append(scan)
            del self.scans[:-10]

    async def since(self, time_s: float, count: int, clock: Clock) -> list[Scan]:
        for _ in range(int(10.0 / TICK_S)):
            if self._task.done():
                self._task.result()  # the driver's error
            fresh = [s for s in self.scans if s.start_time_s >= time_s]
            if len(fresh) >= count:
                return fresh[:count]
            await clock.sleep(TICK_S)
        raise CalibrationError("lidar: no revolutions came for 10 s; check `mazebot lidar health`")

    async def close(self) -> None:
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task


class _TickCounter(Protocol):
    def read(self) -> Any: ...  # a reading with the wheels' ``left`` and ``right`` counts


class _ScanSource(Protocol):
    def scans(self) -> AsyncIterator[Scan]: ...


class CalibrationDevices(Protocol):
    """What the calibration drives and reads: a :class:`mazebot.hardware.Hardware`, or the
    daemon's devices behind its shared state (:class:`mazebot.calibration.on_daemon.DaemonDevices`)."""

    @property
    def motors(self) -> Motors: ...

    @property
    def encoders(self) -> _TickCounter: ...

    @property
    def lidar(self) -> _ScanSource: ...


class Calibrator:
    """Runs the steps on ``hardware`` with ``config`` as the starting guess."""

    def __init__(self, hardware: CalibrationDevices, config: Config, clock: Clock, progress: Progress) -> None:
        self.hw = hardware
        self.config = config
        self.clock = clock
        self.progress = progress
        self.wiring: Wiring | None = None
        lidar = config.lidar
        self._prepare = PrepareParams(
            min_range_m=lidar.min_range_m, max_range_m=min(lidar.max_range_m, 6.0),
            mount_x_m=lidar.mount_x_m, mount_y_m=lidar.mount_y_m,
        )
        # refined far below the SLAM's stop steps: a run's length is wanted to a fraction of a millimetre
        self._icp = IcpParams(
            max_correspondence_m=0.3, min_correspondence_m=0.03, max_iterations=400,
            stop_translation_m=1e-5, stop_rotation_rad=1e-5,
        )
        nominal_m = math.pi * config.drive.wheel_diameter_m / config.encoders.ticks_per_rev
        ratio = config.drive.wheel_diameter_ratio
        self.k_left = nominal_m * 2.0 / (1.0 + ratio)
        self.k_right = nominal_m * 2.0 * ratio / (1.0 + ratio)
        self.track_m = config.drive.track_width_m
        self.scans: list[np.ndarray] = []

    # -- the drivers, through the wiring found so far --------------------------------------

    def _counts(self) -> tuple[int, int]:
        """Counts of the left and right wheel, forward positive, once the wiring is known."""
        r = self.hw.encoders.read()
        raw = {"left": r.left_ticks, "right": r.right_ticks}
        if self.wiring is None:
            return raw["left"], raw["right"]
        by_wheel = {}
        for encoder, wheel in self.wiring.wheel_of_encoder.items():
            by_wheel[wheel] = -raw[encoder] if self.wiring.encoder_reversed[encoder] else raw[encoder]
        return by_wheel["left"], by_wheel["right"]

    def _set(self, left: float, right: float) -> None:
        """Throttles for the left and right wheel (through the wiring found so far)."""
        if self.wiring is None:
            self.hw.motors.set(left, right)
            return
        wanted = {"left": left, "right": right}
        out = {}
        for output, wheel in self.wiring.wheel_of_output.items():
            out[output] = -wanted[wheel] if self.wiring.output_reversed[output] else wanted[wheel]
        self.hw.motors.set(out["left"], out["right"])

    def _turned_by(self, sign: float, turned_m: float) -> Callable[[int, int], bool]:
        """An ``until`` for :meth:`_hold`: the wheels' arcs (ticks times metres per tick) differ by
        ``turned_m`` in the direction ``sign`` (+1: to the left)."""
        return lambda dl, dr: sign * (dr * self.k_right - dl * self.k_left) >= turned_m

    async def _hold(self, left: float, right: float, until: Callable[[int, int], bool], limit_s: float) -> None:
        start = self._counts()
        t0 = self.clock.now_s()
        while self.clock.now_s() - t0 < limit_s:
            c = self._counts()
            if until(c[0] - start[0], c[1] - start[1]):
                break
            self._set(left, right)
            await self.clock.sleep(TICK_S)
        self.hw.motors.stop()

    async def _still(self, feed: _ScanFeed) -> tuple[np.ndarray, tuple[int, int]]:
        """The merged points of a few revolutions after the robot settled, and the counts then."""
        self.hw.motors.stop()
        await self.clock.sleep(SETTLE_S)
        counts = self._counts()
        scans = await feed.since(self.clock.now_s(), STILL_REVOLUTIONS, self.clock)
        points = np.concatenate([prepare_scan(s, None, self._prepare).points_full for s in scans])
        if len(points) < MIN_POINTS * STILL_REVOLUTIONS:
            raise CalibrationError(
                f"only {len(points) // STILL_REVOLUTIONS} lidar points a revolution: no walls in view; "
                "put the robot in an open space with walls within a few metres"
            )
        return points, counts

    def _match(self, step: str, before: np.ndarray, after: np.ndarray, guess: np.ndarray) -> np.ndarray:
        """Pose of the robot after, in the frame before, by ICP; CalibrationError if the fit is bad."""
        sensor = np.array([self._prepare.mount_x_m, self._prepare.mount_y_m])
        target = Target(before, sensor)
        source = after[_thin(after, 0.02)]
        best = None
        for turn in (0.0, 0.15, -0.15, 0.3, -0.3):
            start = guess + np.array([0.0, 0.0, turn])
            result = match_scan(target, source, start, self._icp, sensor_xy=sensor)
            if best is None or result.fitness > best.fitness:
                best = result
            if result.fitness >= MIN_FITNESS and result.rmse_m <= MAX_RMSE_M:
                return np.asarray(result.pose, dtype=np.float64)
        assert best is not None
        raise CalibrationError(
            f"{step}: scan matching failed ({best.fitness:.0%} of points matched, residual "
            f"{best.rmse_m * 1000:.0f} mm): too few walls in view, or the floor slips"
        )

    def _odometry_guess(self, dl: int, dr: int) -> np.ndarray:
        d_l, d_r = dl * self.k_left, dr * self.k_right
        s, dth = 0.5 * (d_l + d_r), (d_r - d_l) / self.track_m
        return np.array([s * math.cos(0.5 * dth), s * math.sin(0.5 * dth), math.remainder(dth, math.tau)])

    # -- the steps ---------------------------------------------------------------------

    async def run(self) -> CalibrationResult:
        feed = _ScanFeed(self.hw.lidar)
        try:
            wiring, pulses, home = await self._step("wiring", self._wiring(feed))
            deadband, speed = await self._step("ramp", self._ramp_then_face(feed, home))
            runs = await self._step("straight", self._straight(feed))
            runs = await self._step("turns", self._turns(feed, runs))
            geometry = solve_geometry(runs)
            speed = {
                "left": self._ramp_rates["left"] * geometry.left_m_per_count,
                "right": self._ramp_rates["right"] * geometry.right_m_per_count,
            }
            self.progress.update(
                "ramp", speed_left_mps_per_throttle=round(speed["left"], 4),
                speed_right_mps_per_throttle=round(speed["right"], 4),
                gain_right_over_left=round(speed["right"] / speed["left"], 4),
            )
            yaw = await self._step("yaw", self._yaw(runs))
            return CalibrationResult(wiring, geometry, yaw, deadband, speed, runs, pulses, self.scans)
        finally:
            self.hw.motors.stop()
            await feed.close()

    async def _step(self, name: str, work: Any) -> Any:
        self.progress.update(name, "running")
        try:
            result = await work
        except CalibrationError as error:
            self.hw.motors.stop()
            self.progress.update(name, "failed", str(error))
            raise CalibrationError(f"calibration step '{name}' failed: {error}") from None
        except BaseException:
            self.hw.motors.stop()
            self.progress.update(name, "failed", "interrupted")
            raise
        self.progress.update(name, "done")
        return result

    async def _wiring(self, feed: _ScanFeed) -> tuple[Wiring, list[Pulse], np.ndarray]:
        """One forward pulse of each motor output, back and forth; also the starting view (``home``),
        the first still scan, so that no walls in view fails this first step."""
        home, _ = await self._still(feed)
        pulses = []
        for output in ("left", "right"):
            before, c0 = await self._still(feed)
            throttles = (PULSE_THROTTLE, 0.0) if output == "left" else (0.0, PULSE_THROTTLE)
            await self._hold(*throttles, until=lambda dl, dr: False, limit_s=PULSE_S)
            after, c1 = await self._still(feed)
            pose = self._match("wiring", before, after, np.zeros(3))
            pulses.append(Pulse(output, c1[0] - c0[0], c1[1] - c0[1], *(float(v) for v in pose)))
            back = (-PULSE_THROTTLE, 0.0) if output == "left" else (0.0, -PULSE_THROTTLE)
            await self._hold(*back, until=lambda dl, dr: False, limit_s=PULSE_S)  # back to where it was
        self.wiring = wiring = deduce_wiring(pulses)
        self.progress.update(
            "wiring",
            detail="left wheel: motor output {}{}, encoder {}{}; right wheel: motor output {}{}, encoder {}{}".format(
                *_describe(wiring, "left"), *_describe(wiring, "right")
            ),
            wheel_of_output=wiring.wheel_of_output,
            output_reversed=wiring.output_reversed,
            wheel_of_encoder=wiring.wheel_of_encoder,
            encoder_reversed=wiring.encoder_reversed,
        )
        return wiring, pulses, home

    async def _ramp_then_face(
        self, feed: _ScanFeed, home: np.ndarray,
    ) -> tuple[dict[str, float], dict[str, float]]:
        """The ramp, then the turn back to the starting heading: one step, as the user sees it."""
        deadband, speed = await self._ramp()
        self.progress.update("ramp", detail="turning back to the starting heading")
        await self._face(feed, home)
        self.progress.update("ramp", detail=f"deadband left {deadband['left']:.3f}, right {deadband['right']:.3f}")
        return deadband, speed

    async def _face(self, feed: _ScanFeed, home: np.ndarray) -> None:
        """Turn back to the heading of the first still scan (the ramp spun the robot round)."""
        for _ in range(3):
            here, _ = await self._still(feed)
            best = None
            for guess_rad in np.linspace(-math.pi, math.pi, 12, endpoint=False):
                with contextlib.suppress(CalibrationError):
                    pose = self._match("ramp", home, here, np.array([0.0, 0.0, guess_rad]))
                    best = pose
                    break
            if best is None:
                raise CalibrationError("cannot find the starting heading again in the scans")
            error_rad = float(best[2])
            if abs(error_rad) < math.radians(2.0):
                return
            turned = abs(error_rad) * self.track_m
            sign = -1.0 if error_rad > 0 else 1.0  # turn the other way
            await self._hold(
                -sign * TURN_THROTTLE, sign * TURN_THROTTLE,
                until=self._turned_by(sign, turned),
                limit_s=10.0,
            )

    async def _ramp(self) -> tuple[dict[str, float], dict[str, float]]:
        """Spin in place at rising throttles; the first that turns a wheel is its deadband,
        and the count rates at higher ones give each wheel's speed per throttle."""
        self.hw.motors.stop()
        await self.clock.sleep(SETTLE_S)  # the last pulse's wheel has stopped
        deadband: dict[str, float] = {}
        rates: dict[float, tuple[float, float]] = {}
        throttle = 0.0
        hold_s, measure_s = 0.35, 0.2
        while throttle < 0.4 - 1e-9:
            throttle = round(throttle + (0.005 if len(deadband) < 2 else 0.05), 3)
            t0 = self.clock.now_s()
            start = None
            # held for hold_s, the last measure_s of it measured; a loop that stalled past the window's
            # start (a starved core) begins the window when it runs again, so it is measure_s long all the same
            while True:
                now_s = self.clock.now_s()
                if start is None and now_s - t0 >= hold_s - measure_s:
                    start = (self._counts(), now_s)
                if start is not None and now_s - start[1] >= measure_s:
                    break
                self._set(-throttle, throttle)
                await self.clock.sleep(TICK_S)
            (l0, r0), s0 = start
            l1, r1 = self._counts()
            dt_s = self.clock.now_s() - s0
            rate = ((l1 - l0) / dt_s, (r1 - r0) / dt_s)
            rates[throttle] = rate
            for side, value in zip(("left", "right"), rate, strict=True):
                if side not in deadband and abs(value) * dt_s >= 1:
                    deadband[side] = round(throttle - 0.0025, 4)
        self.hw.motors.stop()
        missing = [side for side in ("left", "right") if side not in deadband]
        if missing:
            raise CalibrationError(f"the {missing[0]} wheel did not turn at throttle 0.4 or below")
        top = max(rates)
        self._ramp_rates = {"left": -rates[top][0] / top, "right": rates[top][1] / top}  # counts/s per throttle
        self.progress.update("ramp", deadband_left=deadband["left"], deadband_right=deadband["right"])
        return deadband, {}  # speeds in m/s once the wheel sizes are known (run)

    async def _straight(self, feed: _ScanFeed) -> list[Run]:
        runs = []
        for direction in (1, -1) * STRAIGHT_RUNS_EACH_WAY:
            before, c0 = await self._still(feed)
            target_counts = STRAIGHT_M / (0.5 * (self.k_left + self.k_right))
            await self._drive_straight(direction, target_counts)
            after, c1 = await self._still(feed)
            dl, dr = c1[0] - c0[0], c1[1] - c0[1]
            guess = self._odometry_guess(dl, dr)
            pose = self._match("straight", before, after, guess)
            run = Run("straight", dl, dr, *(float(v) for v in pose))
            encoder_m, scan_m = abs(guess[0]), math.hypot(pose[0], pose[1])
            if abs(encoder_m / max(scan_m, 1e-6) - 1.0) > MAX_DISAGREEMENT:
                raise CalibrationError(
                    f"encoders say {encoder_m:.3f} m, the lidar {scan_m:.3f} m: the floor slips, the robot "
                    "ran into something (it needs 1 m free ahead), or [encoders] counts_per_rev / "
                    "[drive] wheel_diameter_m are far off"
                )
            runs.append(run)
            self.scans.append(before)
            self.progress.update("straight", detail=f"run {len(runs)}: {scan_m:.3f} m", runs=len(runs))
        return runs

    async def _drive_straight(self, direction: int, target_counts: float) -> None:
        """Drive until the mean count reaches ``target_counts``, the wheels' counts kept equal."""
        start = self._counts()
        t0 = self.clock.now_s()
        while self.clock.now_s() - t0 < 10.0:
            c = self._counts()
            dl, dr = direction * (c[0] - start[0]), direction * (c[1] - start[1])
            if 0.5 * (dl + dr) >= target_counts:
                break
            trim = max(-0.1, min(0.1, 0.002 * (dl - dr)))
            self._set(direction * (DRIVE_THROTTLE - trim), direction * (DRIVE_THROTTLE + trim))
            await self.clock.sleep(TICK_S)
        self.hw.motors.stop()

    async def _turns(self, feed: _ScanFeed, runs: list[Run]) -> list[Run]:
        runs = list(runs)
        for index, (direction, angle_rad) in enumerate(TURNS):
            before, c0 = await self._still(feed)
            if index == 0:
                self.scans.append(before)
            turned = angle_rad * self.track_m
            await self._hold(
                -direction * TURN_THROTTLE, direction * TURN_THROTTLE,
                until=self._turned_by(direction, turned),
                limit_s=20.0,
            )
            after, c1 = await self._still(feed)
            dl, dr = c1[0] - c0[0], c1[1] - c0[1]
            guess = self._odometry_guess(dl, dr)
            estimate_rad = (dr * self.k_right - dl * self.k_left) / self.track_m
            pose = self._match("turns", before, after, guess)
            total_rad = estimate_rad + math.remainder(float(pose[2]) - estimate_rad, math.tau)
            runs.append(Run("turn", dl, dr, float(pose[0]), float(pose[1]), total_rad))
            geometry = solve_geometry(runs)  # each turn sharpens the track width for the next, longer one
            self.k_left, self.k_right, self.track_m = (
                geometry.left_m_per_count, geometry.right_m_per_count, geometry.track_width_m,
            )
            self.progress.update("turns", detail=f"turn {index + 1}: {math.degrees(total_rad):.1f}°",
                                 track_width_m=round(self.track_m, 5))
        geometry = solve_geometry(runs)
        if geometry.worst_arc_residual > MAX_ARC_RESIDUAL:
            raise CalibrationError(
                f"the straight runs disagree by {geometry.worst_arc_residual:.1%} with one wheel size: "
                "the floor slips; calibrate on a floor that grips"
            )
        return runs

    async def _yaw(self, runs: list[Run]) -> float:
        error_deg = math.degrees(yaw_error_rad(runs))
        self.progress.update("yaw", detail=f"the lidar points {error_deg:+.2f}° off the direction of travel",
                             yaw_error_deg=round(error_deg, 3))
        return error_deg


def _describe(wiring: Wiring, wheel: str) -> tuple[str, str, str, str]:
    output = next(o for o, w in wiring.wheel_of_output.items() if w == wheel)
    encoder = next(e for e, w in wiring.wheel_of_encoder.items() if w == wheel)
    return (output, " reversed" if wiring.output_reversed[output] else "",
            encoder, " reversed" if wiring.encoder_reversed[encoder] else "")


def _thin(points: np.ndarray, voxel_m: float) -> np.ndarray:
    cells = np.floor(points / voxel_m).astype(np.int64)
    _, first = np.unique((cells[:, 0] << 32) ^ (cells[:, 1] & 0xFFFFFFFF), return_index=True)
    return np.sort(first)
