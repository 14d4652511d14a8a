"""The proprioceptive estimator of Tong et al. 2024 behind the :class:`Estimator` protocol
(``estimator="inekf"``): one IMU, the motor encoders and endcap contacts, nothing
outside the robot.

Per period, in the samples' time order: each reading of the base rod's IMU propagates
the right-invariant EKF over the time since the one before (the earlier reading held,
as an IMU integrates); each encoder reading, at most ``shape_rate`` times a second,
reconstructs the shape (Tong et al. 2024 section V); at each encoder or contact reading the
contacts are updated (from the contact sensors, or from the shape and gravity), endcaps
touching down are added to the state (eq. 9), those lifting off are marginalised
(eq. 10), and every endcap in contact corrects the state by forward kinematics
(eq. 11-14). The estimate's nodes are the pose applied to the shape.

It knows its position along the ground only relative to where it started (dead
reckoning: the frame of :mod:`estimation.inekf.initialise`), and its heading only
through the magnetometer at reset: both drift. Its height is pulled back to the floor
it started on by each endcap that touches down (``InekfConfig.floor_correction``).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from scipy.stats import chi2

from estimation.health import EstimatorHealth
from estimation.inekf.config import InekfConfig, noise_from_description
from estimation.inekf.contacts import ContactThresholds, ShapeContactDetector
from estimation.inekf.filter import RightInvariantEkf
from estimation.inekf.initialise import (
    base_imu_readings,
    initial_position,
    levelled,
    triad_orientation,
)
from estimation.inekf.shape import ShapeReconstructor
from estimation.plausibility import PlausibilityBounds
from estimation.screen import PlausibilityScreen
from tensegrity_gym.model.estimate import Estimate
from tensegrity_gym.model.kinematics import center_of_mass
from tensegrity_gym.model.lie import quat_to_matrix
from tensegrity_gym.model.samples import (
    AhrsSample,
    CableLengthSample,
    ContactSample,
    EncoderSample,
    ImuSample,
    ns_to_seconds,
    seconds_to_ns,
)

if TYPE_CHECKING:
    from collections.abc import Sequence

    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import SensorCalibration
    from tensegrity_gym.model.samples import Sample

__all__ = ["InekfEstimator"]

_UP = np.array([0.0, 0.0, 1.0])
_USED = (ImuSample, EncoderSample, CableLengthSample, ContactSample)
"""The kinds of samples the estimator reads after reset; the others (UWB, camera, the
AHRS's orientation, which only the start reads) are not screened."""
_USED_AT_START = (*_USED, AhrsSample)
CLIPPED = 0.999
"""An accelerometer axis reading at least this share of its full scale has clipped."""
SLIP_SLOPE = 0.5
"""An endcap slides along the ground: a contact whose kinematics are off by a vertical
part of more than this times the horizontal one has not slipped (a slope of 27
degrees, steeper than the valley's)."""
ROD_TILT_GAIN = 0.2
"""Gain of each rod's accelerometer low-pass per reading (about 25 ms at 200 Hz): its
tilt for the shape without the jolts of a roll."""


class InekfEstimator:
    """Pose by IMU propagation and contact kinematics, shape from the cable lengths.

    :attr:`health` counts divergences by reason (``"not finite"``, ``"too fast"``,
    ``"contacts refused"``: every contact correction refused for ``max_refused_time``); a
    shape that does not solve is counted in ``rejected`` as ``"shape_not_solved"`` and
    not used. Attributes after each update: :attr:`shape` (n_nodes, 3) body frame,
    :attr:`in_contact` (n_nodes,) bool.
    """

    needs_camera = False

    def __init__(self, config: InekfConfig | None = None) -> None:
        self.requested = config or InekfConfig()
        """The config as given; :attr:`config` is it set for the robot at reset
        (:meth:`InekfConfig.for_robot`)."""
        self.config = self.requested
        self.filter: RightInvariantEkf | None = None
        self.health = EstimatorHealth(self.config.health)
        self._rejected: dict[str, int] = {}

    # ------------------------------------------------------------------ protocol

    def initialisation_missing(
        self,
        description: RobotDescription,
        calibration: SensorCalibration,
        samples: Sequence[Sample],
    ) -> str | None:
        """What ``reset`` lacks: a reading of the base rod's IMU (tilt, heading) and of
        the encoders (the shape)."""
        rod = self.config.base_rod
        if not any(isinstance(s, ImuSample) and s.rod == rod for s in samples):
            name = description.rods[rod].name if rod < description.n_rods else rod
            return f"no reading of the IMU on rod {name!r} (the invariant EKF's body frame)"
        if not any(isinstance(s, EncoderSample) for s in samples):
            return "no encoder reading (the invariant EKF reconstructs the shape from it)"
        return None

    def reset(
        self,
        description: RobotDescription,
        calibration: SensorCalibration,
        samples: Sequence[Sample],
        command: NDArray[np.float64],
        rng: np.random.Generator,
    ) -> Estimate:
        d = description
        if not 0 <= self.requested.base_rod < d.n_rods:
            raise ValueError(
                f"InekfConfig.base_rod {self.requested.base_rod} is not a rod of {d.name!r}"
            )
        self.filter = None  # a reset that fails leaves no filter beside the new contacts
        c = self.config = self.requested.for_robot(d)
        assert c.contact_std is not None and c.kinematics_std is not None  # set for the robot
        self.description = d
        self._rejected = {}
        self.floor_corrections = 0
        """How many contact heights the floor correction has used since the reset."""
        bounds = PlausibilityBounds.from_robot(d, calibration)
        self.screen = PlausibilityScreen(d, bounds, 1.0, self._rejected)
        self.health = EstimatorHealth(c.health, self.screen)
        self.reconstructor = ShapeReconstructor(d, c.shape, base_rod=c.base_rod)
        thresholds = c.contact_thresholds or ContactThresholds.for_rod_length(
            float(d.rods[c.base_rod].length)
        )
        self.detector = ShapeContactDetector(d.n_nodes, thresholds)
        self._gate = float(chi2.ppf(c.gate_probability, 3))
        self._full_scale = float(d.sensors.imu.accel_full_scale)
        self._clip = CLIPPED * self._full_scale
        self._gyro_full_scale = float(d.sensors.imu.gyro_full_scale)
        self._gyro_clip = CLIPPED * self._gyro_full_scale
        self._base_nodes = frozenset(int(n) for n in d.rod_nodes[c.base_rod])
        self._base_endcap_radius = float(d.rods[c.base_rod].endcap_radius)
        self._ground_reach = c.ground_reach * float(d.rods[c.base_rod].length)
        self._cov_touch = np.eye(3) * c.contact_std**2
        # (k, 3, 3) forward-kinematics covariances for k contacts, made once
        self._cov_kinematics = [np.repeat(np.eye(3)[None] * c.kinematics_std**2, k, axis=0)
                                for k in range(d.n_nodes + 1)]  # fmt: skip
        self._clipped = self._gyro_clipped = False
        # the base rod's turn about its axis since the last solve: the gyro's z (rad)
        # and the time (s) it ran over, for the bias; whether a reading clipped
        self._spin_turn = self._spin_time = 0.0
        self._spin_clipped = False
        self._imu_period = 1.0 / float(d.sensors.imu.rate)
        self._accel_spread = 0.0  # (m/s^2)^2: the base accelerometer's mean square off its low-pass
        self._rest = np.asarray(command, dtype=np.float64).copy()
        self._cables: NDArray[np.float64] | None = None
        self._sensed: NDArray[np.bool_] | None = None
        self.shape = self.reconstructor.rest_shape()
        self.in_contact = np.zeros(d.n_nodes, dtype=bool)
        self._rod_accel = np.full((d.n_rods, 3), np.nan)
        self._gyro = np.zeros(3)
        self._accel = np.zeros(3)
        self._imu_ns: int | None = None
        self._shape_ns: int | None = None
        self._refused_since_ns: int | None = None
        # 1 us short of the period, so that readings at exactly the rate are all due
        self._shape_period_ns = seconds_to_ns(1.0 / c.shape_rate) - 1000
        self._rest_sum, self._rest_n, self._resting = np.zeros(3), 0, True
        used = [s for s in samples if type(s) in _USED_AT_START]
        self._start(self.screen.screen(self.screen.timely(used)))
        return self._estimate(0, corrected=True)

    def update(self, samples: Sequence[Sample], command: NDArray[np.float64]) -> Estimate:
        if self.filter is None:
            raise RuntimeError("call reset() before update()")
        before = self._t_ns
        used = [s for s in samples if type(s) in _USED]
        corrected = self._consume(self.screen.screen(self.screen.timely(used)))
        self._check_divergence()
        return self._estimate(self._t_ns - before, corrected=corrected)

    # ------------------------------------------------------------------ start

    def _start(self, samples: Sequence[Sample]) -> None:
        """The filter from the reset's samples: tilt and heading from the IMU at rest,
        the gyro bias from its mean, the shape from the encoders."""
        c, d = self.config, self.description
        gyro, accel, mag = base_imu_readings(samples, c.base_rod)
        field = np.asarray(d.sensors.imu.magnetic_field, dtype=np.float64)
        ahrs = [s for s in samples if isinstance(s, AhrsSample) and s.rod == c.base_rod]
        if ahrs:  # the IMU's own fusion has averaged its magnetometer while it rested
            R = quat_to_matrix(ahrs[-1].quaternion)
        elif len(accel):
            R = triad_orientation(accel.mean(axis=0), mag.mean(axis=0), field)
        else:
            R = np.eye(3)
        bias_g = gyro.mean(axis=0) if len(gyro) else np.zeros(3)
        self._t_ns = seconds_to_ns(max((s.t for s in samples), default=0.0))
        for s in samples:
            if isinstance(s, ImuSample):
                self._low_pass(s.rod, np.ascontiguousarray(s.accel, dtype=np.float64))
            self._absorb(s)
        up = R.T @ _UP
        self._solve_shape(up)
        # The shape's period counts from this solve: at 10 Hz on a 0.1 s control period
        # the next ones fall on each period's last encoder reading, so the estimate's
        # shape is that of its own time (counted from the first reading of the next
        # period, it was 90 ms old, 3.0 instead of 2.7 cm RMS on the bench).
        self._shape_ns = self._t_ns
        p = initial_position(d, R, self.shape)
        noise = c.noise if c.noise is not None else noise_from_description(d)
        slip = noise.contact_velocity
        assert c.slip_per_rate is not None and c.slip_max is not None  # set for the robot
        self._slip_law = np.array([slip, c.slip_per_rate, max(c.slip_max, slip)])
        self._rolled_for: tuple[int, ...] | None = None
        self._roll_radii = np.zeros(0)
        self.filter = RightInvariantEkf(noise, gravity=np.array([0.0, 0.0, -d.gravity]))
        self.filter.reset(R, np.zeros(3), p, bias_g, np.zeros(3), self._initial_covariance(R))
        if len(gyro):
            self._gyro, self._accel = gyro[-1].copy(), accel[-1].copy()
            self._imu_ns = self._t_ns
        self._kinematics()

    def _initial_covariance(self, R: NDArray[np.float64]) -> NDArray[np.float64]:
        """(15, 15): right-invariant error of rotation, velocity, position, then gyro and
        accelerometer bias. Yaw is uncertain about the world z axis; in the right-invariant
        error the rotation part is in the world frame, so yaw is its z entry."""
        c = self.config
        tilt, yaw = c.initial_rotation_std**2, c.initial_yaw_std**2
        diag = np.concatenate([
            [tilt, tilt, yaw],
            np.full(3, c.initial_velocity_std**2),
            np.full(3, c.initial_position_std**2),
            np.full(3, c.initial_gyro_bias_std**2),
            np.full(3, c.initial_accel_bias_std**2),
        ])  # fmt: skip
        return np.diag(diag)

    # ------------------------------------------------------------------ samples

    def _absorb(self, s: Sample) -> bool:
        """Keep what ``s`` says of the shape and the contacts; True if it may change the
        contacts (an encoder or contact reading)."""
        if isinstance(s, EncoderSample):
            self._rest = np.asarray(s.rest_lengths, dtype=np.float64)
            return True
        if isinstance(s, CableLengthSample):
            self._cables = np.asarray(s.lengths, dtype=np.float64)
        elif isinstance(s, ContactSample) and self.config.contacts != "shape":
            self._sensed = np.asarray(s.in_contact, dtype=bool)
            return True
        return False

    def _consume(self, samples: Sequence[Sample]) -> bool:
        """Propagate and correct through ``samples``; True if a contact corrected.

        Encoder and contact readings of one stamp come together (both at 100 Hz on the
        presets): once the last of them is in, the contacts are updated and corrected and
        the shape is solved where one is due (:meth:`_settle`)."""
        corrected = False
        pending: int | None = None
        solve = False
        for s in samples:
            t_ns = seconds_to_ns(s.t)
            if pending is not None and t_ns != pending:
                corrected = self._settle(pending, solve) or corrected
                pending, solve = None, False
            if isinstance(s, ImuSample):
                accel = np.ascontiguousarray(s.accel, dtype=np.float64)
                self._low_pass(s.rod, accel)
                if s.rod == self.config.base_rod:
                    self._imu(s, t_ns, accel)
                continue
            if self._absorb(s):
                self._t_ns = max(self._t_ns, t_ns)
                if isinstance(s, EncoderSample) and self._shape_due(t_ns):
                    if self._sensed is None:  # the contacts come from the shape: solve now
                        self._solve_at(t_ns)
                    else:
                        solve = True
                pending = t_ns
        if pending is not None:
            corrected = self._settle(pending, solve) or corrected
        return corrected

    def _settle(self, t_ns: int, solve: bool) -> bool:
        """The readings stamped ``t_ns`` are all in: the contacts corrected
        (:meth:`_kinematics`), then, if ``solve``, the shape solved from the encoders on
        the sensed contacts of its own stamp and the corrected tilt (solved before the
        correction, which then used the new shape, one of the cross-world bench's
        own-world runs restarted 4 times; none this way). Solved as each encoder
        reading came, before the contact reading of its stamp, the shape took
        the endcaps of 10 ms before for those on the ground (the 1.45 m robot's
        cross-world runs: 2.1-2.2 cm shape RMSE on each world, 1.2-1.4 cm since).
        Without contact sensors the contacts come from the shape, which is solved as
        its encoder reading comes (:meth:`_consume`)."""
        corrected = self._kinematics()
        if solve:
            self._solve_at(t_ns)
        return corrected

    def _solve_at(self, t_ns: int) -> None:
        """The shape solved from the encoder reading stamped ``t_ns``, the next solve
        counted from it."""
        self._solve_shape(self._up())
        self._shape_ns = t_ns

    def _imu(self, s: ImuSample, t_ns: int, accel: NDArray[np.float64] | None = None) -> None:
        """Propagate over the time since the last reading with that reading held;
        ``accel``: the reading's as a (3,) float64 array, where the caller has it."""
        if self._imu_ns is not None and t_ns > self._imu_ns:
            dt = ns_to_seconds(t_ns - self._imu_ns)
            self._propagate(dt, self._lost_variance(dt))
        if self._imu_ns is None or t_ns >= self._imu_ns:
            self._imu_ns = t_ns
            self._gyro = np.ascontiguousarray(s.gyro, dtype=np.float64)
            self._accel = (
                np.ascontiguousarray(s.accel, dtype=np.float64) if accel is None else accel
            )
            smooth = self._rod_accel[self.config.base_rod]
            if not math.isnan(smooth[0]):
                off = self._accel - smooth
                self._accel_spread += ROD_TILT_GAIN * (float(off @ off) - self._accel_spread)
            ax, ay, az = self._accel.tolist()  # 3 floats: faster than numpy's reductions
            wx, wy, wz = self._gyro.tolist()
            self._clipped = max(abs(ax), abs(ay), abs(az)) >= self._clip
            self._gyro_clipped = max(abs(wx), abs(wy), abs(wz)) >= self._gyro_clip
            self._t_ns = max(self._t_ns, t_ns)
            self._rest_phase(self._gyro)

    def _lost_variance(self, dt: float) -> float:
        """(m/s)^2 per axis the velocity's error grows by over ``dt`` s since the last
        base-rod reading, beyond the IMU's noise: 0 unless readings were lost
        (:attr:`InekfConfig.imu_gap_share`; the period is the description's, so an IMU
        slower than described counts every interval, and 2 ms of jitter at 200 Hz a
        few), else the accelerometer's recent spread (the mean square of each reading
        off a low-pass that includes it) times the missing time squared, that time at
        most the health's ``max_prediction_time`` (a longer stall is the watchdog's)."""
        share = self.config.imu_gap_share
        missing = dt - self._imu_period
        if share is None or missing <= share * self._imu_period:
            return 0.0
        missing = min(missing, self.config.health.max_prediction_time)
        return self._accel_spread * missing * missing

    def _propagate(self, dt: float, lost_variance: float = 0.0) -> None:
        """Propagate over ``dt`` s with the held reading, in one compiled call
        (:meth:`RightInvariantEkf.propagate_reading`): the contacts' slip density by the
        angular rate, as the endcaps slide while the robot tips over; the velocity made
        uncertain where the reading clipped, by the full scale over the step (the
        velocity change it missed) and where readings were lost before this one
        (``lost_variance``, :meth:`_lost_variance`); the base rod's endcaps in contact rolled by its
        spin (gyro z): a sphere of radius r turning by theta about the rod moves its
        centre by theta x (r up). The rods roll about their own axes as the robot tips
        over, and an endcap held fixed made the estimate lag the robot's travel
        (Tong et al. 2024's contact model is a point foot); the other rods' spin is not
        measured."""
        f = self.filter
        assert f is not None
        nodes = f.contact_nodes
        if nodes != self._rolled_for:
            self._rolled_for = nodes
            self._roll_radii = np.array(
                [self._base_endcap_radius if n in self._base_nodes else 0.0 for n in nodes]
            ) if self.config.rolling_endcaps else np.zeros(len(nodes))  # fmt: skip
        variance = (self._full_scale * dt) ** 2 if self._clipped else 0.0
        variance += lost_variance
        turn = (self._gyro_full_scale * dt) ** 2 if self._gyro_clipped else 0.0
        f.propagate_reading(
            self._gyro, self._accel, dt, self._slip_law, variance, self._roll_radii, turn
        )
        self._spin_turn += float(self._gyro[2]) * dt
        self._spin_time += dt
        self._spin_clipped = self._spin_clipped or self._gyro_clipped

    def _rest_phase(self, gyro: NDArray[np.float64]) -> None:
        """While the robot rests after reset, the gyro's mean is its bias."""
        if not self._resting:
            return
        mean = self._rest_sum / max(self._rest_n, 1)
        if float(np.linalg.norm(gyro - mean)) > self.config.rest_gyro:
            self._resting = False
            return
        self._rest_sum += gyro
        self._rest_n += 1
        assert self.filter is not None
        self.filter.set_gyro_bias(self._rest_sum / self._rest_n)

    def _low_pass(self, rod: int, accel: NDArray[np.float64]) -> None:
        """Each rod's accelerometer ``accel`` (3,) low-passed: its tilt for the shape
        (``rod_up``)."""
        if 0 <= rod < len(self._rod_accel):
            last = self._rod_accel[rod]
            if math.isnan(last[0]):
                last[:] = accel
            else:
                last += ROD_TILT_GAIN * (accel - last)

    def _shape_due(self, t_ns: int) -> bool:
        if self._shape_ns is None:
            return True
        return t_ns - self._shape_ns >= self._shape_period_ns

    def _up(self) -> NDArray[np.float64]:
        """The up direction in the body frame, by the filter's orientation."""
        assert self.filter is not None
        return np.asarray(self.filter.rotation.T @ _UP)

    def _solve_shape(self, up: NDArray[np.float64]) -> None:
        """Reconstruct the shape; a solve that fails keeps the last shape.

        The endcaps on the ground, which gravity puts at one height, are the sensed
        ones, else those the filter holds (from the shape, with hysteresis): with one
        IMU (Tong et al. 2024's robot) no other rod's tilt pins the rotation about the base
        rod, and the three lowest of the last shape (the solver's own guess) let a wrong
        rotation confirm itself (tests/estimation/test_inekf.py: the forward gait without contact
        sensors drifted 52 % instead of 11 %)."""
        self._turn_in_flight()
        distances, weights = self.reconstructor.cable_distances(self._rest, self._cables)
        contacts = self._sensed
        if contacts is None and np.count_nonzero(self.in_contact) >= 2:
            contacts = self.in_contact
        solution = self.reconstructor.solve(
            distances, weights, up_body=up, contacts=contacts, warm=self.shape,
            rod_up=self._rod_accel,  # the solver takes each row's direction
        )  # fmt: skip
        if solution.converged:
            self.shape = solution.positions
        else:
            self._rejected["shape_not_solved"] = self._rejected.get("shape_not_solved", 0) + 1

    def _turn_in_flight(self) -> None:
        """In a hop (no endcap sensed on the ground), the last shape turned about the
        base rod by minus the rod's own turn since the last solve (``flight_spin``): the
        rod spins on its axis, the rest does not; the solver, with no gravity to fix the
        spin, holds the turn it starts from."""
        f = self.filter
        turn = self._spin_turn - (0.0 if f is None else float(f.gyro_bias[2])) * self._spin_time
        clipped = self._spin_clipped
        self._spin_turn = self._spin_time = 0.0
        self._spin_clipped = False
        sensed = self._sensed
        if not self.config.flight_spin or sensed is None or sensed.any() or clipped:
            return
        c, s = math.cos(turn), math.sin(turn)
        # each node (x, y) turned by -turn about body z
        self.shape = self.shape @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    # ------------------------------------------------------------------ contacts

    def _contacts(self) -> NDArray[np.bool_]:
        if self._sensed is not None:  # only kept where contacts are not "shape"
            return self._sensed.copy()
        return self.detector.update(self.shape, self._up())

    def _kinematics(self) -> bool:
        """Contacts updated, then every endcap in contact corrects, and those that
        touched down correct their height (:meth:`_correct_heights`); True if one did."""
        f, c = self.filter, self.config
        assert f is not None
        now = self._contacts()
        cov_touch = self._cov_touch
        # The filter's contacts are those of in_contact (both start empty and change
        # together), so only a change of the contacts adds or drops one.
        new: list[int] = []  # the contacts that touched down at this stamp
        if now.tobytes() != self.in_contact.tobytes():
            for node in [n for n in f.contact_nodes if not now[n]]:
                f.marginalise(node)
            for touched in np.flatnonzero(now & ~self.in_contact).tolist():
                if touched not in f.contact_nodes:
                    f.augment(touched, self.shape[touched], cov_touch)
                    new.append(touched)
        self.in_contact = now
        nodes = f.contact_nodes
        if not nodes:
            return False
        ok = f.correct_all(self.shape[nodes, :], self._cov_kinematics[len(nodes)], self._gate)
        accepted_each = ok.tolist()
        refused = [] if all(accepted_each) else [
            n for n, a in zip(nodes, accepted_each, strict=True) if not a
        ]  # fmt: skip
        if refused:
            self._rejected["contact_gated"] = self._rejected.get("contact_gated", 0) + len(refused)
        if c.reanchor_slipped and refused and len(refused) < len(nodes):
            # An endcap the gate refuses while others agree, off along the ground, has
            # slid from where it touched down: it is a new contact where the kinematics
            # now put it (held, it refused every correction until it lifted off). All
            # refused at once, or off vertically, is the filter's error, not slip: the
            # divergence check below sees to it.
            for node in self._slipped(refused):
                f.marginalise(node)
                f.augment(node, self.shape[node], cov_touch)
                if node not in new:  # touched down at this stamp and slid at once: one height
                    new.append(node)
        if c.floor_correction:
            self._correct_heights(new)
        accepted = len(refused) < len(nodes)
        if accepted:
            self._refused_since_ns = None
        elif self._refused_since_ns is None:
            self._refused_since_ns = self._t_ns
        return accepted

    def _correct_heights(self, nodes: list[int]) -> None:
        """The heights of the contacts ``nodes``, those that touched down at this stamp
        (or again, re-anchored after a slide), corrected toward the floor
        (``floor_correction``): once each, since the floor under a contact that stays
        is the same floor (corrected at every stamp, 100 Hz, a contact held for a
        second told the filter its height a hundred times over)."""
        f, c = self.filter, self.config
        assert f is not None and c.floor_std is not None
        if nodes:
            f.correct_heights(nodes, self.description.node_radii[nodes], c.floor_std**2)
            self.floor_corrections += len(nodes)

    def _slipped(self, refused: list[int]) -> list[int]:
        """The ``refused`` contacts whose endcap, by the kinematics, lies off its contact
        point mostly along the ground: the vertical part under SLIP_SLOPE times the
        horizontal one."""
        f = self.filter
        assert f is not None
        R, p = f.rotation, f.position
        points = dict(zip(f.contact_nodes, f.contact_positions, strict=True))
        out = []
        for node in refused:
            off = R @ self.shape[node] + p - points[node]
            if abs(off[2]) < SLIP_SLOPE * float(np.hypot(off[0], off[1])):
                out.append(node)
        return out

    # ------------------------------------------------------------------ health

    def _check_divergence(self) -> None:
        f = self.filter
        assert f is not None
        if not f.is_finite():
            reason = "not finite"
        elif math.hypot(*f.velocity.tolist()) > self.config.max_speed:
            reason = "too fast"
        elif abs(self._height_off_ground()) > self._ground_reach:
            reason = "off the ground"
        elif (
            self._refused_since_ns is not None
            and self._t_ns - self._refused_since_ns > seconds_to_ns(self.config.max_refused_time)
        ):
            # A filter that has drifted off refuses every contact, so it would coast on
            # the IMU alone from then on: it has diverged.
            reason = "contacts refused"
        else:
            return
        self.health.diverged(reason)
        self._restart()

    def _height_off_ground(self) -> float:
        """m: how far above the floor (z = 0) the endcaps in contact sit, their radii
        taken off, on average; without contacts, the lowest endcap; negative below."""
        f = self.filter
        assert f is not None
        radii = self.description.node_radii
        nodes = f.contact_nodes
        if nodes:
            return float(np.mean(f.contact_positions[:, 2] - radii[list(nodes)]))
        heights = (self.shape @ f.rotation.T)[:, 2] + f.position[2] - radii
        return float(heights.min())

    def _restart(self) -> None:
        """Start again where the estimate last was (the best guess a dead-reckoning
        estimator has), at rest, uncertain: tilted as the base rod's low-passed
        accelerometer says, heading kept (levelled from the TRIAD of its accelerometer
        took the body x axis for north: 90 degrees off, and never found again), its
        lowest endcap on the floor (a robot does not float)."""
        f = self.filter
        assert f is not None
        last = self._last_position if np.all(np.isfinite(self._last_position)) else np.zeros(3)
        up = self._rod_accel[self.config.base_rod]
        up = up if np.all(np.isfinite(up)) else self._accel
        R = f.rotation if np.all(np.isfinite(f.rotation)) else np.eye(3)
        R = levelled(R, up)
        last = last.copy()
        last[2] = initial_position(self.description, R, self.shape)[2]
        P = self._initial_covariance(R) * 100.0
        bias = f.gyro_bias if np.all(np.isfinite(f.gyro_bias)) else np.zeros(3)
        f.reset(R, np.zeros(3), last, bias, np.zeros(3), P)
        self.detector.reset()
        self.in_contact[:] = False
        self._refused_since_ns = None
        self._kinematics()
        self.health.reinitialised(placed=False)

    # ------------------------------------------------------------------ output

    def _estimate(self, duration_ns: int, *, corrected: bool) -> Estimate:
        f, d = self.filter, self.description
        assert f is not None
        R, p = f.rotation, f.position
        nodes = self.shape @ R.T + p
        omega = self._gyro - f.gyro_bias
        wx, wy, wz = omega.tolist()  # omega x node, written out (np.cross is 5x slower)
        cross = np.array([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]])
        velocities = f.velocity + (self.shape @ cross.T) @ R.T
        self._last_position = p.copy()
        self.health.predicted(duration_ns, corrected=corrected)
        estimate = Estimate(
            t=ns_to_seconds(self._t_ns),
            node_positions=nodes,
            node_velocities=velocities,
            com=center_of_mass(nodes, d.node_masses),
            rest_lengths=self._rest.copy(),
            pose_covariance=f.pose_covariance,
        )
        return self.health.fill(estimate)
