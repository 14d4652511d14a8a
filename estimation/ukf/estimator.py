"""The UKF of Caluwaerts et al. 2016 as an :class:`Estimator`: samples and commands in, estimate
out.

Each control period the filter predicts the spring-mass net forward with the motor
encoders' rest lengths as its input, then corrects it with what arrived: rod axes from
the AHRS, UWB ranges minus the pair offsets, cable lengths, and the rod-length and
ground-contact pseudo-measurements. Its state is the node positions and velocities
(6 n,), then (with the AHRS in use) the rotation vector (3,) from the AHRS's frame to
the world's, which a sloping floor or anchors surveyed off level make other than zero,
then the description's error: each actuated cable's rest length against its encoder,
each rod's length (:class:`~estimation.ukf.state.StateLayout`).
Before anything is kept, readings that are physically implausible are dropped and
counted (:mod:`estimation.screen`), and a stream that gives nothing plausible for
``stream_failure_window`` is failed and not used until it has been plausible as long.
Outliers are gated; a filter that diverges re-initialises itself from recent samples,
never from what the gate rejected, and says so in the estimate. An estimate is unhealthy
after ``max_prediction_time`` without a sensor row fused.

The parts: :class:`~estimation.ukf.readings.Readings` keeps the samples,
:class:`~estimation.ukf.watchdog.FilterWatchdog` judges the gate's verdicts (lock-out,
divergence), :class:`~estimation.health.EstimatorHealth` counts divergences and
re-initialisations and fills the estimate's health fields, :class:`UkfDiagnostics`
counts rows. Time is the samples' own in integer nanoseconds, so that every period, and
with it the number of integration substeps, is the same wherever the clock started.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from estimation.health import EstimatorHealth
from estimation.plausibility import PlausibilityBounds
from estimation.screen import PlausibilityScreen
from estimation.ukf.config import UkfConfig
from estimation.ukf.filter import UnscentedKalmanFilter, UpdateResult, single_threaded_blas
from estimation.ukf.initialise import MIN_ANCHOR_RANGES, InitialisationError, fit_initial_shape
from estimation.ukf.measurements import MeasurementBatch, MeasurementModel, RowKind
from estimation.ukf.process_noise import ProcessNoise
from estimation.ukf.readings import Readings, select_ranges
from estimation.ukf.sigma_points import CholeskyError
from estimation.ukf.spring_mass import SpringMassModel
from estimation.ukf.state import StateLayout
from estimation.ukf.watchdog import JUMPED, FilterWatchdog, Lockout
from tensegrity_gym.model.estimate import Estimate
from tensegrity_gym.model.kinematics import center_of_mass
from tensegrity_gym.model.lie import so3_exp
from tensegrity_gym.model.samples import ns_to_seconds, seconds_to_ns

if TYPE_CHECKING:
    from collections.abc import Sequence

    from numpy.typing import NDArray

    from estimation.ukf.readings import Round
    from estimation.ukf.spring_mass import Kernel
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import SensorCalibration
    from tensegrity_gym.model.samples import Sample

__all__ = ["FilterStep", "UkfConfig", "UkfDiagnostics", "UkfEstimator"]


log = logging.getLogger(__name__)

NOT_PLACED = "not placed at reset"
"""The re-initialisation a reset asks for when too few UWB ranges reached the anchors."""
FAILED_FIT_WARNING_INTERVAL_S = 10.0
"""Robot-clock seconds between warnings of failed re-initialisations: a robot out of UWB
reach fails every period, and one line says so; a later failure warns again."""


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
    """Q for this step: its diagonal (d,), or the whole (d, d) where nodes share noise
    (``UkfConfig.body_position_noise``); d is 6 n, or 6 n + 3 with the AHRS frame's
    alignment."""
    batch: MeasurementBatch
    duration_ns: int = 0
    """``duration`` in whole nanoseconds, as the samples' clock counts it."""


