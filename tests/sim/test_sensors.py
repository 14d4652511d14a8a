"""The simulated sensor suite: rates, time stamps, noise statistics, dropouts, slack
cables, AHRS, contact flags, encoders, determinism and the RGB-D camera, measured on
the three-bar prism resting on the ground."""

from __future__ import annotations

import dataclasses
import math
from collections import Counter
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

from tensegrity_gym.model.description import load_robot
from tensegrity_gym.model.samples import (
    AhrsSample,
    CableLengthSample,
    ContactSample,
    EncoderSample,
    ImuSample,
    RgbdFrame,
    UwbRangeSample,
)
from tensegrity_gym.sim.backend import SimBackend
from tensegrity_gym.sim.sensors import ANCHOR_PLACEMENT_STD, SPEED_OF_LIGHT

if TYPE_CHECKING:
    from collections.abc import Iterator, Sequence

    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import SensorCalibration
    from tensegrity_gym.model.samples import GroundTruth, Sample

SEED = 20240601
N_REST_STEPS = 50  # 5 s of control at 10 Hz


@dataclasses.dataclass(frozen=True)
class RestRun:
    """Everything the sensors gave while the robot rested, step by step."""

    backend: SimBackend
    reset_samples: Sequence[Sample]
    steps: list[Sequence[Sample]]
    periods: list[tuple[float, float]]
    truth_start: GroundTruth
    truth_end: GroundTruth
    calibration: SensorCalibration

    @property
    def samples(self) -> list[Sample]:
        return [s for step in self.steps for s in step]

    @property
    def duration(self) -> float:
        return self.periods[-1][1] - self.periods[0][0]


def _rest_targets(d: RobotDescription) -> NDArray[np.float64]:
    return np.array(d.rest_lengths[d.actuated])


def _of(samples: Sequence[Sample], kind: type) -> list[Any]:
    return [s for s in samples if isinstance(s, kind)]


def _arrays(sample: Sample) -> list[NDArray[Any]]:
    return [
        getattr(sample, name)
        for name in sample.__slots__  # type: ignore[union-attr]
        if isinstance(getattr(sample, name), np.ndarray)
    ]


