"""Domain randomisation: how far the simulated world departs from the robot description.

A :class:`Randomization` holds ranges; at each ``reset`` the simulator draws from them
(:meth:`Randomization.draw`, with the env's ``np_random``) the robot it builds and the
world it puts it in (:class:`WorldDraw`). The estimators keep the nominal description,
as they would with a real robot: that is the honest sim-to-real setting. The draws go to
``info["randomization"]`` at reset and into a recording's run info.

Named presets (``"mild"``, ``"strong"``, and ``"description"``: the description's own
error alone, the world built from a robot whose geometry, motors and cables are not
quite the ones the estimator is handed) are found in :data:`RANDOMIZATIONS`; a lab adds
its own with :func:`register_randomization`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from numbers import Real
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from tensegrity_gym.model.description import Cable, RobotDescription, Rod, SensorSuite

__all__ = [
    "RANDOMIZATIONS",
    "Randomization",
    "WorldDraw",
    "register_randomization",
    "resolve_randomization",
]

Interval = tuple[float, float]
"""(low, high), drawn uniformly."""


@dataclass(frozen=True)
class Randomization:
    """Ranges of the world's departures from the description, each ``(low, high)``.

    Scales multiply the description's value (1 = nominal); each rod, cable and motor
    draws its own. Rest-length offsets are shares of the cable's rest length (a passive
    cable cut long or short; an actuated cable's encoder zero off). Every range at its
    nominal value draws nothing, so a world without randomisation is unchanged.
    """

    rod_mass: Interval = (1.0, 1.0)
    """Scale of each rod's mass."""
    rod_length: Interval = (1.0, 1.0)
    """Scale of each rod's length (its endcaps' distance); the rod stays centred."""
    endcap_offset: Interval = (0.0, 0.0)
    """m by which each endcap, where the cables attach, sits further out along its rod
    than the description says (negative: further in). Both ends draw, and the rod's
    length between its endcaps grows by their sum; the rod's mass stays centred between
    them, so the draw moves where the cables pull, not the rod's balance."""
    cable_stiffness: Interval = (1.0, 1.0)
    """Scale of each cable's stiffness."""
    cable_damping: Interval = (1.0, 1.0)
    """Scale of each cable's damping."""
    passive_rest_offset: Interval = (0.0, 0.0)
    """Share of its rest length added to each passive cable's."""
    actuated_rest_offset: Interval = (0.0, 0.0)
    """Share of its nominal rest length by which each actuated cable is longer than its
    encoder reads (a zero set off): the motors drive their encoders to the commands."""
    friction: Interval = (1.0, 1.0)
    """Scale of the ground's friction coefficients (lateral, rolling, spinning)."""
    restitution: Interval | None = None
    """The ground's restitution, drawn in this range; None: the description's."""
    motor_speed: Interval = (1.0, 1.0)
    """Scale of each motor's top speed."""
    motor_range_offset: Interval = (0.0, 0.0)
    """m by which each motor's rest-length range (its limits) is shifted: a motor that
    cannot reach the commands at one end of the description's range."""
    encoder_zero: Interval = (0.0, 0.0)
    """m by which each actuated cable is longer than its encoder reads, on top of
    :attr:`actuated_rest_offset`'s share (an encoder zero set off by a fixed length)."""
    command_latency: Interval = (0.0, 0.0)
    """Seconds between a command and the motors acting on it."""
    imu_noise: Interval = (1.0, 1.0)
    """Scale of the IMU's noise and bias standard deviations."""
    uwb_packet_loss: Interval | None = None
    """Range of the share of UWB packets lost per episode; None: the description's."""
    uwb_noise: Interval = (1.0, 1.0)
    """Scale of the UWB timestamp noise (the range noise)."""
    camera_depth_noise: Interval = (1.0, 1.0)
    """Scale of the depth camera's noise."""
    gravity_tilt: Interval = (0.0, 0.0)
    """Angle (rad) between gravity and the ground's normal (a slope), its direction
    uniform about z."""

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None:
                continue
            low, high = _interval(value, f.name)
            object.__setattr__(self, f.name, (low, high))  # plain floats, hashable
            if f.name in _SCALES and low <= 0.0:
                raise ValueError(f"Randomization.{f.name}={value!r}: a scale must be > 0")
            if f.name in _SHARES and not (0.0 <= low and high < 1.0):
                raise ValueError(f"Randomization.{f.name}={value!r} must lie in [0, 1)")
            if f.name in _OFFSETS and not (-0.5 < low and high < 0.5):
                raise ValueError(f"Randomization.{f.name}={value!r} must lie in (-0.5, 0.5)")
            if f.name in _NON_NEGATIVE and low < 0.0:
                raise ValueError(f"Randomization.{f.name}={value!r} must be >= 0")
            if f.name in _LENGTHS and not (-_MAX_LENGTH_ERROR < low and high < _MAX_LENGTH_ERROR):
                raise ValueError(
                    f"Randomization.{f.name}={value!r} must lie in "
                    f"(-{_MAX_LENGTH_ERROR:g}, {_MAX_LENGTH_ERROR:g}) m"
                )
        if self.gravity_tilt[1] >= 0.5 * np.pi:
            raise ValueError(f"Randomization.gravity_tilt={self.gravity_tilt!r} must be < pi/2")

    def _cable(self, c: Cable, u: _Uniform) -> tuple[Cable, float]:
        """A cable as drawn, and its encoder's offset (m): how much longer the cable is
        than the encoder reads (0 for a passive cable, whose own length is drawn)."""
        offset = u(self.actuated_rest_offset if c.actuated else self.passive_rest_offset)
        motor = c.motor
        if motor is not None:
            motor = replace(motor, max_speed=motor.max_speed * u(self.motor_speed))
        drawn = replace(
            c,
            stiffness=c.stiffness * u(self.cable_stiffness),
            damping=c.damping * u(self.cable_damping),
            rest_length=c.rest_length if c.actuated else c.rest_length * (1.0 + offset),
            motor=motor,
        )
        if not c.actuated:
            return drawn, 0.0
        zero = offset * c.rest_length + u(self.encoder_zero)
        if motor is not None:  # drawn after the rest, so that older presets draw as before
            shift = u(self.motor_range_offset)
            low, high = motor.min_rest_length + shift, motor.max_rest_length + shift
            if low <= 0.0:
                raise ValueError(
                    f"Randomization.motor_range_offset={self.motor_range_offset!r} moves "
                    f"cable {c.name!r}'s motor range to {low:.4g}-{high:.4g} m (not > 0)"
                )
            motor = replace(motor, min_rest_length=low, max_rest_length=high)
            drawn = replace(drawn, motor=motor)
        return drawn, zero

    def _rod(self, rod: Rod, u: _Uniform) -> Rod:
        """A rod as drawn: its mass, its length and where its endcaps sit."""
        mass = rod.mass * u(self.rod_mass)
        length = rod.length * u(self.rod_length) + u(self.endcap_offset) + u(self.endcap_offset)
        if length <= 2.0 * rod.endcap_radius:
            raise ValueError(
                f"Randomization.rod_length={self.rod_length!r} and endcap_offset="
                f"{self.endcap_offset!r} leave rod {rod.name!r} {length:.4g} m long, no longer "
                "than its endcaps"
            )
        return replace(rod, mass=mass, length=length)

    def draw(self, description: RobotDescription, rng: np.random.Generator) -> WorldDraw:
        """The world of one episode: the robot the simulator builds, gravity, latency.
        Draws from ``rng`` in a fixed order, only for ranges that are not nominal."""
        u = _Uniform(rng)
        rods = tuple(self._rod(r, u) for r in description.rods)
        drawn = [self._cable(c, u) for c in description.cables]
        cables = tuple(c for c, _ in drawn)
        encoder_offsets = np.array([offset for _, offset in drawn])
        g = description.ground
        scale = u(self.friction)
        ground = replace(
            g,
            lateral_friction=g.lateral_friction * scale,
            rolling_friction=g.rolling_friction * scale,
            spinning_friction=g.spinning_friction * scale,
            restitution=g.restitution if self.restitution is None else u(self.restitution),
        )
        sensors = _sensors(self, description, u)
        robot = replace(description, rods=rods, cables=cables, ground=ground, sensors=sensors)
        down = np.array([0.0, 0.0, -1.0])
        if self.gravity_tilt[1] > 0.0:
            tilt, azimuth = u(self.gravity_tilt), u((0.0, 2.0 * np.pi))
            down = np.array([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth),
                             -np.cos(tilt)])  # fmt: skip
        latency = u(self.command_latency)
        return WorldDraw(robot, description.gravity * down, latency, encoder_offsets, u.draws)