@dataclass
class UkfDiagnostics:
    """Counters a user or a test reads after the fact; the health counts (divergences,
    re-initialisations, implausible readings) are the estimator's
    :class:`~estimation.health.EstimatorHealth`'s."""

    updates: int = 0
    rows: int = 0
    rejected_rows: int = 0
    rejected_by_kind: dict[str, int] = field(default_factory=dict)
    """Rows the chi-square gate rejected, by :class:`RowKind` name."""
    covariance_resets: int = 0
    """Gate lock-outs answered by resetting the covariance."""
    jitter_events: int = 0
    last_update: UpdateResult | None = None
    nis_history: deque[float] = field(default_factory=lambda: deque(maxlen=1000))
    health: EstimatorHealth | None = field(default=None, repr=False)

    @property
    def reinitialisations(self) -> int:
        return 0 if self.health is None else self.health.reinitialisations

    @property
    def divergences(self) -> dict[str, int]:
        """Divergences by reason (``"rods stretched"``, ...)."""
        return {} if self.health is None else dict(self.health.divergences)

    @property
    def implausible_by_kind(self) -> dict[str, int]:
        """Readings dropped as physically implausible before the filter saw them, by kind
        (``"uwb_range_too_long"``, ``"cable_negative"``, ...: :mod:`estimation.plausibility`)."""
        return {} if self.health is None else self.health.implausible

    def record(self, batch: MeasurementBatch, result: UpdateResult, nis: float | None) -> None:
        """Count one update's rows and gate verdicts; ``nis`` per accepted row."""
        self.updates += 1
        self.rows += result.n_measurements
        self.rejected_rows += result.n_rejected
        kinds = batch.kind[~result.accepted]
        for k, count in zip(*np.unique(kinds, return_counts=True), strict=True):
            name = RowKind(int(k)).name.lower()
            self.rejected_by_kind[name] = self.rejected_by_kind.get(name, 0) + int(count)
        if result.jitter > 0:
            self.jitter_events += 1
        self.last_update = result
        if nis is not None:
            self.nis_history.append(nis)


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