def _quat_angle(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    """Angle (rad) of the rotation between two unit quaternions; q and -q are equal."""
    dot = abs(float(np.dot(a, b))) / (np.linalg.norm(a) * np.linalg.norm(b))
    return 2.0 * math.acos(min(1.0, dot))


def _run(backend: SimBackend, seed: int, n_steps: int, targets: NDArray[np.float64]) -> RestRun:
    reset = backend.reset(np.random.default_rng(seed))
    truth_start = backend.ground_truth()
    assert truth_start is not None
    steps, periods = [], []
    for _ in range(n_steps):
        t0 = backend.world.time
        result = backend.step(targets)
        assert not result.diverged
        steps.append(result.samples)
        periods.append((t0, backend.world.time))
    truth_end = backend.ground_truth()
    assert truth_end is not None
    return RestRun(
        backend,
        reset.samples,
        steps,
        periods,
        truth_start,
        truth_end,
        backend.calibration,
    )


@pytest.fixture(scope="module")
def d() -> RobotDescription:
    return load_robot("three_bar")


@pytest.fixture(scope="module")
def rest(d: RobotDescription) -> Iterator[RestRun]:
    backend = SimBackend(d)
    try:
        yield _run(backend, SEED, N_REST_STEPS, _rest_targets(d))
    finally:
        backend.close()


@pytest.fixture
def fresh(d: RobotDescription) -> Iterator[SimBackend]:
    backend = SimBackend(d)
    try:
        yield backend
    finally:
        backend.close()


# -------------------------------------------------------------------- the resting robot


def test_resting_robot_stays_put(rest: RestRun) -> None:
    # The statistics below compare readings with the truth at the end of the run, which
    # only works if the robot is still: the settled pose must be at rest.
    moved = np.linalg.norm(rest.truth_end.node_positions - rest.truth_start.node_positions, axis=1)
    assert moved.max() < 1e-4
    assert np.abs(rest.truth_end.node_velocities).max() < 1e-3
    assert rest.truth_end.node_positions[:, 2].min() > 0.0


# ------------------------------------------------------------------------------- rates


def test_reset_gives_one_sample_of_each_sensor_at_time_zero(
    rest: RestRun, d: RobotDescription
) -> None:
    kinds = Counter(type(s) for s in rest.reset_samples)
    assert kinds == {
        ImuSample: d.n_rods,
        AhrsSample: d.n_rods,
        EncoderSample: 1,
        CableLengthSample: 1,
        ContactSample: 1,
        UwbRangeSample: 1,
    }
    assert all(s.t == 0.0 for s in rest.reset_samples)
    assert sorted(s.rod for s in _of(rest.reset_samples, ImuSample)) == list(range(d.n_rods))


def test_sample_rates_match_configuration(rest: RestRun, d: RobotDescription) -> None:
    s = d.sensors
    T = rest.duration
    assert T == pytest.approx(N_REST_STEPS * rest.backend.control_period)
    samples = rest.samples
    expected_per_rod = {ImuSample: s.imu.rate, AhrsSample: s.imu.rate}
    for kind, rate in expected_per_rod.items():
        for rod in range(d.n_rods):
            n = sum(1 for x in _of(samples, kind) if x.rod == rod)
            assert abs(n / T - rate) <= 1.0 / T, (kind.__name__, rod, n / T, rate)
    expected = {
        EncoderSample: s.encoder.rate,
        ContactSample: s.contact.rate,
        CableLengthSample: s.cable_length.rate,
        UwbRangeSample: s.uwb.rate,
    }
    for kind, rate in expected.items():
        n = len(_of(samples, kind))
        assert abs(n / T - rate) <= 1.0 / T, (kind.__name__, n / T, rate)
    assert not _of(samples, RgbdFrame)  # the camera is off unless asked for


def test_sample_streams_are_evenly_spaced(rest: RestRun, d: RobotDescription) -> None:
    s = d.sensors
    dt = rest.backend.time_step
    streams: dict[str, tuple[list[float], float]] = {
        "encoder": ([x.t for x in _of(rest.samples, EncoderSample)], s.encoder.rate),
        "contact": ([x.t for x in _of(rest.samples, ContactSample)], s.contact.rate),
        "cable": ([x.t for x in _of(rest.samples, CableLengthSample)], s.cable_length.rate),
        "uwb": ([x.t for x in _of(rest.samples, UwbRangeSample)], s.uwb.rate),
    }
    for rod in range(d.n_rods):
        streams[f"imu{rod}"] = (
            [x.t for x in _of(rest.samples, ImuSample) if x.rod == rod],
            s.imu.rate,
        )
    for name, (times, rate) in streams.items():
        gaps = np.diff(np.concatenate([[0.0], times]))
        # Sample times land on physics steps: within one step of the nominal period.
        assert np.all(np.abs(gaps - 1.0 / rate) <= dt + 1e-9), name
        assert times[-1] <= rest.periods[-1][1] + 1e-9


# ------------------------------------------------------------------------- time stamps


def test_samples_are_time_ordered_within_each_step(rest: RestRun) -> None:
    for step, (t0, t1) in zip(rest.steps, rest.periods, strict=True):
        times = np.array([s.t for s in step])
        assert len(times) > 0
        assert np.all(np.diff(times) >= 0.0)
        assert np.all(times > t0)
        assert np.all(times <= t1 + 1e-9)


def test_uwb_measurement_times_lie_within_their_round(rest: RestRun, d: RobotDescription) -> None:
    cfg = d.sensors.uwb
    n_modules = d.n_nodes + len(cfg.anchors)
    round_length = 3 * n_modules * cfg.packet_spacing  # poll, response, final per module
    assert round_length < 1.0 / cfg.rate
    for s in _of(rest.samples, UwbRangeSample):
        assert s.times.shape == (len(s.ranges),)
        assert s.pairs.shape == (len(s.ranges), 2)
        # The sample closes its round: no measurement is stamped after it (none from
        # the future of the step that delivers it), none before the round began.
        assert np.all(s.times <= s.t + 1e-12)
        assert np.all(s.times > s.t - round_length)
        assert np.all(np.diff(s.times) >= 0.0)


# -------------------------------------------------------------------- noise statistics


def test_imu_noise_matches_configuration(rest: RestRun, d: RobotDescription) -> None:
    cfg = d.sensors.imu
    imu = _of(rest.samples, ImuSample)
    q = rest.truth_end.rod_quaternions
    for rod in range(d.n_rods):
        accel = np.array([s.accel for s in imu if s.rod == rod])
        gyro = np.array([s.gyro for s in imu if s.rod == rod])
        assert len(accel) >= 100
        np.testing.assert_allclose(accel.std(axis=0), cfg.accel_noise, rtol=0.2)
        np.testing.assert_allclose(gyro.std(axis=0), cfg.gyro_noise, rtol=0.2)
        # Means: +g along the world's up axis, in the body frame, plus a small bias.
        x, y, z, w = q[rod]
        up_in_body = np.array(
            [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)]
        )
        mean_tol = 5.0 * cfg.accel_bias + 5.0 * cfg.accel_noise / np.sqrt(len(accel))
        np.testing.assert_allclose(accel.mean(axis=0), d.gravity * up_in_body, atol=mean_tol)
        gyro_tol = 5.0 * cfg.gyro_bias + 5.0 * cfg.gyro_noise / np.sqrt(len(gyro))
        np.testing.assert_allclose(gyro.mean(axis=0), 0.0, atol=gyro_tol)
        mag = np.array([s.mag for s in imu if s.rod == rod])
        np.testing.assert_allclose(mag.std(axis=0), cfg.mag_noise, rtol=0.2)
        field_norm = float(np.linalg.norm(cfg.magnetic_field))
        assert np.linalg.norm(mag.mean(axis=0)) == pytest.approx(field_norm, abs=0.01)