def _interval(value: Any, name: str) -> Interval:
    """``value`` as a (low, high) pair of floats: any two real numbers (numpy's
    float32 too), finite, low <= high; else ValueError saying which of these fails."""
    where = f"Randomization.{name}={value!r}"
    if isinstance(value, (str, bytes)) or not isinstance(value, (tuple, list, np.ndarray)):
        raise ValueError(f"{where} must be a (low, high) pair")
    if len(value) != 2:
        raise ValueError(f"{where} must be a (low, high) pair, got {len(value)} values")
    if not all(isinstance(v, Real) and not isinstance(v, (bool, np.bool_)) for v in value):
        raise ValueError(f"{where}: low and high must be numbers")
    low, high = float(value[0]), float(value[1])
    if not (math.isfinite(low) and math.isfinite(high)):
        raise ValueError(f"{where}: low and high must be finite")
    if low > high:
        raise ValueError(f"{where} must have low <= high")
    return low, high


_SCALES = ("rod_mass", "rod_length", "cable_stiffness", "cable_damping", "friction", "motor_speed",
           "imu_noise", "uwb_noise", "camera_depth_noise")  # fmt: skip
_SHARES = ("uwb_packet_loss", "restitution")
_OFFSETS = ("passive_rest_offset", "actuated_rest_offset")
_NON_NEGATIVE = ("command_latency", "gravity_tilt")
_LENGTHS = ("endcap_offset", "motor_range_offset", "encoder_zero")
_MAX_LENGTH_ERROR = 0.5
"""m: the largest length error a range may reach (a bigger one is a unit mistake)."""


