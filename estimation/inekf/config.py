"""Parameters of the proprioceptive estimator (``estimator="inekf"``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

from estimation.health import HealthParams
from estimation.inekf.filter import InekfNoise
from estimation.inekf.shape import ShapeConfig

if TYPE_CHECKING:
    from estimation.inekf.contacts import ContactThresholds
    from tensegrity_gym.model.description import RobotDescription

__all__ = [
    "CONTACT_SOURCES",
    "PAPER_LENGTHS",
    "PAPER_ROD_LENGTH",
    "InekfConfig",
    "noise_from_description",
]

BIAS_WALK = 1e-5
"""Random-walk density of both IMU biases (per sqrt(Hz)): a bias that changes slowly over
a run (the simulator's is constant), so that the filter keeps learning it."""
CONTACT_SLIP = 0.005
"""m/s/sqrt(Hz): an endcap's slip in contact while the robot is still; Tong et al. 2024 table I
has 0.05. It grows with the angular rate (:attr:`InekfConfig.slip_per_rate`). On the
1.45 m robot's five runs (agents.benchmarks.proprio, seeds 0-2, one-off replays) a constant
density drifted 9.5 % on average (0.02; 0.01-0.05 were no better, with capsule rods),
a density growing with the rate 6.9 % (0.005 + 0.05 per rad/s; 0.002 6.8 %, 0.01 7.2 %)."""


def noise_from_description(description: RobotDescription) -> InekfNoise:
    """The densities of the robot's IMU: its per-sample noise (the description's
    ``accel_noise``, ``gyro_noise`` at ``rate``) over sqrt(rate)."""
    imu = description.sensors.imu
    root = math.sqrt(imu.rate)
    return InekfNoise(
        gyro=imu.gyro_noise / root,
        accel=imu.accel_noise / root,
        gyro_bias=BIAS_WALK,
        accel_bias=BIAS_WALK,
        contact_velocity=CONTACT_SLIP,
    )


PAPER_ROD_LENGTH = 1.45
"""m: the rods of Tong et al. 2024's robot, on which the lengths of :data:`PAPER_LENGTHS` hold."""
PAPER_LENGTHS = {
    "contact_std": 0.1,
    "kinematics_std": 0.08,
    "slip_per_rate": 0.05,
    "slip_max": 0.05,
    "floor_std": 0.1,
}
"""The defaults of the :class:`InekfConfig` fields that scale with the robot's size, on
Tong et al. 2024's 1.45 m rods (m, m, m/s/sqrt(Hz) per rad/s, m/s/sqrt(Hz), m): the
paper's values but ``floor_std``, which is this project's (the paper has no floor)."""

CONTACT_SOURCES = ("auto", "sensors", "shape")
"""Where contacts come from: the contact sensors (``"sensors"``), the shape and gravity
(``"shape"``), or the sensors where the robot has them and the shape otherwise."""


@dataclass(frozen=True)
class InekfConfig:
    """The contact-aided right-invariant EKF of Tong et al. 2024 and its shape reconstruction."""

    base_rod: int = 0
    """The rod whose IMU defines the body frame (Tong et al. 2024: the red rod)."""
    noise: InekfNoise | None = None
    """The IMU's noise densities and the contacts' slip; None: from the robot's
    description (:func:`noise_from_description`)."""
    shape: ShapeConfig = field(default_factory=ShapeConfig)
    shape_rate: float = 20.0
    """Hz: how often the shape is reconstructed from the encoders (at most one solve per
    encoder reading), counted from the reset's; the corrections in between use the
    latest shape. On the bench (seeds 0 and 1): 10 Hz 12.8 % mean drift, 20 Hz 12.2 %
    (with the slip above; 1.9 cm shape RMSE either way), 50 Hz no better than 20 at
    twice the cost. With thin rods, rolling endcaps and slid contacts touching down
    again: 10 Hz 9.5 %, 20 Hz 9.7 % on the bench, but in closed loop (the gait driven
    by the estimates, tests/estimation/test_inekf.py) 14 % against 5 % with contact sensors and
    76 % against 9 % without: 20 Hz, though a solve is a third of the estimator's time."""
    contacts: str = "auto"
    """See :data:`CONTACT_SOURCES`."""
    contact_thresholds: ContactThresholds | None = None
    """Heights for contacts from the shape; None: in proportion to the rods
    (:meth:`ContactThresholds.for_rod_length`)."""
    contact_std: float | None = None
    """m: standard deviation of an endcap's world position when it touches down, per
    axis (eq. 9: the shape solver gives no Jacobian, so it is a parameter, as in the
    paper). None: 0.1 m on Tong et al. 2024's 1.45 m rods, in proportion to the robot's
    (:meth:`for_robot`; so are the other lengths whose default is None)."""
    kinematics_std: float | None = None
    """m: standard deviation of a contact endcap's body-frame position from the shape,
    per axis (the forward-kinematics measurement noise of eq. 12); None: 0.08 m on the
    1.45 m rods, about the shape's node error there rolling (tests/estimation/test_shape.py); 2 cm
    made the filter trust a wrong shape and drift 10 % instead of 4 % on the forward
    gait."""
    gate_probability: float = 0.9999
    """Chi-square gate on each contact correction: innovations less likely are refused."""
    slip_per_rate: float | None = None
    """m/s/sqrt(Hz) per rad/s: the contacts' slip density grows by this times the base
    rod's angular rate (None: 0.05 on the 1.45 m rods: an endcap slides at the rate
    times a lever of the robot's size). The endcaps slide most while the robot tips
    over a face (1 kHz truth: a third of the contact time faster than 5 cm/s), and
    barely while it rests on one; a constant density either trusts the sliding contacts
    or loosens the still ones. On the bench (seeds 0-2): 9.5 % -> 6.9 % mean drift;
    0.04 7.1 %, 0.07 7.0 %, and no growth below 1 rad/s 8.8 % (the left turn rocks
    slowly and slides)."""
    slip_max: float | None = None
    """m/s/sqrt(Hz): the most the rate makes of the slip density (None: Tong et al. 2024's
    constant 0.05 on its 1.45 m rods). A robot shaken by random actions turns fast all
    the time, and an unbounded density let its pose coast on the IMU: on
    ThreeBarRoll-v0, 300 random steps (seeds 1000-1002), the CoM 0.9 and 2.3 m off at
    the end on two seeds against 0.25 and 0.17 with a constant 0.02; capped at 0.05
    0.39 and 0.78 m (0.03: 0.30 and 0.36 m). On the 1.45 m robot's bench the cap helps
    too: 6.9 % -> 6.1 % mean drift (0.03: 7.3 %). Scaled to the 0.325 m rods of
    ThreeBarRoll-v0 with the three lengths above, a PPO policy's 16 episodes (seeds
    1000-1015, ``evaluate --conditions inekf``) had the CoM 0.23 m off on average
    instead of 0.53 m (unscaled, one-off script), and the 300 random steps above ended
    0.11, 0.17 and 0.08 m off (one-off script; with the saturated gyro's rotation
    variance too)."""
    reanchor_slipped: bool = True
    """A contact the gate refuses has slipped: it touches down again where the shape and
    the pose put it. On the bench (agents.benchmarks.proprio, seeds 0 and 1) the mean drift
    fell from 10.3 % to 9.5 % with it."""
    rolling_endcaps: bool = True
    """The base rod's endcaps in contact roll with its spin (the gyro's z): on the bench
    the mean drift fell from 11.8 % to 10.3 %; rolling the other rods' endcaps by
    their axes' turn (from the shape) made it worse (11.0 %)."""
    flight_spin: bool = True
    """Through a hop (no endcap sensed on the ground) the shape, in the base rod's
    frame, turns about the rod against its gyro's z: the rod spins on its own axis,
    about which no cable pulls, and the rest of the robot does not follow (the stiff
    contacts' world, one-off check: the true shape turned 23-24 degrees a 0.1 s against
    220-240 deg/s of gyro z). Without it the solver held the last spin in the rod's
    frame, and the shape landed up to 0.9 m off. Not where a gyro reading clipped since
    the last solve (its z then undercounts the turn). Cross-world drift, stiff / MuJoCo
    / own / description error: 13.4 / 5.3 / 2.5 / 5.3 % -> 9.9 / 5.7 / 2.5 / 5.1 %
    (replays of the bench's runs at a456103)."""
    initial_rotation_std: float = 0.02
    """rad: roll and pitch from the accelerometer at rest."""
    initial_yaw_std: float = 0.2
    """rad: heading from the magnetometer."""
    initial_position_std: float = 0.01
    """m: the estimator's frame is where the robot starts; it knows that well."""
    initial_velocity_std: float = 0.01
    """m/s: the robot rests at reset."""
    initial_gyro_bias_std: float = 0.002
    """rad/s, before the rest phase has measured it."""
    initial_accel_bias_std: float = 0.01
    """m/s^2."""
    rest_gyro: float = 0.02
    """rad/s: below this angular rate (and with the encoders still) the robot rests; the
    gyro's mean over the first rest after reset is its bias."""
    imu_gap_share: float | None = 0.5
    """A base-rod IMU reading that comes later than the IMU's period (the description's
    rate) by more than this share of it, one or more readings lost in between, makes
    the velocity uncertain: the propagation holds the last reading over the gap, and
    the rods' vibration (tens of m/s^2 at 25 Hz and up) is not held; the variance
    added per axis is the accelerometer's recent mean square about its low-pass times
    the missing time squared. None: off (Tong et al. 2024 has no such term). On the
    1.45 m robot's seed-0 runs with a fifth of the IMU readings dropped at random
    (one-off script, at 8aef248): rolling 7.4 % -> 3.7 % drift (2 restarts -> none),
    rolling with 2 ms of time jitter as well 11.2 % -> 2.3 %, turning with both 28.6 %
    -> 7.5 %; turning with the drops alone 9.8 % -> 10.3 % (a reading lost at an
    impact while the robot flies is lost to dead reckoning). Without lost readings
    nothing changes (3.8 % and 1.2 % on the same runs)."""
    max_speed: float = 20.0
    """m/s: an estimated speed beyond this is a divergence (the filter restarts)."""
    floor_correction: bool = True
    """Each endcap that touches down (or touches down again, :attr:`reanchor_slipped`)
    corrects the filter once with its height: it stands on the floor the filter started
    on (z = 0), its radius above it, within :attr:`floor_std`
    (:meth:`RightInvariantEkf.correct_heights`; not gated: a filter whose height has
    drifted off is what it is for). Not in Tong et al. 2024, where the height is
    unobservable and only the ground bound (:attr:`ground_reach`) restarts a filter
    that has drifted off. On the cross-world bench's 1.45 m runs (replays of its 18
    runs, at 8cf5bf9), mean drift own / MuJoCo / description error 2.68 / 6.59 / 6.34 %
    -> 2.54 / 5.29 / 5.26 %, restarts 0 / 0.8 / 0.7 a run -> none. Corrected at every
    contact stamp instead (22d8591; 100 Hz: a contact held for a second told the filter
    its height a hundred times over: after 3 s of the gait, seed 2, a height std of
    1.1 cm against 3.9 cm without the correction, one-off script), 2.81 / 6.37 / 5.18 %;
    that, gated at 0.9999 and with the rotation's row, at 0.05 m (a filter off by more
    refuses it, and restarts): 2.64 / 13.7 / 21.9 %."""
    floor_std: float | None = None
    """m: standard deviation of a contact's height above that floor at touch-down: the
    floor's unevenness the filter allows for (None: 0.1 m on the 1.45 m rods, in
    proportion to the robot's). On the runs above, at 0.05 m: 2.63 / 5.84 / 5.14 %; at
    0.2 m: 2.63 / 7.57 / 5.23 %, with 0.5 restarts a run on MuJoCo."""
    ground_reach: float = 0.5
    """Rod lengths (the base rod's): the endcaps in contact (else the lowest endcap)
    estimated further above or below the floor the filter started on (z = 0, less
    their radii) is a divergence: a robot rolling on the ground cannot float or sink.
    Twice the deepest of the terrain presets' troughs (the valley's, a quarter of a rod
    length): the filter knows no map. With the floor correction a filter whose height
    drifts is pulled back before it gets this far; what is left for the bound is a
    robot coasting through the air on its IMU, no endcap in contact. On a sloping floor
    the ground rises along the travel, and the floor correction holds the estimate to
    the level floor it started on: a robot rolling far uphill or downhill (on a slope
    of s, 0.5 / s rod lengths: 14 at 2 degrees) is estimated too low or too high."""
    max_refused_time: float = 0.5
    """s: the gate refusing every contact correction for longer is a divergence (the
    filter restarts): one that has drifted off would otherwise refuse them ever after."""
    health: HealthParams = field(default_factory=lambda: HealthParams(max_prediction_time=0.5))

    def for_robot(self, description: RobotDescription) -> InekfConfig:
        """This config with every length left None set in proportion to the base rod:
        its value on Tong et al. 2024's 1.45 m rods (:data:`PAPER_LENGTHS`) times the
        rod's length over 1.45 m."""
        scale = float(description.rods[self.base_rod].length) / PAPER_ROD_LENGTH

        def length(name: str) -> float:
            value: float | None = getattr(self, name)
            return PAPER_LENGTHS[name] * scale if value is None else value

        return replace(
            self,
            contact_std=length("contact_std"),
            kinematics_std=length("kinematics_std"),
            slip_per_rate=length("slip_per_rate"),
            slip_max=length("slip_max"),
            floor_std=length("floor_std"),
        )

    def __post_init__(self) -> None:
        if self.contacts not in CONTACT_SOURCES:
            raise ValueError(
                f"InekfConfig.contacts must be one of {list(CONTACT_SOURCES)}, "
                f"got {self.contacts!r}"
            )
        if isinstance(self.base_rod, bool) or not isinstance(self.base_rod, int):
            raise ValueError(f"InekfConfig.base_rod must be a rod index, got {self.base_rod!r}")
        for name in ("contact_std", "kinematics_std", "floor_std"):
            value = getattr(self, name)
            if value is not None and not (
                isinstance(value, (int, float)) and math.isfinite(value) and value > 0
            ):
                raise ValueError(f"InekfConfig.{name} must be a number > 0 or None, got {value!r}")
        for name in (
            "shape_rate", "initial_rotation_std",
            "initial_yaw_std", "initial_position_std", "initial_velocity_std",
            "initial_gyro_bias_std", "initial_accel_bias_std", "rest_gyro", "max_speed",
            "max_refused_time", "ground_reach",
        ):  # fmt: skip
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"InekfConfig.{name} must be a number > 0, got {value!r}")
        for name in ("slip_per_rate", "slip_max", "imu_gap_share"):
            k = getattr(self, name)
            if k is not None and not (isinstance(k, (int, float)) and math.isfinite(k) and k >= 0):
                raise ValueError(f"InekfConfig.{name} must be a number >= 0 or None, got {k!r}")
        for name in ("reanchor_slipped", "rolling_endcaps", "floor_correction", "flight_spin"):
            flag = getattr(self, name)
            if not isinstance(flag, bool):
                raise ValueError(f"InekfConfig.{name} must be True or False, got {flag!r}")
        p = self.gate_probability
        if not (isinstance(p, float) and 0.0 < p < 1.0):
            raise ValueError(f"InekfConfig.gate_probability must lie in (0, 1), got {p!r}")