def test_cable_length_noise_matches_configuration(rest: RestRun, d: RobotDescription) -> None:
    cfg = d.sensors.cable_length
    pairs = d.cable_nodes
    x = rest.truth_end.node_positions
    true = np.linalg.norm(x[pairs[:, 1]] - x[pairs[:, 0]], axis=1)
    taut = true > rest.truth_end.rest_lengths
    assert taut.all()  # a prestressed robot at rest has no slack cable
    readings = np.array([s.lengths for s in _of(rest.samples, CableLengthSample)])
    assert readings.shape[1] == d.n_cables
    err = (readings - true)[:, taut].ravel()
    assert err.size >= 300
    assert err.std() == pytest.approx(cfg.noise, rel=0.15)
    assert abs(err.mean()) < 4.0 * cfg.noise / np.sqrt(err.size)
    # Noise is independent per cable: no cable is systematically off.
    per_cable = (readings - true).mean(axis=0)
    assert np.all(np.abs(per_cable) < 5.0 * cfg.noise / np.sqrt(len(readings)))


def _uwb_errors(run: RestRun) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """Ranges minus true module distance minus the calibrated offset, and their pairs."""
    pos = run.backend.uwb.module_positions(run.truth_end.node_positions)
    errors, pairs = [], []
    for s in _of(run.samples, UwbRangeSample):
        i, j = s.pairs[:, 0], s.pairs[:, 1]
        true = np.linalg.norm(pos[j] - pos[i], axis=1)
        errors.append(s.ranges - true - run.calibration.uwb_offsets[i, j])
        pairs.append(s.pairs)
    return np.concatenate(errors), np.concatenate(pairs)


def test_uwb_range_noise_matches_configuration(rest: RestRun, d: RobotDescription) -> None:
    cfg = d.sensors.uwb
    err, pairs = _uwb_errors(rest)
    assert err.size > 1000
    assert abs(err.mean()) < 0.01
    # SDS-TWR (Caluwaerts et al. 2016 eq. 6) takes half the difference of two time differences:
    # four stamps with weight 1/2 give c * sigma; the ratio b/a adds the other two.
    sigma = SPEED_OF_LIGHT * cfg.timestamp_noise
    assert err.std() == pytest.approx(sigma, rel=0.2)
    # The exact spread per pair: with r = d/a = (N + i - j) / 2N the stamps enter with
    # weights (1 - r, 1, 1 - r, 1, r, r) / 2.
    n_modules = rest.backend.uwb.n_modules
    r = (n_modules + pairs[:, 0] - pairs[:, 1]) / (2.0 * n_modules)
    predicted = 0.5 * sigma * np.sqrt(2.0 * (1.0 - r) ** 2 + 2.0 + 2.0 * r**2)
    z = err / predicted
    assert z.std() == pytest.approx(1.0, rel=0.05)
    assert abs(z.mean()) < 5.0 / np.sqrt(z.size)