class UkfEstimator:
    """The unscented Kalman filter over the spring-mass net (Caluwaerts et al. 2016, section IV).

    Args:
        config: tuning; defaults work for the presets.
    """

    needs_camera = False
    filter: UnscentedKalmanFilter
    """The filter over the state (made at reset, again at each re-initialisation)."""

    def __init__(self, config: UkfConfig | None = None) -> None:
        self.config = config if config is not None else UkfConfig()
        self.diagnostics = UkfDiagnostics()
        self._ready = False
        self._unplaced = False
        """Whether the reset could not place the robot (too few UWB ranges yet)."""
        self._failed_fits = 0
        """Re-initialisations that found no fit since the last that placed the robot."""
        self._fit_warned_ns: int | None = None
        """Robot-clock ns of the last warning of a failed re-initialisation."""

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
        readings = self._readings(description, calibration, samples, np.zeros(0))
        readings.absorb(samples)
        n = description.n_nodes
        pairs, _, _ = select_ranges(readings.rounds, allowed, c.use_robot_ranges, n, for_fit=True)
        found = int(np.count_nonzero((pairs >= n).any(axis=1)))
        if found >= MIN_ANCHOR_RANGES:
            return None
        rejected = readings.screen.rejected
        dropped = sum(v for kind, v in rejected.items() if kind.startswith("uwb"))
        note = f" ({dropped} implausible ones dropped)" if dropped else ""
        return f"{found} UWB ranges to anchors, {MIN_ANCHOR_RANGES} needed{note}"

    def _readings(
        self,
        description: RobotDescription,
        calibration: SensorCalibration,
        samples: Sequence[Sample],
        rest: NDArray[np.float64],
    ) -> Readings:
        """An empty sample buffer behind a new plausibility screen, its clock at the
        newest of ``samples``."""
        c = self.config
        bounds = PlausibilityBounds.from_robot(description, calibration)
        screen = PlausibilityScreen(description, bounds, c.stream_failure_window)
        timely = screen.timely(samples)
        t_ns = seconds_to_ns(max((s.t for s in timely), default=0.0))
        return Readings(screen, c.range_window, t_ns, rest)

    def _reset(
        self,
        description: RobotDescription,
        calibration: SensorCalibration,
        samples: Sequence[Sample],
        command: NDArray[np.float64],
    ) -> Estimate:
        c = self.config
        d = description
        self._ready = False  # nothing of the last episode (its floor) carries over
        self.description = d
        self.model = SpringMassModel(d, c.model)
        anchors, self.offsets, self._module_allowed = _ranging(c, d, calibration)
        self.layout = layout = StateLayout.of(c, d)
        self.measurements = MeasurementModel(
            d, anchors, d.sensors.uwb.module_offset, layout.alignment,
            layout.rod_offsets(d.n_cables),
        )  # fmt: skip
        self.process_noise = ProcessNoise(c, d, layout.n_offsets)
        rest = np.asarray(command, dtype=np.float64).copy()
        self.readings = self._readings(d, calibration, samples, rest)
        self.health = EstimatorHealth(c.health, self.readings.screen)
        self.diagnostics = UkfDiagnostics(health=self.health)
        self.readings.absorb(samples)
        self._unplaced = False
        self._failed_fits = 0
        self._fit_warned_ns = None
        if c.initial_positions is not None:
            nodes = np.asarray(c.initial_positions, dtype=np.float64)
            n = d.n_nodes
            if nodes.shape != (n, 3):
                raise ValueError(
                    f"UkfConfig.initial_positions has shape {nodes.shape}, expected {(n, 3)}"
                )
            if not np.all(np.isfinite(nodes)):
                raise ValueError("UkfConfig.initial_positions has non-finite entries")
        else:
            nodes = self._first_fit()
        self._start(nodes)
        self._ready = True
        return self._estimate()

    def _first_fit(self) -> NDArray[np.float64]:
        """The reset's node positions from its samples; where too few UWB ranges reached
        the anchors (packets lost), the description's resting shape, placed by the first
        update that has them (:meth:`_place`), and unhealthy until then."""
        try:
            return self._fit()
        except InitialisationError as err:
            log.warning("UKF not placed at reset (%s): placed once enough ranges arrive", err)
            self._unplaced = True
            self.health.request_reinitialisation(NOT_PLACED)
            return np.asarray(self.description.initial_positions, dtype=np.float64)

    def _place(self) -> Estimate | None:
        """Start again from the samples so far if the reset could not place the robot
        and now can; None otherwise."""
        try:
            nodes = self._fit()
        except (InitialisationError, ValueError, np.linalg.LinAlgError):
            return None
        return self._placed(nodes)

    def _placed(self, nodes: NDArray[np.float64]) -> Estimate:
        """Start over from ``nodes`` (n, 3), m, fitted to the samples just now."""
        if self._failed_fits > 1:
            log.info("UKF re-initialised after %d failed attempts", self._failed_fits)
        kept = self._kept_calibration()
        self._failed_fits = 0
        self._unplaced = False
        self._start(nodes, kept)
        self.health.reinitialised(placed=True)
        return self._estimate()

    def _fit(self) -> NDArray[np.float64]:
        c = self.config
        r = self.readings
        pairs, ranges, _ = select_ranges(
            r.rounds, self._module_allowed, c.use_robot_ranges, self.description.n_nodes,
            for_fit=True,
        )  # fmt: skip
        # The AHRS's axes turned into the world's by the alignment the filter keeps.
        turn = so3_exp(self._kept_alignment())
        return fit_initial_shape(
            self.description,
            self.measurements,
            axes={rod: turn @ u for rod, u in r.latest_axes.items()} if c.use_imu else {},
            range_pairs=pairs,
            ranges=ranges - self.offsets[pairs[:, 0], pairs[:, 1]],
            range_sigma=c.range_sigma,
            axis_sigma=c.axis_sigma,
            cable_lengths=r.latest_cables if c.use_cable_lengths else None,
            cable_sigma=c.cable_sigma,
            contact_nodes=r.latest_contacts if c.use_contacts else None,
        ).node_positions

    def _start(self, nodes: NDArray[np.float64], kept: NDArray[np.float64] | None = None) -> None:
        """Start the filter at ``nodes`` (n, 3), m, at rest, uncertain by its prior, with
        the calibration ``kept`` (the alignment (3,), rad, then the description's
        errors, m: :meth:`_kept_calibration`; a re-initialisation: the floor and the
        robot have not changed; None: zero)."""
        c, layout = self.config, self.layout
        n = self.description.n_nodes
        L = self.description.characteristic_length
        x = np.zeros(layout.dim)
        x[: 3 * n] = nodes.ravel()
        # Where the robot is is uncertain, its shape much less so: independent errors
        # of centimetres would stretch the stiff rods, or sink the nodes into the
        # ground, of every sigma point and fling them apart in the first predict.
        P = np.zeros((layout.dim, layout.dim))
        # The ground fixes the height: the robot as a whole is uncertain horizontally.
        P[: 3 * n, : 3 * n] = (c.initial_position_sigma * L) ** 2 * np.kron(
            np.ones((n, n)), np.diag([1.0, 1.0, 0.0])
        ) + (c.initial_shape_sigma * L) ** 2 * np.eye(3 * n)
        P[3 * n : 6 * n, 3 * n : 6 * n] = (c.initial_velocity_sigma * L) ** 2 * np.eye(3 * n)
        if layout.alignment is not None and c.alignment_sigma is not None:
            a = layout.alignment
            P[a : a + 3, a : a + 3] = c.alignment_sigma**2 * np.eye(3)
        if layout.offsets is not None:
            o = layout.offsets
            P[o:, o:] = np.diag(layout.prior_sigma**2)
        if kept is not None:
            x[6 * n :] = kept
        self._initial_P = P
        self.filter = UnscentedKalmanFilter(x, P.copy(), c.sigma_points)
        self.watchdog = FilterWatchdog(c, self.description, self.measurements.rod_lengths)

    def _kept_alignment(self) -> NDArray[np.float64]:
        """(3,) rad: the alignment a re-initialisation keeps (:meth:`_kept_calibration`),
        zeros where the state has none."""
        if self.layout.alignment is None:
            return np.zeros(3)
        return self._kept_calibration()[:3]

    def _kept_calibration(self) -> NDArray[np.float64]:
        """The alignment (3,), rad, and the description's errors (k,), m, a
        re-initialisation starts from: the filter's, unless there are none yet (a
        reset) or the robot was never placed (the template shape's orientation, not the
        floor's, would be in the alignment), in which case zero; each part also zero
        where it went beyond reach of its prior (5 sigma: a diverged state's)."""
        layout = self.layout
        n6 = 6 * self.description.n_nodes
        kept = np.zeros(layout.dim - n6)
        if not self._ready or self._unplaced:
            return kept
        x = self.filter.x[n6:]
        if layout.alignment is not None:
            phi = x[:3]
            reach = 5.0 * (self.config.alignment_sigma or 0.0)
            if np.all(np.isfinite(phi)) and float(np.linalg.norm(phi)) <= reach:
                kept[:3] = phi
        if layout.offsets is not None:
            o = layout.offsets - n6
            errors = x[o:]
            fine = np.isfinite(errors) & (np.abs(errors) <= 5.0 * layout.prior_sigma)
            kept[o:] = np.where(fine, errors, 0.0)
        return kept

    @property
    def ahrs_alignment(self) -> NDArray[np.float64]:
        """(3,) rad: the rotation vector from the AHRS's frame to the world's as estimated
        (``UkfConfig.alignment_sigma``); zeros where it is not estimated."""
        if not self._ready:
            raise RuntimeError("call reset() before reading ahrs_alignment")
        a = self.layout.alignment
        return self.filter.x[a : a + 3].copy() if a is not None else np.zeros(3)

    @property
    def description_errors(self) -> dict[str, NDArray[np.float64]]:
        """The description's errors as estimated, m: ``"rest_lengths"`` (m,) what each
        actuated cable's rest length adds to its encoder's reading, ``"rod_lengths"``
        (r,) what each rod's length adds to the description's; zeros where the filter
        does not estimate them (``UkfConfig.rest_length_error_sigma``,
        ``rod_length_error_sigma``)."""
        if not self._ready:
            raise RuntimeError("call reset() before reading description_errors")
        d, layout = self.description, self.layout
        offsets = layout.member_offsets(self.filter.x, d.n_cables + d.n_rods)
        member = np.zeros(d.n_cables + d.n_rods) if offsets is None else offsets[0]
        return {"rest_lengths": member[d.actuated], "rod_lengths": member[d.n_cables :]}

    # ------------------------------------------------------------------ filtering

    def update(self, samples: Sequence[Sample], command: NDArray[np.float64]) -> Estimate:
        """Predict over the time the samples span, then correct with them."""
        if not self._ready:
            raise RuntimeError("call reset() before update()")
        with single_threaded_blas():
            return self._update(samples, command)

    def _update(self, samples: Sequence[Sample], command: NDArray[np.float64]) -> Estimate:
        step = self.prepare(samples, command)
        if self._unplaced and (placed := self._place()) is not None:
            return placed
        try:
            result = self.apply(step, self.filter)
        except (CholeskyError, np.linalg.LinAlgError, FloatingPointError) as err:
            log.warning("UKF numerics failed (%s); re-initialising", err)
            self.health.diverged("numerics failed")
            return self._reinitialise()
        batch = step.batch
        self.diagnostics.record(batch, result, self.watchdog.observe(batch, result))
        self.readings.forget_gated(batch, result.accepted)
        fused = np.any(result.accepted & (batch.kind != RowKind.ROD_LENGTH))
        self.health.predicted(step.duration_ns, corrected=bool(fused))
        return self._judge()

    def _judge(self) -> Estimate:
        """The estimate after an update, or after the re-initialisation or covariance
        reset that the watchdog's verdict calls for."""
        reason = self.watchdog.divergence(self.filter.x, self.filter.P)
        if reason is not None:
            log.info("UKF diverged (%s); re-initialising", reason)
            if reason == JUMPED:
                # This period's anchor ranges were what disagreed: they may be the bad
                # ones (a corrupted round), so none of its rounds is fitted to, even
                # the ranges the gate let through.
                self.readings.blame_period()
            self.health.diverged(reason)
            return self._reinitialise()
        lockout = self.watchdog.lockout()
        if lockout is Lockout.REINITIALISE:
            self.health.diverged("gate lock-out soon after a covariance reset")
            return self._reinitialise()
        if lockout is Lockout.RESET_COVARIANCE:
            # Widen the covariance so that the rows the gate shut out are heard again.
            self.diagnostics.covariance_resets += 1
            self.filter.P = self.filter.P + self._initial_P
        return self._estimate()

    def prepare(self, samples: Sequence[Sample], command: NDArray[np.float64]) -> FilterStep:
        """Take in the samples of one period and say what the filter must do with them.

        :meth:`update` is ``apply(prepare(samples, command), self.filter)`` plus the
        book-keeping; the two halves are public so that a benchmark can run the same
        filter step through another UKF implementation.
        """
        if not self._ready:
            raise RuntimeError("call reset() before prepare()")
        r = self.readings
        t_before = r.t_ns
        rest_before = r.rest.copy()
        rounds, encoder = r.absorb(samples)
        if not encoder and np.all(np.isfinite(command)):
            # No encoder reading this period: trust that the motors follow the command.
            r.rest = np.asarray(command, dtype=np.float64)
        dt_ns = max(r.t_ns - t_before, 0)
        dt = ns_to_seconds(dt_ns)
        heights = self.filter.x[2 : 3 * self.description.n_nodes : 3]
        q = self.process_noise.covariance(dt, rest_before, r.rest, heights)
        return FilterStep(dt, rest_before, r.rest.copy(), q, self._batch(rounds), dt_ns)

    def propagate(
        self, states: NDArray[np.float64], step: FilterStep, kernel: Kernel | None = None
    ) -> NDArray[np.float64]:
        """``states`` (S, d) or (d,) after the step's duration (a new array): the nodes by
        the spring-mass model (``kernel``: another implementation of it), with each
        state's own rest lengths where it carries the description's errors; those and
        the AHRS frame's alignment held."""
        k = self.model.state_dim
        d = self.description
        offsets = self.layout.member_offsets(states, d.n_cables + d.n_rods)
        nodes = self.model.propagate(
            states[..., :k], step.duration, step.rest_start, step.rest_end,
            offsets=offsets, kernel=kernel,
        )  # fmt: skip
        if states.shape[-1] == k:
            return nodes
        return np.concatenate([nodes, states[..., k:]], axis=-1)

    def apply(self, step: FilterStep, ukf: UnscentedKalmanFilter) -> UpdateResult:
        """Predict ``ukf`` over the step's duration, then update it with its batch."""
        if step.duration > 0:
            ukf.predict(lambda sigmas: self.propagate(sigmas, step), step.process_noise)
        batch = step.batch
        return ukf.update(
            batch.z,
            batch.variance,
            lambda sigmas: self.measurements.predict(batch, sigmas),
            batch.groups,
            self.config.gate_probability if self.watchdog.gating else None,
        )

    def _batch(self, rounds: list[Round]) -> MeasurementBatch:
        """The measurements of the readings not yet fused and this period's ``rounds``."""
        c = self.config
        pairs, ranges, index = select_ranges(
            rounds if c.use_ranges else [],
            self._module_allowed, c.use_robot_ranges, self.description.n_nodes,
        )  # fmt: skip
        # Each reading is used once: the next update waits for fresh ones. The range
        # rows' places let the gate's verdicts reach the buffered rounds.
        fresh = self.readings.take(rounds, index)
        L = self.description.characteristic_length
        return self.measurements.batch(
            axes=fresh.axes if c.use_imu else None,
            axis_variance=c.axis_sigma**2,
            range_pairs=pairs,
            ranges=ranges,
            range_offsets=self.offsets[pairs[:, 0], pairs[:, 1]],
            range_variance=c.range_sigma**2,
            cable_lengths=fresh.cables if c.use_cable_lengths else None,
            cable_variance=c.cable_sigma**2,
            rod_variance=(c.rod_length_sigma * L) ** 2,
            contact_nodes=fresh.contacts if c.use_contacts else None,
            contact_variance=c.contact_sigma**2,
        )

    def _reinitialise(self) -> Estimate:
        """Start over from the recent samples (the health has counted why)."""
        try:
            nodes = self._fit()
        except (InitialisationError, ValueError, np.linalg.LinAlgError) as err:
            # A robot out of UWB reach fails every period: warn once, not at 10 Hz.
            self._failed_fits += 1
            t, last = self.readings.t_ns, self._fit_warned_ns
            interval = seconds_to_ns(FAILED_FIT_WARNING_INTERVAL_S)
            level = logging.DEBUG
            if self._failed_fits == 1 or last is None or t - last >= interval:
                level, self._fit_warned_ns = logging.WARNING, t
            log.log(level, "UKF re-initialisation failed (%s); keeping the last estimate", err)
            x = self.filter.x
            if not np.all(np.isfinite(x)):
                # Nothing finite to fall back on: the description's resting shape.
                nodes = self.description.initial_positions
            else:
                nodes = x[: 3 * self.description.n_nodes].reshape(-1, 3)
            self._start(nodes, self._kept_calibration())
            self.health.reinitialised(placed=False)
            return self._estimate()
        return self._placed(nodes)

    def _estimate(self) -> Estimate:
        d = self.description
        n = d.n_nodes
        x = self.filter.x
        nodes = x[: 3 * n].reshape(n, 3).copy()
        velocities = x[3 * n : 6 * n].reshape(n, 3).copy()
        estimate = Estimate(
            t=ns_to_seconds(self.readings.t_ns),
            node_positions=nodes,
            node_velocities=velocities,
            com=center_of_mass(nodes, d.node_masses),
            rest_lengths=self.readings.rest.copy(),
            covariance=self.filter.P[: 6 * n, : 6 * n].copy(),
        )
        filled = self.health.fill(estimate)
        return replace(filled, healthy=False) if self._unplaced else filled