class _Uniform:
    """Draws ``uniform(low, high)``; a range of one value draws nothing and gives it."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.draws = 0

    def __call__(self, interval: Interval) -> float:
        low, high = interval
        if low == high:
            return float(low)
        self.draws += 1
        return float(self.rng.uniform(low, high))


def _sensors(r: Randomization, d: RobotDescription, u: _Uniform) -> SensorSuite:
    s = d.sensors
    imu_scale = u(r.imu_noise)
    imu = replace(
        s.imu,
        accel_noise=s.imu.accel_noise * imu_scale,
        gyro_noise=s.imu.gyro_noise * imu_scale,
        accel_bias=s.imu.accel_bias * imu_scale,
        gyro_bias=s.imu.gyro_bias * imu_scale,
    )
    uwb = replace(
        s.uwb,
        timestamp_noise=s.uwb.timestamp_noise * u(r.uwb_noise),
        reject_fraction=s.uwb.reject_fraction if r.uwb_packet_loss is None else r.uwb_packet_loss,
    )
    depth = u(r.camera_depth_noise)
    camera = replace(
        s.camera,
        depth_noise=s.camera.depth_noise * depth,
        depth_noise_quadratic=s.camera.depth_noise_quadratic * depth,
    )
    return replace(s, imu=imu, uwb=uwb, camera=camera)


@dataclass(frozen=True)
class WorldDraw:
    """One episode's world, drawn by :meth:`Randomization.draw`."""

    robot: RobotDescription
    """The robot the simulator builds (masses, cables, motors, ground, sensor noise);
    never handed to an estimator."""
    gravity: NDArray[np.float64]
    """(3,) m/s^2, the gravity vector in the world frame (tilted on a slope)."""
    command_latency: float
    """Seconds between a command and the motors acting on it."""
    encoder_offsets: NDArray[np.float64]
    """(n_cables,) m by which each actuated cable is longer than its encoder reads (0 for
    the passive ones): the motors drive their encoders to the commands."""
    n_draws: int
    """Numbers drawn from the rng."""

    def summary(self, nominal: RobotDescription) -> dict[str, Any]:
        """The draws as plain numbers (``info["randomization"]``, the run info): each
        scale against ``nominal``, per rod, cable and motor."""
        r, n = self.robot, nominal
        pairs = list(zip(r.cables, n.cables, strict=True))
        motors = [(a.motor, b.motor) for a, b in pairs if a.motor is not None and b.motor]
        tilt = np.arccos(-self.gravity[2] / np.linalg.norm(self.gravity))
        return {
            "rod_mass": [_ratio(a.mass, b.mass) for a, b in zip(r.rods, n.rods, strict=True)],
            "rod_length": [_ratio(a.length, b.length) for a, b in zip(r.rods, n.rods, strict=True)],
            "cable_stiffness": [_ratio(a.stiffness, b.stiffness) for a, b in pairs],
            "cable_damping": [_ratio(a.damping, b.damping) for a, b in pairs],
            "rest_length_offset": [
                round(_ratio(a.rest_length + e, b.rest_length) - 1.0, 5)
                for (a, b), e in zip(pairs, self.encoder_offsets, strict=True)
            ],
            "motor_speed": [_ratio(a.max_speed, b.max_speed) for a, b in motors],
            "motor_range_offset_m": [
                round(a.min_rest_length - b.min_rest_length, 5) for a, b in motors
            ],
            # m each actuated cable is longer than its encoder reads: the zero and the
            # share of actuated_rest_offset together.
            "encoder_zero_m": [
                round(float(e), 5)
                for (a, _), e in zip(pairs, self.encoder_offsets, strict=True)
                if a.actuated
            ],
            "friction": _ratio(r.ground.lateral_friction, n.ground.lateral_friction),
            "restitution": round(r.ground.restitution, 4),
            "imu_noise": _ratio(r.sensors.imu.accel_noise, n.sensors.imu.accel_noise),
            "uwb_noise": _ratio(r.sensors.uwb.timestamp_noise, n.sensors.uwb.timestamp_noise),
            "uwb_packet_loss": [round(v, 4) for v in r.sensors.uwb.reject_fraction],
            "camera_depth_noise": _ratio(
                r.sensors.camera.depth_noise, n.sensors.camera.depth_noise
            ),
            "gravity_tilt_deg": round(float(np.degrees(tilt)), 3),
            "command_latency_s": round(self.command_latency, 4),
        }