def test_uwb_offsets_are_symmetric_and_as_configured(rest: RestRun, d: RobotDescription) -> None:
    cfg = d.sensors.uwb
    o = rest.calibration.uwb_offsets
    n_modules = d.n_nodes + len(cfg.anchors)
    assert o.shape == (n_modules, n_modules)
    np.testing.assert_array_equal(o, o.T)
    off_diagonal = o[np.triu_indices(n_modules, 1)]
    mean_tol = 4.0 * cfg.offset_std / np.sqrt(off_diagonal.size)
    assert off_diagonal.mean() == pytest.approx(cfg.offset_mean, abs=mean_tol)
    assert off_diagonal.std() == pytest.approx(cfg.offset_std, rel=0.25)
    # The lab's anchors stand near the description's layout (drawn once per world).
    assert np.abs(rest.calibration.anchors - d.anchors).max() < 5 * ANCHOR_PLACEMENT_STD


def test_uwb_pairs(rest: RestRun, d: RobotDescription) -> None:
    uwb = rest.backend.uwb
    n, n_anchors = d.n_nodes, len(d.sensors.uwb.anchors)
    # Robot modules range each other both ways; each anchor ranges each robot module once.
    assert len(uwb.pairs) == n * (n - 1) + n_anchors * n
    assert len({tuple(p) for p in uwb.pairs.tolist()}) == len(uwb.pairs)
    assert np.all(uwb.pairs[:, 0] != uwb.pairs[:, 1])
    assert np.all(uwb.pairs[:, 1] < n)  # the responder always computes: a robot module
    full = {tuple(p) for p in uwb.pairs.tolist()}
    for s in _of(rest.samples, UwbRangeSample):
        assert {tuple(p) for p in s.pairs.tolist()} <= full


# --------------------------------------------------------------------------- dropouts


def _rejected_share(samples: Sequence[Sample], n_pairs: int) -> tuple[float, int]:
    rounds = _of(samples, UwbRangeSample)
    total = len(rounds) * n_pairs
    kept = sum(len(s.ranges) for s in rounds)
    return 1.0 - kept / total, total


def test_uwb_rejected_share_lies_in_configured_range(rest: RestRun, d: RobotDescription) -> None:
    lo, hi = d.sensors.uwb.reject_fraction
    n_pairs = len(rest.backend.uwb.pairs)
    share, total = _rejected_share(rest.samples, n_pairs)
    slack = 4.0 * np.sqrt(0.25 / total)
    assert lo - slack <= share <= hi + slack
    assert share == pytest.approx(rest.backend.uwb.reject_fraction, abs=slack)


def test_uwb_rejected_share_is_drawn_per_episode(fresh: SimBackend, d: RobotDescription) -> None:
    lo, hi = d.sensors.uwb.reject_fraction
    n_pairs = len(fresh.uwb.pairs)
    targets = _rest_targets(d)
    shares = []
    for seed in range(6):
        fresh.reset(np.random.default_rng(seed))
        drawn = fresh.uwb.reject_fraction
        assert lo <= drawn <= hi
        samples = [s for _ in range(10) for s in fresh.step(targets).samples]
        share, total = _rejected_share(samples, n_pairs)
        slack = 4.0 * np.sqrt(0.25 / total)
        assert share == pytest.approx(drawn, abs=slack)
        assert lo - slack <= share <= hi + slack
        shares.append(share)
    assert max(shares) - min(shares) > 0.05


def _with_reject_fraction(d: RobotDescription, share: float) -> RobotDescription:
    uwb = dataclasses.replace(d.sensors.uwb, reject_fraction=(share, share))
    return dataclasses.replace(d, sensors=dataclasses.replace(d.sensors, uwb=uwb))


