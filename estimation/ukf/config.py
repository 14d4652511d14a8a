"""Everything that tunes the UKF: :class:`UkfConfig`."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from estimation.health import HealthParams
from estimation.ukf.sigma_points import SigmaPointParams
from estimation.ukf.spring_mass import SpringMassParams

__all__ = ["UkfConfig"]


@dataclass(frozen=True)
class UkfConfig:
    """Everything that tunes the filter. Lengths scale with the robot where noted.

    Noise is given as standard deviations; the filter squares them.
    """

    sigma_points: SigmaPointParams = field(default_factory=lambda: SigmaPointParams(alpha=0.3))
    """Spread of the sigma points. Wider than Caluwaerts et al. 2016's alpha = 0.0139, which puts
    them
    within 0.08 standard deviations of the mean with weights near -5000 and 70: a kink of
    the model between them (a cable going slack, a rod tipping over an edge) then moves
    the predicted mean by centimetres. With the AHRS frame's alignment estimated, the
    robot's tilt is uncertain in its first seconds, and at 0.0139 single runs diverged
    (docs/results/sim_to_real.md); at 0.3 none did, and the NEES is otherwise the same."""
    model: SpringMassParams = field(default_factory=SpringMassParams)
    position_noise: float = 0.01
    """Process noise on node positions: std per sqrt(s), in rod lengths."""
    velocity_noise: float = 0.5
    """Process noise on node velocities: std per sqrt(s), in rod lengths per s."""
    driven_position_noise: float = 0.025
    """``position_noise`` while the robot is driven: an actuated rest length moving
    faster than ``driven_speed``, or did so within ``driven_hold`` seconds. The model is
    rougher for a rolling robot than a resting one (estimation/ukf/process_noise.py)."""
    driven_velocity_noise: float = 1.0
    """``velocity_noise`` while the robot is driven."""
    driven_speed: float = 0.01
    """Speed (m/s) of an actuated rest length above which the robot counts as driven
    (an encoder's jitter of a tick stays under it)."""
    driven_hold: float = 3.0
    """Seconds after the motors stop that the robot still counts as driven: one set
    tipping rolls on."""
    body_position_noise: float = 0.0
    """Process noise shared by every node while driven: the robot as a whole moving off
    the model (a roll landing short or long, a slip, a floor's slope), std per sqrt(s),
    in rod lengths. Per-node noise alone leaves the CoM ``sqrt(n)`` times surer than a
    node, where a rolling robot's model errs most in the CoM. Off by default: at 0.02
    the 3-bar's CoM was estimated consistently, but the filter diverged in two of three
    long rolls with the self-calibrated UWB (a one-off run; no results page holds it)."""
    node_noise_scale: tuple[float, ...] | None = None
    """Per node (n,), a factor on both process noises: where the model is known to be
    rougher (an endcap carrying a payload, a worn cable's ends). None: 1 for every node."""
    contact_noise_scale: float = 1.0
    """A factor on both process noises of a node touching the ground (its estimated
    height within ``contact_band`` of its endcap radius): the model's ground contact and
    friction are approximate (a real floor's compliance and friction vary)."""
    contact_band: float = 0.01
    """How far (m) above its resting height a node still counts as touching the ground,
    for ``contact_noise_scale``."""
    axis_sigma: float = 0.04
    """Std of each component of an AHRS rod axis (unit vector, ~ rad)."""
    alignment_sigma: float | None = 0.05
    """Prior std (rad) of each component of the rotation from the AHRS's frame (z
    against gravity, x toward magnetic north) to the world's (the UWB anchors', its
    floor at z = 0), which the filter estimates with the nodes: on a sloping floor, or
    with anchors surveyed off level or off north, the AHRS gives every rod axis turned
    by it (under ``"mild"`` randomisation, a slope of up to 2 degrees). None: the frames
    are taken as one, not estimated."""
    alignment_noise: float = 0.001
    """Random walk of that rotation, rad per sqrt(s): a constant, allowed to settle."""
    rest_length_error_sigma: float | None = 0.02
    """Prior std (m) of each actuated cable's rest length against what its encoder
    reads (the encoder's zero set by hand, the cable attached off its place), which the
    filter estimates with the nodes (estimation/ukf/state.py). None: the encoders are
    taken as exact."""
    rod_length_error_sigma: float | None = 0.01
    """Prior std (m) of each rod's length (its endcaps' distance) against the
    description's, estimated likewise. None: the description's lengths are exact."""
    description_noise: float = 1e-4
    """Random walk of those length errors, m per sqrt(s): constants, allowed to settle."""
    range_sigma: float = 0.03
    """Std of a UWB range (m)."""
    cable_sigma: float = 0.03
    """Std of a cable-length sensor (m); slack cables read long, the gate drops them."""
    rod_length_sigma: float = 0.002
    """Std of the rod-length pseudo-measurement, in rod lengths."""
    contact_sigma: float = 0.005
    """Std of the height of an endcap in contact with the ground (m)."""
    use_imu: bool = True
    use_ranges: bool = True
    use_robot_ranges: bool = True
    """Node-node ranges as well as node-anchor ones."""
    use_cable_lengths: bool = True
    use_contacts: bool = True
    anchors: tuple[int, ...] | None = None
    """Indices of the anchors to use (ablations: 4 of 8); None uses all."""
    constant_offset: bool = False
    """One offset (the mean of the calibration's) for every pair instead of o_ij."""
    gate_probability: float | None = 0.9999
    """Chi-square gate on each measurement group; None turns gating off."""
    gate_after: int = 10
    """Updates after (re)initialisation before the gate applies."""
    initial_position_sigma: float = 0.1
    """Std of the initial position of the robot as a whole, in rod lengths."""
    initial_shape_sigma: float = 0.02
    """Std of each node's initial position about that, in rod lengths."""
    initial_velocity_sigma: float = 0.05
    """Std of the initial node velocities (m/s), in rod lengths per s."""
    initial_positions: tuple[tuple[float, float, float], ...] | None = None
    """Start from these node positions (m) instead of fitting them to the first samples."""
    range_window: float = 0.5
    """Seconds of ranges kept for re-initialisation; of a period's rounds, only those
    this close to its newest sample are fused (after a stall, not the whole backlog)."""
    divergence_nis: float = 25.0
    """Mean NIS per accepted row over ``divergence_window`` updates that counts as
    divergence."""
    divergence_window: int = 5
    lockout_range_share: float = 0.3
    """Gating out more than this share of the ranges, or a rod's axis, ..."""
    lockout_updates: int = 3
    """... in this many updates in a row is a gate lock-out: the covariance is reset to
    its initial size around the current state; a second lock-out soon after counts as
    divergence."""
    axis_fault_range_share: float = 0.1
    """A rod's axis gated out while the ranges of those updates fit (at most this share
    of them gated out in each, and ranges in each) is its AHRS's fault, not the
    filter's: no lock-out, the axis stays gated. The ranges place every node, so a
    filter whose rod has turned away from the truth misfits that rod's ranges; an AHRS
    whose gyro saturated (a 1.45 m robot's base rod spinning on its endcaps faster than
    the gyro's full scale, on MuJoCo) reads a wrong axis while they fit: counted a
    lock-out, that reset the covariance and then restarted a filter that was right
    (two runs of six, ``bench --cross-world``'s 1.45 m 3-bar on MuJoCo)."""
    divergence_anchor_reject_share: float = 0.6
    """Gating out more than this share of the anchor ranges of one update (at least 5)
    counts as divergence at once: the estimate has jumped away from where the anchors
    put the robot."""
    divergence_rod_strain: float = 0.25
    """A rod estimated this much longer or shorter (share of its length) is divergence."""
    stream_failure_window: float = 1.0
    """Seconds of nothing but physically implausible samples after which a sensor stream
    is failed (``Estimate.failed_streams``) and not used, plausible or not, until it has
    given only plausible samples this long again. One second is 15 UWB rounds, 10 cable
    readings, 200 AHRS readings: no single garbled message fails a stream, a dead one is
    dropped within a second, and a flickering one is not taken back at its first good
    value."""
    max_prediction_time: float = 0.5
    """Seconds the filter may predict without fusing any sensor row (AHRS axis, range,
    cable, contact; the rod-length pseudo-measurement does not count) before its estimate
    is reported unhealthy: five control periods of the envs, in which a rolling 3-bar
    moves some 5 cm on its model alone. Updates without any sample count as long as the
    last update that had some."""

    def __post_init__(self) -> None:
        positive = (
            "position_noise", "velocity_noise", "driven_position_noise",
            "driven_velocity_noise", "driven_speed", "driven_hold", "axis_sigma", "range_sigma",
            "cable_sigma",
            "rod_length_sigma", "contact_sigma", "initial_position_sigma", "initial_shape_sigma",
            "initial_velocity_sigma", "range_window", "divergence_nis", "contact_noise_scale",
            "contact_band", "alignment_noise", "description_noise",
            "divergence_rod_strain", "stream_failure_window", "max_prediction_time",
        )  # fmt: skip
        for name in positive:
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"UkfConfig.{name} must be positive, got {value}")
        if self.gate_probability is not None and not 0.5 < self.gate_probability < 1:
            raise ValueError(
                f"UkfConfig.gate_probability must lie in (0.5, 1) or be None, "
                f"got {self.gate_probability}"
            )
        scales = self.node_noise_scale
        if scales is not None and not all(np.isfinite(v) and v > 0 for v in scales):
            raise ValueError(f"UkfConfig.node_noise_scale must be positive factors, got {scales}")
        body = self.body_position_noise
        if not (np.isfinite(body) and body >= 0):
            raise ValueError(f"UkfConfig.body_position_noise must be non-negative, got {body}")
        for name in ("alignment_sigma", "rest_length_error_sigma", "rod_length_error_sigma"):
            value = getattr(self, name)
            if value is not None and not (np.isfinite(value) and value > 0):
                raise ValueError(f"UkfConfig.{name} must be positive or None, got {value}")
        if self.divergence_window < 1 or self.lockout_updates < 1:
            raise ValueError("UkfConfig.divergence_window and lockout_updates must be at least 1")
        if not 0 < self.divergence_anchor_reject_share < 1:
            raise ValueError(
                "UkfConfig.divergence_anchor_reject_share must lie in (0, 1), "
                f"got {self.divergence_anchor_reject_share}"
            )
        if not 0 <= self.axis_fault_range_share < 1:
            raise ValueError(
                "UkfConfig.axis_fault_range_share must lie in [0, 1), "
                f"got {self.axis_fault_range_share}"
            )
        if not 0 < self.lockout_range_share < 1:
            raise ValueError(
                f"UkfConfig.lockout_range_share must lie in (0, 1), got {self.lockout_range_share}"
            )

    @property
    def estimates_alignment(self) -> bool:
        """Whether the state carries the AHRS frame's alignment: where it is asked for
        and the AHRS is used, which alone observes it."""
        return self.alignment_sigma is not None and self.use_imu

    @property
    def health(self) -> HealthParams:
        """When the filter's estimate is healthy."""
        return HealthParams(max_prediction_time=self.max_prediction_time)