def _ratio(value: float, nominal: float) -> float:
    return round(float(value) / float(nominal), 5) if nominal else 1.0


RANDOMIZATIONS: dict[str, Randomization] = {
    "mild": Randomization(
        rod_mass=(0.9, 1.1),
        cable_stiffness=(0.85, 1.15),
        cable_damping=(0.7, 1.3),
        passive_rest_offset=(-0.01, 0.01),
        actuated_rest_offset=(-0.005, 0.005),
        friction=(0.8, 1.2),
        restitution=(0.0, 0.1),
        motor_speed=(0.9, 1.1),
        command_latency=(0.0, 0.02),
        imu_noise=(1.0, 2.0),
        uwb_packet_loss=(0.3, 0.8),
        uwb_noise=(1.0, 1.5),
        camera_depth_noise=(1.0, 1.5),
        gravity_tilt=(0.0, float(np.radians(2.0))),
    ),
    "strong": Randomization(
        rod_mass=(0.75, 1.25),
        rod_length=(0.98, 1.02),
        endcap_offset=(-0.01, 0.01),
        motor_range_offset=(-0.03, 0.03),
        encoder_zero=(-0.03, 0.03),
        cable_stiffness=(0.7, 1.3),
        cable_damping=(0.5, 1.5),
        passive_rest_offset=(-0.03, 0.03),
        actuated_rest_offset=(-0.015, 0.015),
        friction=(0.6, 1.4),
        restitution=(0.0, 0.3),
        motor_speed=(0.75, 1.25),
        command_latency=(0.0, 0.05),
        imu_noise=(1.0, 4.0),
        uwb_packet_loss=(0.3, 0.9),
        uwb_noise=(1.0, 2.0),
        camera_depth_noise=(1.0, 2.0),
        gravity_tilt=(0.0, float(np.radians(5.0))),
    ),
    "description": Randomization(
        rod_mass=(0.9, 1.1),
        rod_length=(0.98, 1.02),
        endcap_offset=(-0.01, 0.01),
        cable_stiffness=(0.85, 1.15),
        passive_rest_offset=(-0.02, 0.02),
        motor_range_offset=(-0.03, 0.03),
        encoder_zero=(-0.03, 0.03),
    ),
}
"""The named presets; :func:`register_randomization` adds a lab's. ``"description"``
is the description's error alone (issue: a lab's description is never exact): rod
lengths within 2 %, endcaps within 1 cm, motor ranges and encoder zeros within 3 cm,
cable stiffness within 15 %, passive rest lengths within 2 %, rod masses within 10 %."""


def register_randomization(name: str, randomization: Randomization) -> None:
    """Make ``randomization`` known as ``gym.make(..., randomization=name)``."""
    if not isinstance(randomization, Randomization):
        raise TypeError(f"register_randomization({name!r}): expected a Randomization")
    RANDOMIZATIONS[name] = randomization


def resolve_randomization(value: object) -> Randomization | None:
    """``None``, a registered name or a :class:`Randomization`; a bad one refused by name
    with the valid choices."""
    if value is None or isinstance(value, Randomization):
        return value
    if isinstance(value, str) and value in RANDOMIZATIONS:
        return RANDOMIZATIONS[value]
    raise ValueError(
        f"make: randomization={value!r} must be None, one of {sorted(RANDOMIZATIONS)} "
        "or a Randomization"
    )