@pytest.mark.parametrize("share", [0.5, 0.0])
def test_uwb_fixed_reject_fraction(d: RobotDescription, share: float) -> None:
    backend = SimBackend(_with_reject_fraction(d, share))
    try:
        run = _run(backend, SEED + 1, 30, _rest_targets(d))
    finally:
        backend.close()
    n_pairs = len(backend.uwb.pairs)
    rounds = _of(run.samples, UwbRangeSample)
    assert len(rounds) >= 40
    kept = sum(len(s.ranges) for s in rounds) / (len(rounds) * n_pairs)
    assert kept == pytest.approx(1.0 - share, abs=0.05)
    if share == 0.0:
        assert all(len(s.ranges) == n_pairs for s in rounds)
    else:
        # Dropouts are per packet, not per round: every round keeps some.
        counts = np.array([len(s.ranges) for s in rounds])
        assert counts.min() > 0
        assert counts.max() < n_pairs


# ------------------------------------------------------------------------ slack cables


def test_slack_cable_reads_rest_length_plus_bias(fresh: SimBackend, d: RobotDescription) -> None:
    cfg = d.sensors.cable_length
    fresh.reset(np.random.default_rng(SEED))
    k = next(i for i, c in enumerate(d.cables) if not c.actuated)
    truth = fresh.ground_truth()
    assert truth is not None
    i, j = d.cable_nodes[k]
    length = float(np.linalg.norm(truth.node_positions[j] - truth.node_positions[i]))
    # Longer than any two endcaps of the prism can be apart: slack whatever the robot does.
    rest_length = length + 1.0
    fresh.world.rest_lengths[k] = rest_length
    readings = []
    for _ in range(3):
        result = fresh.step(_rest_targets(d))
        assert not result.diverged
        readings += [s.lengths[k] for s in _of(result.samples, CableLengthSample)]
        truth = fresh.ground_truth()
        assert truth is not None
        assert truth.rest_lengths[k] == rest_length
        true_now = float(np.linalg.norm(truth.node_positions[j] - truth.node_positions[i]))
        assert true_now < rest_length  # still slack
    readings_arr = np.array(readings)
    assert len(readings_arr) >= 3
    expected = rest_length + cfg.slack_bias
    assert np.all(np.abs(readings_arr - expected) < 5.0 * cfg.noise)
    assert abs(readings_arr.mean() - expected) < 4.0 * cfg.noise / np.sqrt(len(readings_arr))
    # Wrong: far from the true endcap distance.
    assert np.all(readings_arr - true_now > 0.5)


# ----------------------------------------------------------------------------- AHRS


def test_ahrs_orientation_agrees_with_truth_at_rest(rest: RestRun, d: RobotDescription) -> None:
    ahrs = _of(rest.reset_samples, AhrsSample) + _of(rest.samples, AhrsSample)
    assert len(ahrs) > d.n_rods
    q_true = rest.truth_end.rod_quaternions
    worst = 0.0
    for s in ahrs:
        assert s.quaternion.shape == (4,)
        assert np.linalg.norm(s.quaternion) == pytest.approx(1.0, abs=1e-5)
        worst = max(worst, _quat_angle(s.quaternion, q_true[s.rod]))
    assert np.degrees(worst) < 3.0


def test_ahrs_follows_the_reset_heading(d: RobotDescription, fresh: SimBackend) -> None:
    # Different seeds give different headings; the AHRS tracks each one.
    for seed in (1, 2):
        result = fresh.reset(np.random.default_rng(seed))
        truth = fresh.ground_truth()
        assert truth is not None
        for s in _of(result.samples, AhrsSample):
            assert np.degrees(_quat_angle(s.quaternion, truth.rod_quaternions[s.rod])) < 3.0


# -------------------------------------------------------------------------- contacts


def test_contact_flags_mark_the_bottom_endcaps(rest: RestRun, d: RobotDescription) -> None:
    z = rest.truth_end.node_positions[:, 2]
    bottom = np.zeros(d.n_nodes, dtype=bool)
    bottom[np.argsort(z)[:3]] = True
    # The prism rests on one endcap of each rod.
    assert sorted(d.node_rod[bottom].tolist()) == list(range(d.n_rods))
    contacts = _of(rest.samples, ContactSample)
    assert contacts
    for s in contacts:
        assert s.in_contact.dtype == np.bool_
        np.testing.assert_array_equal(s.in_contact, bottom)


# -------------------------------------------------------------------------- encoders


