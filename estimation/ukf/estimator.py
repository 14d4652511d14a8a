"""The UKF of papers/000 as an :class:`Estimator`: samples and commands in, estimate out.

Each control period the filter predicts the spring-mass net forward with the motor
encoders' rest lengths as its input, then corrects it with what arrived: rod axes from
the AHRS, UWB ranges minus the pair offsets, cable lengths, and the rod-length and
ground-contact pseudo-measurements. Before anything is kept, readings that are
physically implausible are dropped and counted (:mod:`estimation.screen`), and a stream
that gives nothing plausible for ``stream_failure_window`` is failed and not used until
it has been plausible as long. Outliers are gated; a filter that diverges
re-initialises itself from recent samples, never from what the gate rejected, and says
so in the estimate. An estimate is unhealthy after ``max_prediction_time`` without a
sensor row fused.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from estimation.plausibility import PlausibilityBounds
from estimation.screen import PlausibilityScreen
from estimation.ukf.filter import UnscentedKalmanFilter, UpdateResult, single_threaded_blas
from estimation.ukf.initialise import MIN_ANCHOR_RANGES, InitialisationError, fit_initial_shape
from estimation.ukf.measurements import (
    MeasurementBatch,
    MeasurementModel,
    RowKind,
    ahrs_axis,
)
from estimation.ukf.sigma_points import CholeskyError, SigmaPointParams
from estimation.ukf.spring_mass import SpringMassModel, SpringMassParams
from tensegrity_gym.model.estimate import Estimate
from tensegrity_gym.model.kinematics import center_of_mass, member_lengths
from tensegrity_gym.model.samples import (
    AhrsSample,
    CableLengthSample,
    ContactSample,
    EncoderSample,
    ImuSample,
    UwbRangeSample,
)

if TYPE_CHECKING:
    from collections.abc import Sequence

    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import SensorCalibration
    from tensegrity_gym.model.samples import Sample

__all__ = ["FilterStep", "UkfConfig", "UkfDiagnostics", "UkfEstimator"]

log = logging.getLogger(__name__)

_JUMPED = "most anchor ranges gated out at once"
"""The divergence in which the estimate has jumped away from where the anchors put it."""

_TIME_TOLERANCE = 1e-6
"""s: sums of sample periods differ from their nominal values by rounding."""


@dataclass(frozen=True)
class UkfConfig:
    """Everything that tunes the filter. Lengths scale with the robot where noted.

    Noise is given as standard deviations; the filter squares them.
    """

    sigma_points: SigmaPointParams = field(default_factory=SigmaPointParams)
    model: SpringMassParams = field(default_factory=SpringMassParams)
    position_noise: float = 0.01
    """Process noise on node positions: std per sqrt(s), in rod lengths."""
    velocity_noise: float = 0.5
    """Process noise on node velocities: std per sqrt(s), in rod lengths per s."""
    axis_sigma: float = 0.04
    """Std of each component of an AHRS rod axis (unit vector, ~ rad)."""
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
    """Seconds of ranges kept for re-initialisation."""
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
            "position_noise", "velocity_noise", "axis_sigma", "range_sigma", "cable_sigma",
            "rod_length_sigma", "contact_sigma", "initial_position_sigma", "initial_shape_sigma",
            "initial_velocity_sigma", "range_window", "divergence_nis",
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
        if self.divergence_window < 1 or self.lockout_updates < 1:
            raise ValueError("UkfConfig.divergence_window and lockout_updates must be at least 1")
        if not 0 < self.divergence_anchor_reject_share < 1:
            raise ValueError(
                "UkfConfig.divergence_anchor_reject_share must lie in (0, 1), "
                f"got {self.divergence_anchor_reject_share}"
            )
        if not 0 < self.lockout_range_share < 1:
            raise ValueError(
                f"UkfConfig.lockout_range_share must lie in (0, 1), got {self.lockout_range_share}"
            )


@dataclass(frozen=True)
class FilterStep:
    """One predict-update cycle of the filter, everything it needs."""

    duration: float
    """Seconds to predict over."""
    rest_start: NDArray[np.float64]
    """Actuated cable rest lengths at the start (m), (m,)."""
    rest_end: NDArray[np.float64]
    """... and at the end, from the motor encoders (m), (m,)."""
    process_noise: NDArray[np.float64]
    """Diagonal of Q for this step, (6 n,)."""
    batch: MeasurementBatch


@dataclass
class UkfDiagnostics:
    """Counters a user or a test reads after the fact."""

    updates: int = 0
    rows: int = 0
    rejected_rows: int = 0
    rejected_by_kind: dict[str, int] = field(default_factory=dict)
    """Rows the chi-square gate rejected, by :class:`RowKind` name."""
    implausible_by_kind: dict[str, int] = field(default_factory=dict)
    """Readings dropped as physically implausible before the filter saw them, by kind
    (``"uwb_range_too_long"``, ``"cable_negative"``, ...: :mod:`estimation.plausibility`)."""
    reinitialisations: int = 0
    covariance_resets: int = 0
    """Gate lock-outs answered by resetting the covariance."""
    jitter_events: int = 0
    last_update: UpdateResult | None = None
    nis_history: deque[float] = field(default_factory=lambda: deque(maxlen=1000))


@dataclass(frozen=True, eq=False)
class _Round:
    """A UWB round as the filter keeps it: only its plausible ranges."""

    t: float
    pairs: NDArray[np.intp]
    """(k, 2) module ids."""
    ranges: NDArray[np.float64]
    """(k,) m, pair offsets included."""
    for_fit: NDArray[np.bool_]
    """(k,) False where the chi-square gate rejected the range or a divergence blamed
    its round: re-initialisation does not fit to those."""

    @classmethod
    def of(cls, sample: UwbRangeSample) -> _Round:
        ranges = np.asarray(sample.ranges, dtype=np.float64).reshape(-1)
        pairs = np.asarray(sample.pairs, dtype=np.intp).reshape(-1, 2)
        return cls(sample.t, pairs, ranges, np.ones(len(ranges), dtype=bool))


def _ranging(
    config: UkfConfig, description: RobotDescription, calibration: SensorCalibration
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """Anchor positions (a, 3) (m), the pair offsets the filter subtracts (m), and the
    modules it uses, each (n_modules, n_modules) and (n_modules,); checks the inputs."""
    c = config
    n = description.n_nodes
    anchors = np.asarray(calibration.anchors, dtype=np.float64).reshape(-1, 3)
    n_modules = n + len(anchors)
    offsets = np.asarray(calibration.uwb_offsets, dtype=np.float64)
    if offsets.shape != (n_modules, n_modules):
        raise ValueError(
            f"calibration.uwb_offsets has shape {offsets.shape}, expected "
            f"{(n_modules, n_modules)} for {n} nodes and {len(anchors)} anchors"
        )
    if c.constant_offset:
        off_diag = ~np.eye(n_modules, dtype=bool)
        offsets = np.where(off_diag, offsets[off_diag].mean(), 0.0)
    allowed = np.ones(n_modules, dtype=bool)
    if c.anchors is not None:
        bad = [a for a in c.anchors if not 0 <= a < len(anchors)]
        if bad:
            raise ValueError(f"UkfConfig.anchors names anchors {bad}; the scene has {len(anchors)}")
        allowed[n:] = False
        allowed[[n + a for a in c.anchors]] = True
    return anchors, offsets, allowed


def _recent(rounds: Sequence[_Round], t: float, window: float) -> list[_Round]:
    """The rounds no older than ``window`` seconds before ``t``."""
    return [r for r in rounds if r.t >= t - window]


def _select(
    rounds: Sequence[_Round],
    allowed: NDArray[np.bool_],
    robot_ranges: bool,
    n_nodes: int,
    *,
    for_fit: bool = False,
) -> tuple[NDArray[np.intp], NDArray[np.float64], NDArray[np.intp]]:
    """The ranges of ``rounds`` the filter uses: pairs (r, 2), ranges (r,) (m), and their
    places (r,) in the rounds' ranges laid end to end.

    Only modules in ``allowed``; node-node ranges only if ``robot_ranges``; only the
    ranges still marked ``for_fit`` if ``for_fit``.
    """
    if not rounds:
        return np.zeros((0, 2), dtype=np.intp), np.zeros(0), np.zeros(0, dtype=np.intp)
    pairs = np.concatenate([r.pairs for r in rounds])
    ranges = np.concatenate([r.ranges for r in rounds])
    keep = allowed[pairs].all(axis=1)
    if not robot_ranges:
        keep &= (pairs >= n_nodes).any(axis=1)
    if for_fit:
        keep &= np.concatenate([r.for_fit for r in rounds])
    return pairs[keep], ranges[keep], np.flatnonzero(keep).astype(np.intp)


class UkfEstimator:
    """The unscented Kalman filter over the spring-mass net (papers/000, section IV).

    Args:
        config: tuning; defaults work for the presets.
    """

    needs_camera = False

    def __init__(self, config: UkfConfig | None = None) -> None:
        self.config = config if config is not None else UkfConfig()
        self.diagnostics = UkfDiagnostics()
        self._ready = False

    # ------------------------------------------------------------------ set-up

    def reset(
        self,
        description: RobotDescription,
        calibration: SensorCalibration,
        samples: Sequence[Sample],
        command: NDArray[np.float64],
        rng: np.random.Generator,
    ) -> Estimate:
        """Start from the first samples (or ``config.initial_positions``).

        ``rng`` is unused: the filter is deterministic given its samples.
        """
        with single_threaded_blas():
            return self._reset(description, calibration, samples, command)

    def initialisation_missing(
        self,
        description: RobotDescription,
        calibration: SensorCalibration,
        samples: Sequence[Sample],
    ) -> str | None:
        """None if :meth:`reset` could start from ``samples``, else what is missing.

        Counts, as the fit in ``reset`` does, the plausible UWB ranges to the anchors in
        use within ``range_window`` of the newest sample; fits nothing. With
        ``initial_positions`` nothing is needed. Raises as ``reset`` does on a malformed
        calibration or config.
        """
        c = self.config
        _, _, allowed = _ranging(c, description, calibration)
        if c.initial_positions is not None:
            return None
        bounds = PlausibilityBounds.from_robot(description, calibration)
        screen = PlausibilityScreen(description, bounds, c.stream_failure_window)
        kept = screen.screen(samples)
        rounds = [_Round.of(s) for s in kept if isinstance(s, UwbRangeSample)]
        t = max((s.t for s in samples), default=0.0)
        n = description.n_nodes
        pairs, _, _ = _select(
            _recent(rounds, t, c.range_window), allowed, c.use_robot_ranges, n, for_fit=True
        )
        found = int(np.count_nonzero((pairs >= n).any(axis=1)))
        if found >= MIN_ANCHOR_RANGES:
            return None
        dropped = sum(v for kind, v in screen.rejected.items() if kind.startswith("uwb"))
        note = f" ({dropped} implausible ones dropped)" if dropped else ""
        return f"{found} UWB ranges to anchors, {MIN_ANCHOR_RANGES} needed{note}"

    def _reset(
        self,
        description: RobotDescription,
        calibration: SensorCalibration,
        samples: Sequence[Sample],
        command: NDArray[np.float64],
    ) -> Estimate:
        c = self.config
        d = description
        self.description = d
        self.model = SpringMassModel(d, c.model)
        anchors, self.offsets, self._module_allowed = _ranging(c, d, calibration)
        self.measurements = MeasurementModel(d, anchors, d.sensors.uwb.module_offset)
        n = d.n_nodes
        L = d.characteristic_length
        self._q_pos = (c.position_noise * L) ** 2
        self._q_vel = (c.velocity_noise * L) ** 2
        self._rest = np.asarray(command, dtype=np.float64).copy()
        self._ranges: list[_Round] = []
        # Readings not yet used by an update, and the latest of each for re-initialising
        # (of which the chi-square gate takes back what it rejects).
        self._axes: dict[int, NDArray[np.float64]] = {}
        self._cables: NDArray[np.float64] | None = None
        self._contacts: NDArray[np.intp] | None = None
        self._latest_axes: dict[int, NDArray[np.float64]] = {}
        self._axes_before: dict[int, NDArray[np.float64] | None] = {}
        self._latest_cables: NDArray[np.float64] | None = None
        self._latest_contacts: NDArray[np.intp] | None = None
        self._period_rounds: list[_Round] = []
        self._period_range_index = np.zeros(0, dtype=np.intp)
        self._t = max((s.t for s in samples), default=0.0)
        self._uncorrected = 0.0  # s predicted without a sensor row fused
        self._period = 0.0  # s spanned by the last update with samples
        self.diagnostics = UkfDiagnostics()
        bounds = PlausibilityBounds.from_robot(d, calibration)
        self._screen = PlausibilityScreen(
            d, bounds, c.stream_failure_window, self.diagnostics.implausible_by_kind
        )
        self._absorb(samples)
        if c.initial_positions is not None:
            nodes = np.asarray(c.initial_positions, dtype=np.float64)
            if nodes.shape != (n, 3):
                raise ValueError(
                    f"UkfConfig.initial_positions has shape {nodes.shape}, expected {(n, 3)}"
                )
            if not np.all(np.isfinite(nodes)):
                raise ValueError("UkfConfig.initial_positions has non-finite entries")
        else:
            nodes = self._fit()
        self._start(nodes)
        self._ready = True
        return self._estimate(reinitialised=False)

    def _fit(self) -> NDArray[np.float64]:
        c = self.config
        pairs, ranges, _ = _select(
            self._ranges, self._module_allowed, c.use_robot_ranges, self.description.n_nodes,
            for_fit=True,
        )  # fmt: skip
        return fit_initial_shape(
            self.description,
            self.measurements,
            axes=self._latest_axes if c.use_imu else {},
            range_pairs=pairs,
            ranges=ranges - self.offsets[pairs[:, 0], pairs[:, 1]],
            range_sigma=c.range_sigma,
            axis_sigma=c.axis_sigma,
            cable_lengths=self._latest_cables if c.use_cable_lengths else None,
            cable_sigma=c.cable_sigma,
            contact_nodes=self._latest_contacts if c.use_contacts else None,
        ).node_positions

    def _start(self, nodes: NDArray[np.float64]) -> None:
        c = self.config
        n = self.description.n_nodes
        L = self.description.characteristic_length
        x = np.concatenate([nodes.ravel(), np.zeros(3 * n)])
        # Where the robot is is uncertain, its shape much less so: independent errors
        # of centimetres would stretch the stiff rods, or sink the nodes into the
        # ground, of every sigma point and fling them apart in the first predict.
        P = np.zeros((6 * n, 6 * n))
        # The ground fixes the height: the robot as a whole is uncertain horizontally.
        P[: 3 * n, : 3 * n] = (c.initial_position_sigma * L) ** 2 * np.kron(
            np.ones((n, n)), np.diag([1.0, 1.0, 0.0])
        ) + (c.initial_shape_sigma * L) ** 2 * np.eye(3 * n)
        P[3 * n :, 3 * n :] = (c.initial_velocity_sigma * L) ** 2 * np.eye(3 * n)
        self._initial_P = P
        self.filter = UnscentedKalmanFilter(x, P.copy(), c.sigma_points)
        self._nis_window: deque[float] = deque(maxlen=c.divergence_window)
        self._clear_lockout()
        self._updates_since_reset: int | None = None  # no covariance reset yet
        self._updates_since_start = 0
        self._last_range_reject: float | None = None

    def _clear_lockout(self) -> None:
        self._range_rejects: deque[float] = deque(maxlen=self.config.lockout_updates)
        self._axis_reject_run = np.zeros(self.description.n_rods, dtype=np.intp)

    # ------------------------------------------------------------------ samples

    def _absorb(self, samples: Sequence[Sample]) -> tuple[list[_Round], bool]:
        """Keep the latest of each sensor; return this period's UWB rounds and whether
        an encoder reading arrived.

        Only what the plausibility screen passes is kept; the clock still advances with
        every sample, plausible or not.
        """
        if samples:
            self._t = max(self._t, max(s.t for s in samples))
        rounds: list[_Round] = []
        latest_ahrs: dict[int, AhrsSample] = {}
        encoders: list[EncoderSample] = []
        latest_cables: CableLengthSample | None = None
        latest_contacts: ContactSample | None = None
        # Most samples are raw IMU readings, which the filter does not use; of the
        # rest only the newest of each kind counts, except the UWB rounds.
        for s in self._screen.screen(samples):
            if isinstance(s, ImuSample):
                continue
            if isinstance(s, AhrsSample):
                latest_ahrs[s.rod] = s
            elif isinstance(s, UwbRangeSample):
                rounds.append(_Round.of(s))
            elif isinstance(s, EncoderSample):
                encoders.append(s)
            elif isinstance(s, CableLengthSample):
                latest_cables = s
            elif isinstance(s, ContactSample):
                latest_contacts = s
        if encoders:
            self._rest = np.asarray(encoders[-1].rest_lengths, dtype=np.float64)
        if latest_cables is not None:
            self._cables = np.asarray(latest_cables.lengths, dtype=np.float64)
            self._latest_cables = self._cables
        if latest_contacts is not None:
            self._contacts = np.flatnonzero(latest_contacts.in_contact).astype(np.intp)
            self._latest_contacts = self._contacts
        self._axes_before = {}
        for rod, sample in latest_ahrs.items():
            q = np.asarray(sample.quaternion, dtype=np.float64)
            self._axes_before[rod] = self._latest_axes.get(rod)
            self._axes[rod] = ahrs_axis(q / np.linalg.norm(q))
            self._latest_axes[rod] = self._axes[rod]
        self._ranges = _recent([*self._ranges, *rounds], self._t, self.config.range_window)
        return rounds, bool(encoders)

    # ------------------------------------------------------------------ filtering

    def update(self, samples: Sequence[Sample], command: NDArray[np.float64]) -> Estimate:
        """Predict over the time the samples span, then correct with them."""
        if not self._ready:
            raise RuntimeError("call reset() before update()")
        with single_threaded_blas():
            return self._update(samples, command)

    def _update(self, samples: Sequence[Sample], command: NDArray[np.float64]) -> Estimate:
        step = self.prepare(samples, command)
        try:
            result = self.apply(step, self.filter)
        except (CholeskyError, np.linalg.LinAlgError, FloatingPointError) as err:
            log.warning("UKF numerics failed (%s); re-initialising", err)
            return self._reinitialise()
        self._record(step.batch, result)
        self._forget_gated(step.batch, result)
        self._count_prediction(step, result)
        self._updates_since_start += 1
        reason = self._divergence()
        if reason is not None:
            log.info("UKF diverged (%s); re-initialising", reason)
            if reason == _JUMPED:
                # This period's anchor ranges were what disagreed: they may be the bad
                # ones (a corrupted round), so none of its rounds is fitted to, even
                # the ranges the gate let through.
                for r in self._period_rounds:
                    r.for_fit[:] = False
            return self._reinitialise()
        if self._updates_since_reset is not None:
            self._updates_since_reset += 1
        if self._locked_out():
            # A filter that has slid away gates out the very rows that would pull it
            # back, while the rows it still accepts look consistent. Widen the
            # covariance so they are heard again; if that does not help, start over.
            recent = self._updates_since_reset
            if recent is not None and recent < 10 * self.config.lockout_updates:
                return self._reinitialise()
            self.diagnostics.covariance_resets += 1
            self.filter.P = self.filter.P + self._initial_P
            self._clear_lockout()
            self._updates_since_reset = 0
        return self._estimate(reinitialised=False)

    @property
    def _gating(self) -> bool:
        # Right after (re)initialisation the state is still far off: gating then would
        # throw away the rows that pull it in.
        return self._updates_since_start >= self.config.gate_after

    def _locked_out(self) -> bool:
        c = self.config
        rejects = self._range_rejects
        if len(rejects) == rejects.maxlen and min(rejects) > c.lockout_range_share:
            return True
        return bool(np.any(self._axis_reject_run >= c.lockout_updates))

    def prepare(self, samples: Sequence[Sample], command: NDArray[np.float64]) -> FilterStep:
        """Take in the samples of one period and say what the filter must do with them.

        :meth:`update` is ``apply(prepare(samples, command), self.filter)`` plus the
        book-keeping; the two halves are public so that a benchmark can run the same
        filter step through another UKF implementation.
        """
        if not self._ready:
            raise RuntimeError("call reset() before prepare()")
        t_before = self._t
        rest_before = self._rest.copy()
        rounds, encoder = self._absorb(samples)
        if not encoder and np.all(np.isfinite(command)):
            # No encoder reading this period: trust that the motors follow the command.
            self._rest = np.asarray(command, dtype=np.float64)
        dt = max(self._t - t_before, 0.0)
        n = self.description.n_nodes
        q = np.concatenate([np.full(3 * n, self._q_pos * dt), np.full(3 * n, self._q_vel * dt)])
        return FilterStep(dt, rest_before, self._rest.copy(), q, self._batch(rounds))

    def apply(self, step: FilterStep, ukf: UnscentedKalmanFilter) -> UpdateResult:
        """Predict ``ukf`` over the step's duration, then update it with its batch."""
        if step.duration > 0:

            def fx(sigmas: NDArray[np.float64]) -> NDArray[np.float64]:
                return self.model.propagate(sigmas, step.duration, step.rest_start, step.rest_end)

            ukf.predict(fx, step.process_noise)
        batch = step.batch
        return ukf.update(
            batch.z,
            batch.variance,
            lambda sigmas: self.measurements.predict(batch, sigmas),
            batch.groups,
            self.config.gate_probability if self._gating else None,
        )

    def _batch(self, rounds: list[_Round]) -> MeasurementBatch:
        c = self.config
        pairs, ranges, index = _select(
            rounds if c.use_ranges else [],
            self._module_allowed, c.use_robot_ranges, self.description.n_nodes,
        )  # fmt: skip
        # Which buffered ranges the rows are, for the gate's verdicts to reach them.
        self._period_rounds, self._period_range_index = rounds, index
        offsets = self.offsets[pairs[:, 0], pairs[:, 1]]
        L = self.description.characteristic_length
        batch = self.measurements.batch(
            axes=self._axes if c.use_imu else None,
            axis_variance=c.axis_sigma**2,
            range_pairs=pairs,
            ranges=ranges,
            range_offsets=offsets,
            range_variance=c.range_sigma**2,
            cable_lengths=self._cables if c.use_cable_lengths else None,
            cable_variance=c.cable_sigma**2,
            rod_variance=(c.rod_length_sigma * L) ** 2,
            contact_nodes=self._contacts if c.use_contacts else None,
            contact_variance=c.contact_sigma**2,
        )
        # Each reading is used once: the next update waits for fresh ones.
        self._axes = {}
        self._cables = None
        self._contacts = None
        return batch

    def _record(self, batch: MeasurementBatch, result: UpdateResult) -> None:
        kinds = batch.kind
        diag = self.diagnostics
        diag.updates += 1
        diag.rows += result.n_measurements
        diag.rejected_rows += result.n_rejected
        for k, count in zip(*np.unique(kinds[~result.accepted], return_counts=True), strict=True):
            name = RowKind(int(k)).name.lower()
            diag.rejected_by_kind[name] = diag.rejected_by_kind.get(name, 0) + int(count)
        if result.jitter > 0:
            diag.jitter_events += 1
        diag.last_update = result
        accepted = int(np.count_nonzero(result.accepted))
        ranges = kinds == RowKind.RANGE
        if np.count_nonzero(ranges) >= 5:
            self._range_rejects.append(float(np.mean(~result.accepted[ranges])))
        # Ranges to the anchors place the robot; those between its own nodes only
        # shape it, and still fit when the whole estimate has jumped.
        to_anchor = (batch.range_pairs >= self.description.n_nodes).any(axis=1)
        self._last_range_reject = None
        if np.count_nonzero(to_anchor) >= 5:
            rejected = ~result.accepted[ranges][to_anchor]
            self._last_range_reject = float(np.mean(rejected))
        if batch.axis_rods.size:
            # Axis rows come first, three a rod.
            rejected = ~result.accepted[: 3 * batch.axis_rods.size].reshape(-1, 3).all(axis=1)
            run = self._axis_reject_run
            run[batch.axis_rods] = np.where(rejected, run[batch.axis_rods] + 1, 0)
        if accepted:
            nis = result.nis / accepted
            diag.nis_history.append(nis)
            self._nis_window.append(nis)

    def _forget_gated(self, batch: MeasurementBatch, result: UpdateResult) -> None:
        """Take back from re-initialisation every reading the chi-square gate rejected:
        a range is marked not to fit, a rod's axis reverts to its last accepted one, a
        cable's reading and a contact are dropped."""
        rejected = ~result.accepted
        if not rejected.any():
            return
        ranges = rejected[batch.kind == RowKind.RANGE]
        if ranges.any():
            flat = self._period_range_index[ranges]
            sizes = np.array([len(r.ranges) for r in self._period_rounds])
            ends = np.cumsum(sizes)
            which = np.searchsorted(ends, flat, side="right")
            for j, k in zip(which, flat - (ends - sizes)[which], strict=True):
                self._period_rounds[j].for_fit[k] = False
        if batch.axis_rods.size:
            gated = rejected[: 3 * batch.axis_rods.size].reshape(-1, 3).any(axis=1)
            for rod in batch.axis_rods[gated].tolist():
                before = self._axes_before.get(rod)
                if before is None:
                    self._latest_axes.pop(rod, None)
                else:
                    self._latest_axes[rod] = before
        cables = batch.cables[rejected[batch.kind == RowKind.CABLE_LENGTH]]
        if cables.size and self._latest_cables is not None:
            self._latest_cables = self._latest_cables.copy()
            self._latest_cables[cables] = np.nan
        contacts = batch.contact_nodes[rejected[batch.kind == RowKind.CONTACT_HEIGHT]]
        if contacts.size and self._latest_contacts is not None:
            self._latest_contacts = np.setdiff1d(self._latest_contacts, contacts)

    def _count_prediction(self, step: FilterStep, result: UpdateResult) -> None:
        """Add up the time predicted since a sensor row was last fused."""
        if np.any(result.accepted & (step.batch.kind != RowKind.ROD_LENGTH)):
            self._uncorrected = 0.0
        else:
            # An update without samples spans no sample time: count it as the last did.
            self._uncorrected += step.duration if step.duration > 0 else self._period
        if step.duration > 0:
            self._period = step.duration

    def _divergence(self) -> str | None:
        """Why the filter has diverged, or None."""
        c = self.config
        x, P = self.filter.x, self.filter.P
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(P))):
            return "non-finite state"
        d = self.description
        nodes = x[: 3 * d.n_nodes].reshape(-1, 3)
        rod_len = self.measurements.rod_lengths
        strain = np.abs(member_lengths(nodes, d.rod_nodes) / rod_len - 1.0)
        if np.any(strain > c.divergence_rod_strain):
            return "rods stretched"
        if np.max(np.diag(P)[: 3 * d.n_nodes]) > (10.0 * d.characteristic_length) ** 2:
            return "covariance exploded"
        ranges = self._last_range_reject
        if ranges is not None and ranges > c.divergence_anchor_reject_share:
            return _JUMPED
        window = self._nis_window
        if len(window) == window.maxlen and float(np.mean(window)) > c.divergence_nis:
            return "innovations too large"
        return None

    def _reinitialise(self) -> Estimate:
        self.diagnostics.reinitialisations += 1
        try:
            nodes = self._fit()
        except (InitialisationError, ValueError, np.linalg.LinAlgError) as err:
            log.warning("UKF re-initialisation failed (%s); keeping the last estimate", err)
            x = self.filter.x
            if not np.all(np.isfinite(x)):
                # Nothing finite to fall back on: the description's resting shape.
                nodes = self.description.initial_positions
            else:
                nodes = x[: 3 * self.description.n_nodes].reshape(-1, 3)
            self._start(nodes)
            return replace(self._estimate(reinitialised=True), healthy=False)
        self._start(nodes)
        self._uncorrected = 0.0  # placed by the samples just now
        return self._estimate(reinitialised=True)

    def _estimate(self, *, reinitialised: bool) -> Estimate:
        d = self.description
        n = d.n_nodes
        x = self.filter.x
        nodes = x[: 3 * n].reshape(n, 3).copy()
        velocities = x[3 * n :].reshape(n, 3).copy()
        return Estimate(
            t=self._t,
            node_positions=nodes,
            node_velocities=velocities,
            com=center_of_mass(nodes, d.node_masses),
            rest_lengths=self._rest.copy(),
            covariance=self.filter.P.copy(),
            healthy=not reinitialised
            and self._uncorrected <= self.config.max_prediction_time + _TIME_TOLERANCE,
            reinitialised=reinitialised,
            failed_streams=self._screen.failed,
            rejected=dict(self.diagnostics.implausible_by_kind),
        )
