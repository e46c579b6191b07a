"""Differential-drive physics of the simulated robot: motors, wheels, slip and walls.

Why one module of ~620 lines: the motor model of each wheel, the body's kinematics and the
contact with the walls are integrated in one step (:meth:`RobotPhysics.step`) on one state; the
contact capsules (:class:`_Capsules`) are its only helper, and the model's numbered description
below is the step's.

The simulator turns motor throttles into a true pose (what the lidar is ray cast from)
and true wheel rotations (what the encoders count). The two differ the way they do on
the real robot: the wheels are not identical, the motors are not matched, the battery
sags under load and the tyres slip, so dead reckoning from the encoders drifts away
from the true pose and SLAM has something real to correct.

Model, per wheel (left and right alike):

1. Throttle ``u`` to target wheel rate. A DC gear motor does not turn until its
   torque beats static friction, then its no-load speed grows linearly with voltage::

       u_eff = sign(u) · (|u| − deadband) / (1 − deadband)      (0 when |u| < deadband)
       v* = max_wheel_speed · gain · (1 − battery_sag · (|u_l| + |u_r|) / 2) · u_eff
       ω* = v* / r_nominal                                       [rad/s]

2. Motor lag, first order ``dω/dt = (ω* − ω) / τ``, integrated exactly over a sub-step
   of length ``h`` (so any internal rate gives the same wheel motion)::

       ω(t + h) = ω* + (ω − ω*) · e^(−h/τ)
       Δφ = ∫ω dt = ω*·h + (ω − ω*) · τ · (1 − e^(−h/τ))        [rad, what the encoder sees]

3. Ground travel of the wheel: its true surface travel ``Δφ · r_true`` (``r_true`` is
   the nominal radius times the per-side diameter scale), times ``1 + ε`` with ``ε`` a
   random slip fraction. Slip changes how far the body moves, never the wheel angle.
   With ``backlash_rad`` of play between the encoder's shaft and the wheel (a cheap
   gearbox, a loose hub) the wheel follows the shaft only once the play is taken up:
   after every reversal the encoder counts up to ``backlash_rad`` the wheel never turned.
4. Turn scrub: tyres scrub sideways when the robot turns, so the body turns
   ``1 − turn_slip · |d_r − d_l| / (|d_r| + |d_l|)`` of what the wheels' travel says
   (the whole ``turn_slip`` in place, nothing driving straight).

Body, from the two ground travels ``d_l, d_r`` of a sub-step (Siegwart, Nourbakhsh &
Scaramuzza, *Introduction to Autonomous Mobile Robots*, 2nd ed., section 5.2.4)::

    Δs = (d_r + d_l) / 2,     Δθ = (d_r − d_l) / L
    Δx = Δs · sinc(Δθ/2) · cos(θ + Δθ/2),   Δy = Δs · sinc(Δθ/2) · sin(θ + Δθ/2)

with ``sinc(a) = sin(a)/a``: the chord of a circular arc, exact for constant curvature
and the straight line when ``Δθ = 0``. At steady wheel speeds the robot therefore drives
a circle of radius ``R = (L/2) · (v_r + v_l) / (v_r − v_l)``.

Walls: the robot's footprint is a circle of ``footprint_radius_m`` centred on the axle
midpoint. A sub-step whose end would put the footprint inside a wall segment or a post
is cut short at the contact: the body stops there (its translation velocity for that
step is zero) while the heading change still applies, since a round body can always
turn in place. The wheels keep turning against the wall, as a real robot's do on a
smooth floor, so the encoders keep counting while the pose stands still, which is
exactly the failure dead reckoning has to survive.

Example::

    world = World("box", segments=[[1, -1, 1, 1]], circles=[], start_pose=(0, 0, 0),
                  bounds_m=(-1, -1, 1, 1))
    robot = RobotPhysics(PhysicsParams(), world, world.start_pose, np.random.default_rng(1))
    robot.set_throttle(0.5, 0.5)
    robot.step(5.0)
    robot.x_m          # ≈ 0.91: stopped at the wall, one footprint radius off
    robot.collisions   # 1
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np

from mazebot.sim.world import World

#: Contact search resolution: a blocked sub-step is sampled at this many points along
#: its chord, so the robot stops within chord/64 (≈ 25 µm at 0.6 m/s, 400 Hz) of the wall.
_CONTACT_SAMPLES = 64
_CONTACT_FRACTIONS = (np.arange(1, _CONTACT_SAMPLES + 1) / _CONTACT_SAMPLES)[:, None]

#: A contact episode ends once the footprint is this far clear of every obstacle again.
#: The hysteresis keeps a robot scraping along a wall from counting a collision per step.
_CONTACT_RELEASE_M = 1e-3

#: How much farther than the nearest obstacle the cached neighbourhood of obstacles
#: reaches; the robot re-selects its neighbours after moving about half of this.
_NEIGHBOURHOOD_MARGIN_M = 0.05

#: Wheel-rate residuals below this (rad/s) snap to the target so that a stopped robot
#: is exactly stopped and the integrator can skip it.
_RATE_SNAP_RAD_S = 1e-9


@dataclass(frozen=True)
class PhysicsParams:
    """Physical constants of the simulated robot; defaults are the reference robot.

    Every field is a plain number with its unit in the name, so a ``[sim]`` section of
    ``config.toml`` can map onto it key for key. The defaults include realistic
    imperfections (motor and wheel mismatch, slip); :meth:`ideal` gives a perfectly
    matched, slip-free robot for checks against closed-form motion.
    """

    # Nominal drive wheel diameter: what the odometry assumes.
    wheel_diameter_m: float = 0.065
    # Distance between the two wheels' contact points (L in the kinematics).
    track_width_m: float = 0.15
    # Wheel surface speed at full throttle on a fresh battery (before battery_sag).
    max_wheel_speed_mps: float = 0.6
    # First-order lag of the wheel speed towards its target while driven or coasting
    # (throttle None or inside the deadband), in seconds.
    motor_time_constant_s: float = 0.08
    # The same lag when the throttle is exactly 0: the motor driver shorts the winding
    # (TB6612 short brake), so the wheel stops faster than it coasts.
    brake_time_constant_s: float = 0.04
    # |throttle| below this cannot overcome static friction: no motion. Above it the
    # speed grows linearly to full speed at |throttle| = 1. Dimensionless, [0, 1).
    deadband: float = 0.08
    # Per-side speed gain of motor + gearbox: unmatched motors curve a "straight" drive.
    gain_left: float = 1.0
    gain_right: float = 0.97
    # Fractional speed loss per unit of mean throttle demand (|u_l| + |u_r|) / 2: at full
    # throttle on both motors the wheels run (1 - battery_sag) times slower.
    battery_sag: float = 0.05
    # True wheel diameter over the nominal one, per side: unequal tyres, an odometry
    # error the encoders cannot see.
    wheel_diameter_left_scale: float = 1.0
    wheel_diameter_right_scale: float = 1.004
    # Standard deviation of the random slip fraction, per wheel and per sub-step at
    # rate_hz: the ground travel of a wheel is its surface travel times (1 + N(0, slip_std)).
    slip_std: float = 0.01
    # Play (radians of wheel rotation) between the encoder's shaft and the wheel, and the
    # share of an in-place turn lost to scrubbing tyres (see the module docstring, 3 and 4).
    backlash_rad: float = 0.0
    turn_slip: float = 0.0
    # Radius of a circle, centred on the axle midpoint, that holds the whole robot.
    footprint_radius_m: float = 0.09
    # Internal integration rate in Hz; step() sub-steps at least this finely.
    rate_hz: float = 400.0

    def __post_init__(self) -> None:
        positive = (
            "wheel_diameter_m",
            "track_width_m",
            "max_wheel_speed_mps",
            "motor_time_constant_s",
            "brake_time_constant_s",
            "gain_left",
            "gain_right",
            "wheel_diameter_left_scale",
            "wheel_diameter_right_scale",
            "footprint_radius_m",
        )
        for f in fields(self):
            value = getattr(self, f.name)
            if not math.isfinite(value):
                raise ValueError(f"physics parameter {f.name} must be finite, got {value!r}")
            if f.name in positive and value <= 0:
                raise ValueError(f"physics parameter {f.name} must be > 0, got {value!r}")
        if not 0.0 <= self.deadband < 1.0:
            raise ValueError(f"physics parameter deadband must be in [0, 1), got {self.deadband!r}")
        if not 0.0 <= self.battery_sag < 1.0:
            raise ValueError(
                f"physics parameter battery_sag must be in [0, 1), got {self.battery_sag!r}"
            )
        if self.slip_std < 0:
            raise ValueError(f"physics parameter slip_std must be >= 0, got {self.slip_std!r}")
        if self.backlash_rad < 0 or not 0.0 <= self.turn_slip < 1.0:
            raise ValueError(
                f"physics parameters backlash_rad must be >= 0 and turn_slip in [0, 1), "
                f"got {self.backlash_rad!r}, {self.turn_slip!r}"
            )
        if self.rate_hz < 200:
            raise ValueError(
                f"physics parameter rate_hz must be >= 200 to resolve the motor lag, "
                f"got {self.rate_hz!r}"
            )

    @classmethod
    def ideal(cls, **overrides: float) -> PhysicsParams:
        """A robot with matched motors, identical wheels and no slip.

        It still has the deadband, motor lag and battery sag (they are symmetric and
        deterministic), so its motion has closed forms to test against.
        """
        values: dict[str, float] = {
            "gain_left": 1.0,
            "gain_right": 1.0,
            "wheel_diameter_left_scale": 1.0,
            "wheel_diameter_right_scale": 1.0,
            "slip_std": 0.0,
        }
        values.update(overrides)
        return replace(cls(), **values)


class _Capsules:
    """Obstacles as capsules (a segment swept by a radius), for clearance queries.

    A wall surface is a capsule of radius 0, a post a capsule of length 0; one set of
    arrays then serves both. The distance from point p to a capsule with end a,
    direction d and radius ρ is ``|p − (a + t·d)| − ρ`` with
    ``t = clip((p − a)·d / |d|², 0, 1)``, the closest point on the segment.
    """

    def __init__(
        self,
        ax: np.ndarray,
        ay: np.ndarray,
        dx: np.ndarray,
        dy: np.ndarray,
        radius: np.ndarray,
    ) -> None:
        self.ax, self.ay, self.dx, self.dy, self.radius = ax, ay, dx, dy, radius
        length2 = dx * dx + dy * dy
        # A zero-length segment (a post) has t = 0: its closest point is its centre.
        self.inv_length2 = np.divide(1.0, length2, out=np.zeros_like(length2), where=length2 > 0)

    @classmethod
    def from_world(cls, world: World) -> _Capsules:
        seg, circ = world.segments, world.circles
        return cls(
            ax=np.concatenate([seg[:, 0], circ[:, 0]]),
            ay=np.concatenate([seg[:, 1], circ[:, 1]]),
            dx=np.concatenate([seg[:, 2] - seg[:, 0], np.zeros(len(circ))]),
            dy=np.concatenate([seg[:, 3] - seg[:, 1], np.zeros(len(circ))]),
            radius=np.concatenate([np.zeros(len(seg)), circ[:, 2]]),
        )

    def __len__(self) -> int:
        return len(self.ax)

    def subset(self, mask: np.ndarray) -> _Capsules:
        return _Capsules(
            self.ax[mask], self.ay[mask], self.dx[mask], self.dy[mask], self.radius[mask]
        )

    def distances_m(self, px: float | np.ndarray, py: float | np.ndarray) -> np.ndarray:
        """Surface distances from points to every capsule; negative inside a post.

        ``px, py`` are scalars (result shape (n,)) or column arrays of shape (k, 1)
        (result shape (k, n)).
        """
        ux = px - self.ax
        uy = py - self.ay
        t = np.clip((ux * self.dx + uy * self.dy) * self.inv_length2, 0.0, 1.0)
        return np.hypot(ux - t * self.dx, uy - t * self.dy) - self.radius


class RobotPhysics:
    """The true motion of the simulated robot in a static world.

    Set the throttles with :meth:`set_throttle` (what the fake motor HAT forwards), then
    advance time with :meth:`step`. Read the true pose for ray casting, the true wheel
    angles for the encoders, and ``collisions`` / ``in_contact`` for ground truth.

    Example::

        rng = np.random.default_rng(7)
        robot = RobotPhysics(PhysicsParams(), world, world.start_pose, rng)
        robot.set_throttle(0.4, 0.4)
        for _ in range(100):
            robot.step(0.01)                 # any dt: sub-steps at params.rate_hz
        x_m, y_m, theta_rad = robot.pose
        left_rad, right_rad = robot.wheel_angle_rad

    ``rng`` draws the wheel slip; with ``slip_std = 0`` it is never used and the motion
    is deterministic.
    """

    def __init__(
        self,
        params: PhysicsParams,
        world: World,
        start_pose: tuple[float, float, float],
        rng: np.random.Generator,
    ) -> None:
        self.params = params
        self.world = world
        self._rng = rng
        self._obstacles = _Capsules.from_world(world)

        radius_nominal_m = 0.5 * params.wheel_diameter_m
        self._radius_nominal_m = radius_nominal_m
        self._radius_left_m = radius_nominal_m * params.wheel_diameter_left_scale
        self._radius_right_m = radius_nominal_m * params.wheel_diameter_right_scale

        x_m, y_m, theta_rad = (float(v) for v in start_pose)
        self._x_m, self._y_m = x_m, y_m
        self._theta_rad = math.remainder(theta_rad, math.tau)
        clearance_m = self._clearance_m(x_m, y_m)
        if clearance_m < params.footprint_radius_m:
            raise ValueError(
                f"start pose ({x_m:.3f}, {y_m:.3f}) of world {world.name!r} puts the robot "
                f"footprint inside an obstacle: clearance {clearance_m:.3f} m < footprint "
                f"radius {params.footprint_radius_m:.3f} m; move the start or shrink the footprint"
            )
        # Distance the body may still move before a wall check is needed: the clearance
        # is 1-Lipschitz in position, so it cannot drop by more than the path travelled.
        self._free_m = clearance_m - params.footprint_radius_m
        self._near = self._obstacles
        self._near_centre_m = (x_m, y_m)
        self._near_reach_m = math.inf
        if len(self._obstacles):
            self._refresh_neighbourhood(x_m, y_m, 0.0)

        self._throttle: tuple[float | None, float | None] = (None, None)
        self._rate_left_rad_s = 0.0
        self._rate_right_rad_s = 0.0
        self._angle_left_rad = 0.0
        self._angle_right_rad = 0.0
        # where each wheel stands within the play of its shaft: wheel angle minus shaft angle
        self._play_left_rad = 0.0
        self._play_right_rad = 0.0
        self._body_speed_mps = 0.0
        self._body_rate_rad_s = 0.0
        self._collisions = 0
        self._in_contact = False
        self._odometer_m = 0.0
        self._time_s = 0.0
        #: share of each wheel's surface travel that reaches the ground, (left, right): 1 grips,
        #: below 1 the tyre spins on the floor (a wet patch, dust): the encoder counts, the body lags
        self.grip = (1.0, 1.0)

    # -- state ---------------------------------------------------------------------------

    @property
    def pose(self) -> tuple[float, float, float]:
        """True pose ``(x_m, y_m, theta_rad)`` of the axle midpoint, world frame."""
        return (self._x_m, self._y_m, self._theta_rad)

    @property
    def x_m(self) -> float:
        return self._x_m

    @property
    def y_m(self) -> float:
        return self._y_m

    @property
    def theta_rad(self) -> float:
        """Heading, counter-clockwise from the world x axis, in (−π, π]."""
        return self._theta_rad

    @property
    def throttle(self) -> tuple[float | None, float | None]:
        """The commanded ``(left, right)`` throttles; None is coasting."""
        return self._throttle

    @property
    def wheel_rate_rad_s(self) -> tuple[float, float]:
        """Wheel angular speeds ``(left, right)`` in rad/s."""
        return (self._rate_left_rad_s, self._rate_right_rad_s)

    @property
    def wheel_speed_mps(self) -> tuple[float, float]:
        """True wheel surface speeds ``(left, right)`` in m/s (before slip)."""
        return (
            self._rate_left_rad_s * self._radius_left_m,
            self._rate_right_rad_s * self._radius_right_m,
        )

    @property
    def wheel_angle_rad(self) -> tuple[float, float]:
        """Cumulative true wheel rotation ``(left, right)`` in radians, forward positive.

        This is what a quadrature encoder on the wheel shaft counts: slip and walls do
        not change it, they only change how far the body moves for it.
        """
        return (self._angle_left_rad, self._angle_right_rad)

    @property
    def body_velocity(self) -> tuple[float, float]:
        """``(v_mps, omega_rad_s)`` of the body over the last sub-step; v is 0 at a wall."""
        return (self._body_speed_mps, self._body_rate_rad_s)

    @property
    def collisions(self) -> int:
        """Number of contact episodes so far (entering contact with a wall or post)."""
        return self._collisions

    @property
    def in_contact(self) -> bool:
        """True from the step the footprint hits an obstacle until it is 1 mm clear again."""
        return self._in_contact

    @property
    def odometer_m(self) -> float:
        """True path length of the axle midpoint in metres (forward and back both add)."""
        return self._odometer_m

    @property
    def time_s(self) -> float:
        """Simulated time in seconds since construction."""
        return self._time_s

    def true_wheel_travel_m(self) -> tuple[float, float]:
        """Distance ``(left, right)`` each wheel has rolled at its surface, in metres.

        Equal to the body's travel for straight motion without slip or walls; the
        encoders would report this times ``wheel_diameter_m / true diameter``.
        """
        return (
            self._angle_left_rad * self._radius_left_m,
            self._angle_right_rad * self._radius_right_m,
        )

    # -- commands ------------------------------------------------------------------------

    def set_throttle(self, left: float | None, right: float | None) -> None:
        """Command both motors, like ``MotorKit.motorN.throttle``.

        Each value is in [−1, 1], or None to coast (motor disconnected: the wheel slows
        with ``motor_time_constant_s``). Exactly 0 brakes (winding shorted: the wheel
        slows with the shorter ``brake_time_constant_s``).
        """
        for side, value in (("left", left), ("right", right)):
            if value is not None and not -1.0 <= value <= 1.0:
                raise ValueError(
                    f"{side} throttle must be in [-1, 1] or None (coast), got {value!r}"
                )
        self._throttle = (
            None if left is None else float(left),
            None if right is None else float(right),
        )

    def step(self, dt_s: float) -> None:
        """Advance the simulation by ``dt_s`` seconds with the current throttles.

        The interval is split into equal sub-steps no longer than ``1 / rate_hz``, so
        ``step(0.1)`` and ten ``step(0.01)`` take the same sub-steps and, without slip,
        end in the same pose.
        """
        if not dt_s >= 0.0 or not math.isfinite(dt_s):
            raise ValueError(f"step dt_s must be a finite number >= 0, got {dt_s!r}")
        if dt_s == 0.0:
            return
        p = self.params
        n_steps = max(1, math.ceil(dt_s * p.rate_hz * (1.0 - 1e-12)))
        h_s = dt_s / n_steps
        self._time_s += dt_s

        (target_l, tau_l), (target_r, tau_r) = self._targets_rad_s()
        if (
            target_l == 0.0
            and target_r == 0.0
            and self._rate_left_rad_s == 0.0
            and self._rate_right_rad_s == 0.0
        ):
            self._body_speed_mps = self._body_rate_rad_s = 0.0
            return

        # Exact first-order-lag discretisation (module docstring, step 2).
        decay_l, decay_r = math.exp(-h_s / tau_l), math.exp(-h_s / tau_r)
        gain_l, gain_r = tau_l * (1.0 - decay_l), tau_r * (1.0 - decay_r)
        if p.slip_std > 0.0:
            # slip_std is per sub-step at rate_hz; finer sub-steps get proportionally
            # larger independent slips so the slip per second does not depend on dt.
            std = p.slip_std * math.sqrt(1.0 / (p.rate_hz * h_s))
            slip = 1.0 + self._rng.normal(0.0, std, size=(n_steps, 2))
        else:
            slip = np.ones((n_steps, 2))

        radius_l, radius_r = self._radius_left_m * self.grip[0], self._radius_right_m * self.grip[1]
        inv_track_per_m = 1.0 / p.track_width_m
        half_play = 0.5 * p.backlash_rad
        rate_l, rate_r = self._rate_left_rad_s, self._rate_right_rad_s
        fraction = ds = dtheta = 0.0
        for slip_l, slip_r in slip.tolist():
            # 1. Wheels: rotation this sub-step (what the encoders count), then new rate.
            dphi_l = target_l * h_s + (rate_l - target_l) * gain_l
            dphi_r = target_r * h_s + (rate_r - target_r) * gain_r
            rate_l = target_l + (rate_l - target_l) * decay_l
            rate_r = target_r + (rate_r - target_r) * decay_r
            self._angle_left_rad += dphi_l
            self._angle_right_rad += dphi_r
            if half_play > 0.0:  # the wheel moves only once the shaft has taken up the play
                play_l = min(max(self._play_left_rad - dphi_l, -half_play), half_play)
                play_r = min(max(self._play_right_rad - dphi_r, -half_play), half_play)
                dphi_l += play_l - self._play_left_rad
                dphi_r += play_r - self._play_right_rad
                self._play_left_rad, self._play_right_rad = play_l, play_r

            # 2. Body: ground travel of each wheel, then the exact arc.
            d_l = dphi_l * radius_l * slip_l
            d_r = dphi_r * radius_r * slip_r
            ds = 0.5 * (d_r + d_l)
            dtheta = (d_r - d_l) * inv_track_per_m
            if p.turn_slip > 0.0 and dtheta != 0.0:
                dtheta *= 1.0 - p.turn_slip * abs(d_r - d_l) / (abs(d_r) + abs(d_l))
            half = 0.5 * dtheta
            chord = ds if abs(half) < 1e-9 else ds * math.sin(half) / half
            heading = self._theta_rad + half

            # 3. Walls: translate as far as the footprint allows; always turn.
            fraction = self._translate(chord * math.cos(heading), chord * math.sin(heading))
            self._theta_rad = math.remainder(self._theta_rad + dtheta, math.tau)
            self._odometer_m += fraction * abs(ds)

        if abs(rate_l - target_l) < _RATE_SNAP_RAD_S:
            rate_l = target_l
        if abs(rate_r - target_r) < _RATE_SNAP_RAD_S:
            rate_r = target_r
        self._rate_left_rad_s, self._rate_right_rad_s = rate_l, rate_r
        self._body_speed_mps = fraction * ds / h_s
        self._body_rate_rad_s = dtheta / h_s

    def teleport(self, x_m: float, y_m: float, theta_rad: float) -> None:
        """Put the robot somewhere else at once (someone picked it up): the wheels never turned.

        Raises ValueError if the footprint would overlap an obstacle there.
        """
        clearance_m = self._clearance_m(x_m, y_m)
        if clearance_m < self.params.footprint_radius_m:
            raise ValueError(
                f"cannot put the robot at ({x_m:.3f}, {y_m:.3f}): clearance {clearance_m:.3f} m "
                f"< footprint radius {self.params.footprint_radius_m:.3f} m"
            )
        self._x_m, self._y_m = float(x_m), float(y_m)
        self._theta_rad = math.remainder(float(theta_rad), math.tau)
        self._free_m = clearance_m - self.params.footprint_radius_m
        self._in_contact = False
        if len(self._obstacles):
            self._refresh_neighbourhood(self._x_m, self._y_m, 0.0)

    def clearance_m(self, x_m: float, y_m: float) -> float:
        """Distance from a point to the nearest wall or post surface (inf in an empty world)."""
        return self._clearance_m(x_m, y_m)

    # -- internals -----------------------------------------------------------------------

    def _targets_rad_s(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """``((ω*_l, τ_l), (ω*_r, τ_r))`` for the current throttles (docstring, step 1)."""
        p = self.params
        left, right = self._throttle
        demand = 0.5 * (abs(left or 0.0) + abs(right or 0.0))
        full_rad_s = p.max_wheel_speed_mps * (1.0 - p.battery_sag * demand) / self._radius_nominal_m

        def one(throttle: float | None, gain: float) -> tuple[float, float]:
            if throttle is None:
                return 0.0, p.motor_time_constant_s
            if throttle == 0.0:
                return 0.0, p.brake_time_constant_s
            magnitude = abs(throttle)
            if magnitude < p.deadband:
                return 0.0, p.motor_time_constant_s
            effective = math.copysign((magnitude - p.deadband) / (1.0 - p.deadband), throttle)
            return full_rad_s * gain * effective, p.motor_time_constant_s

        return one(left, p.gain_left), one(right, p.gain_right)

    def _clearance_m(self, x_m: float, y_m: float) -> float:
        """Distance from a point to the nearest obstacle surface (inf in an empty world)."""
        if len(self._obstacles) == 0:
            return math.inf
        return float(self._obstacles.distances_m(x_m, y_m).min())

    def _refresh_neighbourhood(self, x_m: float, y_m: float, move_m: float) -> None:
        """Keep only the obstacles the footprint can reach from near ``(x_m, y_m)``.

        With centre c and reach ρ, an obstacle left out is more than ``r + ρ`` from c,
        so for any point q closer than ρ to c it is more than ``r + ρ − |q − c|`` away:
        it cannot block q, and that bound stands in for its clearance. Walls are then
        checked against a handful of capsules instead of the whole maze.
        """
        radius_m = self.params.footprint_radius_m
        distances_m = self._obstacles.distances_m(x_m, y_m)
        slack_m = max(0.0, float(distances_m.min()) - radius_m)
        reach_m = _NEIGHBOURHOOD_MARGIN_M + max(2.0 * move_m, slack_m)
        self._near = self._obstacles.subset(distances_m < radius_m + reach_m)
        self._near_centre_m = (x_m, y_m)
        self._near_reach_m = reach_m

    def _translate(self, dx_m: float, dy_m: float) -> float:
        """Move the footprint centre by ``(dx_m, dy_m)`` up to the first contact.

        Returns the fraction of the move made (1 when free). Entering contact counts a
        collision; contact ends when the clearance exceeds the release margin.
        """
        move_m = math.hypot(dx_m, dy_m)
        if move_m == 0.0:
            return 1.0
        if not self._in_contact and move_m <= self._free_m:
            self._x_m += dx_m
            self._y_m += dy_m
            self._free_m -= move_m
            return 1.0

        # Only reached near an obstacle: in an empty world _free_m is infinite.
        radius_m = self.params.footprint_radius_m
        x0_m, y0_m = self._x_m, self._y_m
        x1_m, y1_m = x0_m + dx_m, y0_m + dy_m
        cx_m, cy_m = self._near_centre_m
        if math.hypot(x1_m - cx_m, y1_m - cy_m) + move_m >= 0.5 * self._near_reach_m:
            self._refresh_neighbourhood(x0_m, y0_m, move_m)
            cx_m, cy_m = x0_m, y0_m
        near = self._near
        near_min_m = float(near.distances_m(x1_m, y1_m).min()) if len(near) else math.inf
        if near_min_m >= radius_m:
            far_bound_m = radius_m + self._near_reach_m - math.hypot(x1_m - cx_m, y1_m - cy_m)
            clearance_m = min(near_min_m, far_bound_m)
            self._x_m, self._y_m = x1_m, y1_m
            self._free_m = clearance_m - radius_m
            if clearance_m >= radius_m + _CONTACT_RELEASE_M:
                self._in_contact = False
            return 1.0

        # Blocked: stop at the last of evenly spaced points along the move that is clear.
        sample_d = near.distances_m(
            x0_m + _CONTACT_FRACTIONS * dx_m, y0_m + _CONTACT_FRACTIONS * dy_m
        ).min(axis=1)
        first_blocked = int(np.argmax(sample_d < radius_m))
        fraction = first_blocked / _CONTACT_SAMPLES
        self._x_m = x0_m + fraction * dx_m
        self._y_m = y0_m + fraction * dy_m
        self._free_m = 0.0
        if not self._in_contact:
            self._in_contact = True
            self._collisions += 1
        return fraction