def test_encoders_read_commanded_rest_lengths_at_rest(rest: RestRun, d: RobotDescription) -> None:
    res = d.sensors.encoder.resolution
    targets = _rest_targets(d)
    encoders = _of(rest.reset_samples, EncoderSample) + _of(rest.samples, EncoderSample)
    for s in encoders:
        assert s.rest_lengths.shape == (d.n_actuated,)
        assert np.all(np.abs(s.rest_lengths - targets) <= 0.5 * res + 1e-12)
        steps = s.rest_lengths / res
        np.testing.assert_allclose(steps, np.round(steps), atol=1e-6)


def test_encoders_slew_toward_a_shorter_target(fresh: SimBackend, d: RobotDescription) -> None:
    res = d.sensors.encoder.resolution
    _, _, max_speed = d.motor_limits
    start = _rest_targets(d)
    target = start - 0.04
    result = fresh.reset(np.random.default_rng(SEED))
    history = [(s.t, s.rest_lengths) for s in _of(result.samples, EncoderSample)]
    period = fresh.control_period
    n_steps = math.ceil(0.04 / (max_speed.min() * period)) + 2
    for _ in range(n_steps):
        result = fresh.step(target)
        assert not result.diverged
        history += [(s.t, s.rest_lengths) for s in _of(result.samples, EncoderSample)]
    t = np.array([h[0] for h in history])
    x = np.array([h[1] for h in history])
    # Toward the target, never past it, never faster than the motors go.
    assert np.all(np.diff(x, axis=0) <= res + 1e-12)
    assert np.all(x >= target - 0.5 * res - 1e-12)
    speed = np.abs(np.diff(x, axis=0)) / np.diff(t)[:, None]
    assert np.all(speed <= max_speed + 2.0 * res / np.diff(t).min())
    # And there in the end: within one resolution step.
    assert np.all(np.abs(x[-1] - target) <= 0.5 * res + 1e-12)
    # The first period is spent moving at full speed.
    first = x[t <= period + 1e-9][-1]
    np.testing.assert_allclose(start - first, max_speed * period, atol=2.0 * res)


def test_encoders_stop_at_the_motor_limit(fresh: SimBackend, d: RobotDescription) -> None:
    res = d.sensors.encoder.resolution
    _, hi, max_speed = d.motor_limits
    fresh.reset(np.random.default_rng(SEED))
    target = np.array(_rest_targets(d))
    target[0] = hi[0] + 0.5  # beyond the motor's range: clipped
    n_steps = math.ceil((hi[0] - d.rest_lengths[d.actuated[0]]) / (max_speed[0] * 0.1)) + 2
    for _ in range(n_steps):
        result = fresh.step(target)
        assert not result.diverged
    last = _of(result.samples, EncoderSample)[-1].rest_lengths
    assert last[0] == pytest.approx(hi[0], abs=0.5 * res + 1e-12)
    np.testing.assert_allclose(last[1:], target[1:], atol=0.5 * res + 1e-12)


# ------------------------------------------------------------------------ determinism


def _assert_same_samples(a: Sequence[Sample], b: Sequence[Sample]) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert type(x) is type(y)
        for name in x.__slots__:  # type: ignore[union-attr]
            u, v = getattr(x, name), getattr(y, name)
            if isinstance(u, np.ndarray):
                assert u.dtype == v.dtype
                assert np.array_equal(u, v), name
            else:
                assert u == v, name


def _record(backend: SimBackend, seed: int, n_steps: int) -> list[Sample]:
    d = backend.description
    out = list(backend.reset(np.random.default_rng(seed)).samples)
    for _ in range(n_steps):
        out += backend.step(_rest_targets(d) - 0.02).samples
    return out


def test_same_seed_gives_identical_samples(d: RobotDescription) -> None:
    a, b = SimBackend(d), SimBackend(d)
    try:
        first = _record(a, 5, 4)
        second = _record(b, 5, 4)
        _assert_same_samples(first, second)
        # The same backend reset with the same seed replays the episode too.
        _assert_same_samples(_record(a, 5, 4), first)
        other = _record(b, 6, 4)
    finally:
        a.close()
        b.close()
    assert len(first) > 0
    differs = len(other) != len(first) or any(
        type(x) is not type(y)
        or any(
            not np.array_equal(u, v)
            for u, v in zip(_arrays(x), _arrays(y), strict=True)
            if u.shape == v.shape
        )
        for x, y in zip(first, other, strict=False)
    )
    assert differs
    imu_a = np.array([s.accel for s in _of(first, ImuSample)])
    imu_b = np.array([s.accel for s in _of(other, ImuSample)])
    assert not np.array_equal(imu_a, imu_b)


# ----------------------------------------------------------------------------- camera


def test_camera_frames(d: RobotDescription) -> None:
    cam = d.sensors.camera
    backend = SimBackend(d, camera=True)
    try:
        result = backend.reset(np.random.default_rng(SEED))
        frames = _of(result.samples, RgbdFrame)
        steps = []
        for _ in range(3):
            step = backend.step(_rest_targets(d)).samples
            steps.append((step, backend.world.time))
            frames += _of(step, RgbdFrame)
        truth = backend.ground_truth()
        calibration = backend.calibration
    finally:
        backend.close()
    assert truth is not None
    for step, t_end in steps:
        in_step = _of(step, RgbdFrame)
        assert len(in_step) == 1
        assert in_step[0].t == pytest.approx(t_end)
        times = [s.t for s in step]
        assert times == sorted(times)
    for frame in frames:
        assert frame.rgb.shape == (cam.height, cam.width, 3)
        assert frame.rgb.dtype == np.uint8
        assert frame.depth.shape == (cam.height, cam.width)
        assert frame.depth.dtype == np.float32
        assert np.all(np.isfinite(frame.depth))
        assert np.all(frame.depth >= 0.0)
        assert np.all(frame.depth <= cam.far)
        assert (frame.depth > 0.0).mean() > 0.9  # the floor fills the view

    frame = frames[-1]
    rgb = frame.rgb.astype(np.float64)
    norm = np.linalg.norm(rgb, axis=-1)
    for rod in d.rods:
        colour = np.array(rod.color[:3])
        cosine = rgb @ colour / (np.linalg.norm(colour) * np.maximum(norm, 1e-9))
        assert np.count_nonzero((cosine > 0.97) & (norm > 40.0)) >= 5, rod.name

    # Each endcap projects, with the calibrated intrinsics and pose, onto a pixel of its
    # rod's colour, at about its depth (the near side of the sphere).
    K, pose = calibration.camera_intrinsics, calibration.camera_pose
    cam_xyz = (truth.node_positions - pose[:3, 3]) @ pose[:3, :3]
    uv = cam_xyz @ K.T
    hits = 0
    for node in range(d.n_nodes):
        u, v = uv[node, :2] / uv[node, 2]
        row, col = int(v), int(u)
        assert 0 <= row < cam.height
        assert 0 <= col < cam.width
        rod = d.rods[d.node_rod[node]]
        colour = np.array(rod.color[:3])
        patch = rgb[max(row - 1, 0) : row + 2, max(col - 1, 0) : col + 2].reshape(-1, 3)
        cosine = patch @ colour / (np.linalg.norm(colour) * np.linalg.norm(patch, axis=1))
        depth = frame.depth[max(row - 1, 0) : row + 2, max(col - 1, 0) : col + 2].ravel()
        near = np.abs(depth - cam_xyz[node, 2]) < rod.endcap_radius + 0.03
        hits += bool(np.any((cosine > 0.97) & near))
    assert hits >= d.n_nodes - 1  # one endcap may hide behind another rod


def test_camera_floor_composite_equals_one_render(d: RobotDescription) -> None:
    # The floor is rendered once per camera pose in a client of its own and the robot
    # z-composited over it; that must give the pixels of one render of both, also
    # where endcaps touch the floor and where the robot hides part of it.
    import pybullet

    from tensegrity_gym.sim import world as world_module

    cam = d.sensors.camera
    backend = SimBackend(d, camera=True)
    try:
        backend.reset(np.random.default_rng(SEED))
        world = backend.world
        rng = np.random.default_rng(1)
        lo, hi, _ = d.motor_limits
        images, states = [], []
        for _ in range(12):
            backend.step(rng.uniform(lo, hi))
            images.append(world.camera_image(cam))
            states.append(world.save_state())
        assert len(world._floor_images) == 1  # a fixed camera renders its floor once
        # Make the floor visible in the robot's own client and render in one pass.
        pybullet.changeVisualShape(
            world.ground, -1, rgbaColor=[0.55, 0.55, 0.5, 1.0], physicsClientId=world.client
        )
        view = pybullet.computeViewMatrix(cam.position, cam.target, cam.up)
        proj = pybullet.computeProjectionMatrixFOV(
            cam.vertical_fov, cam.width / cam.height, cam.near, cam.far
        )
        for (rgb, depth), state in zip(images, states, strict=True):
            world.restore_state(state)
            one_rgb, zb = world_module._render(world.client, cam.width, cam.height, view, proj)
            one_depth = (cam.far * cam.near / (cam.far - (cam.far - cam.near) * zb)).astype(
                np.float32
            )
            np.testing.assert_array_equal(rgb, one_rgb)
            np.testing.assert_array_equal(depth, one_depth)
            floor = world._floor_images[next(iter(world._floor_images))][0]
            assert (rgb != floor).any(axis=-1).sum() > 100  # the robot is in the picture
    finally:
        backend.close()


# ------------------------------------------------------------------------- finiteness


def test_all_samples_are_finite(rest: RestRun) -> None:
    samples = list(rest.reset_samples) + rest.samples
    assert samples
    for s in samples:
        for array in _arrays(s):
            if array.dtype.kind == "f":
                assert np.all(np.isfinite(array)), type(s).__name__
        assert math.isfinite(s.t)


def test_float_arrays_are_float64(rest: RestRun) -> None:
    # Sample types promise float64 arrays (the camera's depth image is float32).
    for s in list(rest.reset_samples) + rest.samples:
        for array in _arrays(s):
            if array.dtype.kind == "f":
                assert array.dtype == np.float64, type(s).__name__


def _edge_scene(far_plane: float) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
    """A 40 x 40 frame: a square 1 m away on a floor 2 m away, and a strip of sky (no
    return, at the far plane) along the top, touching the square."""
    depth = np.full((40, 40), 2.0, dtype=np.float32)
    depth[10:30, 10:30] = 1.0
    depth[:5, :] = far_plane
    depth[5:10, 15:25] = 1.0  # the square reaches up to the sky
    rgb = np.zeros((40, 40, 3), dtype=np.uint8)
    rgb[depth == 1.0] = (255, 0, 0)
    return rgb, depth


def test_flying_pixels_read_between_the_two_surfaces_of_a_depth_edge(d: RobotDescription) -> None:
    from tensegrity_gym.sim.sensors import CameraModel

    quiet = dataclasses.replace(d.sensors.camera, depth_noise=0.0, depth_noise_quadratic=0.0)
    rgb, depth = _edge_scene(quiet.far)
    near = depth == 1.0
    pad = np.pad(depth, 1, constant_values=1.0)
    beside_floor = near & (
        (pad[:-2, 1:-1] == 2.0) | (pad[2:, 1:-1] == 2.0)
        | (pad[1:-1, :-2] == 2.0) | (pad[1:-1, 2:] == 2.0)
    )  # fmt: skip

    def frame(share: float, noise: bool = False, seed: int = 0) -> NDArray[np.float32]:
        config = dataclasses.replace(d.sensors.camera if noise else quiet, flying_pixels=share)
        model = CameraModel(config)
        return model.frame(0.0, rgb, depth.copy(), np.random.default_rng(seed)).depth

    clean = frame(0.0)
    sky = depth >= quiet.far
    assert np.array_equal(clean[~sky], depth[~sky]) and np.all(clean[sky] == 0.0)
    every = frame(1.0)
    moved = every != clean
    assert np.array_equal(moved, beside_floor)  # the edge toward the floor, not the sky's
    assert np.all((every[moved] > 1.0) & (every[moved] < 2.0))  # between the two surfaces
    assert np.array_equal(every[sky], clean[sky])  # no return stays none
    half = frame(0.5) != clean
    assert 0.3 < half.sum() / beside_floor.sum() < 0.7
    # The noise is drawn first: off the edges the frames agree bit for bit, and the
    # same seed gives the same frame.
    noisy0, noisy1 = frame(0.0, noise=True), frame(1.0, noise=True)
    assert np.array_equal(noisy0[~beside_floor], noisy1[~beside_floor])
    assert np.array_equal(noisy1, frame(1.0, noise=True))
