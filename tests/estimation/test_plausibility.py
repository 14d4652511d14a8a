"""Physical plausibility of raw measurements (estimation/plausibility.py) and the screen
that drops the implausible ones and fails streams (estimation/screen.py); at the end, a
replayed bag whose ranges turn to millimetres, through the env and its UKF."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
import pytest

import tensegrity_gym  # noqa: F401  (registers the envs)
from estimation.mismatch import RateMismatch
from estimation.plausibility import PlausibilityBounds
from estimation.screen import PlausibilityScreen, StreamMonitor
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.model.samples import (
    AhrsSample,
    CableLengthSample,
    EncoderSample,
    ImuSample,
    UwbRangeSample,
)
from tensegrity_gym.sim.backend import SimBackend
from tests.hardware.test_bag_robustness import _edit_every, _rewrite

if TYPE_CHECKING:
    from pathlib import Path

    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import SensorCalibration
    from tensegrity_gym.model.samples import Sample

THREE_BAR = "tensegrity_gym/ThreeBarRoll-v0"


def _three_bar() -> tuple[RobotDescription, SensorCalibration]:
    d = load_robot("three_bar")
    backend = SimBackend(d)
    backend.reset(np.random.default_rng(0))
    calibration = backend.calibration
    backend.close()
    return d, calibration


@pytest.fixture(scope="module")
def robot() -> tuple[RobotDescription, SensorCalibration, PlausibilityBounds]:
    d, calibration = _three_bar()
    return d, calibration, PlausibilityBounds.from_robot(d, calibration)


def test_bounds_of_the_three_bar_robot(robot: Any) -> None:
    """Rods laid end to end 0.975 m; anchors about 4.24 m apart at most (the layout's,
    each anchor within a few cm of it); UWB noise margin 8 c sigma_t + 0.1 m = 0.34 m;
    cable noise margin 8 x 4 mm."""
    d, calibration, b = robot
    assert b.range_tolerance == pytest.approx(8 * 299_792_458.0 * 1e-10 + 0.1)
    assert b.node_range_max == pytest.approx(0.975 + b.range_tolerance)
    a = calibration.anchors
    extent = np.linalg.norm(a[:, None] - a[None], axis=-1).max()
    assert extent == pytest.approx(np.hypot(3.0, 3.0), abs=0.3)  # the corner anchors
    assert b.anchor_range_max == pytest.approx(2 * extent + 0.975 + b.range_tolerance)
    assert b.cable_length_max == pytest.approx(0.975 + 0.032)
    assert b.accel_full_scale == pytest.approx(16 * 9.80665 * 1.02)
    assert b.gyro_full_scale == pytest.approx(np.radians(2000) * 1.02)
    lo, hi, _ = d.motor_limits
    assert np.all(b.rest_length_min < lo) and np.all(b.rest_length_max > hi)


def test_each_check_names_the_first_reason(robot: Any) -> None:
    d, calibration, b = robot
    n = d.n_nodes
    o = calibration.uwb_offsets
    pairs = np.array([[0, 1], [0, n], [0, 99], [2, 2], [1, 2], [1, n + 1], [3, n + 2], [4, 5]])
    ranges = np.array(
        [0.3 + o[0, 1], 9.0 + o[0, n], 1.0, 1.0, np.nan, 50.0, -0.5 + o[3, n + 2], 1.4 + o[4, 5]]
    )
    v = b.uwb(pairs, ranges)
    np.testing.assert_array_equal(v.plausible, [1, 1, 0, 0, 0, 0, 0, 0])
    assert v.counts() == {
        "uwb_bad_pair": 2,
        "uwb_range_not_finite": 1,
        "uwb_range_too_long": 2,  # 50 m to an anchor; 1.4 m between two nodes
        "uwb_range_negative": 1,
    }
    fs = d.sensors.imu.accel_full_scale
    accel = np.array([[0, 0, fs], [0, 0, -1.05 * fs], [np.nan, 0, 0], [0, 0, 9.8]])
    gyro = np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 40.0, 0]])
    v = b.imu(accel, gyro)
    np.testing.assert_array_equal(v.plausible, [1, 0, 0, 0])  # saturated is plausible
    assert v.counts() == {
        "accel_over_full_scale": 1,
        "imu_not_finite": 1,
        "gyro_over_full_scale": 1,
    }
    q = np.array(
        [[0, 0, 0, 1], [0, 0, 0.0999, 0.995], [0, 0, 0, 2], [0, 0, 0, 0], [np.inf, 0, 0, 1]]
    )
    v = b.ahrs(q)
    np.testing.assert_array_equal(v.plausible, [1, 1, 0, 0, 0])
    assert v.counts() == {"ahrs_not_unit": 2, "ahrs_not_finite": 1}
    v = b.cables([0.2, np.nan, 1.5, -0.1, np.inf, 0.0])
    np.testing.assert_array_equal(v.plausible, [1, 0, 0, 0, 0, 1])
    assert v.counts() == {"cable_too_long": 2, "cable_negative": 1}  # NaN: no reading
    lo, hi, _ = d.motor_limits
    v = b.encoders(np.stack([lo, hi, 1000 * hi, np.full_like(lo, np.nan)]))
    np.testing.assert_array_equal(v.plausible, [1, 1, 0, 0])
    assert v.counts() == {"encoder_out_of_range": 1, "encoder_not_finite": 1}


def test_a_plausible_batch_at_once_and_one_bad_reading_in_it(robot: Any) -> None:
    # The common case (every reading plausible) is judged in one test; a batch with one
    # reading that is not finite or out of range still names it.
    d, _, b = robot
    rng = np.random.default_rng(0)
    accel = rng.uniform(-b.accel_full_scale, b.accel_full_scale, (40, 3))
    gyro = rng.uniform(-b.gyro_full_scale, b.gyro_full_scale, (40, 3))
    v = b.imu(accel, gyro)
    assert v.plausible.all() and v.counts() == {}
    for bad, kind in ((np.inf, "imu_not_finite"), (np.nan, "imu_not_finite"),
                      (1.01 * b.gyro_full_scale, "gyro_over_full_scale")):  # fmt: skip
        g = gyro.copy()
        g[17, 1] = bad
        v = b.imu(accel, g)
        assert np.flatnonzero(~v.plausible).tolist() == [17] and v.counts() == {kind: 1}
    lo, hi, _ = d.motor_limits
    readings = rng.uniform(lo, hi, (10, len(lo)))
    assert b.encoders(readings).plausible.all()
    for bad, kind in ((-np.inf, "encoder_not_finite"), (2 * hi[0], "encoder_out_of_range")):
        r = readings.copy()
        r[3, 0] = bad
        v = b.encoders(r)
        assert np.flatnonzero(~v.plausible).tolist() == [3] and v.counts() == {kind: 1}


@pytest.mark.parametrize("preset", ["three_bar", "three_bar_large", "superball"])
def test_nothing_simulated_is_implausible(preset: str) -> None:
    """Half a second of every simulated sensor under random commands: not one reading
    is rejected."""
    d = load_robot(preset)
    backend = SimBackend(d)
    rng = np.random.default_rng(2)
    samples = list(backend.reset(rng).samples)
    lo, hi, _ = d.motor_limits
    for _ in range(5):
        samples += backend.step(rng.uniform(lo, hi)).samples
    screen = PlausibilityScreen(d, PlausibilityBounds.from_robot(d, backend.calibration), 1.0)
    backend.close()
    kept = screen.screen(samples)
    assert screen.rejected == {} and screen.failed == ()
    assert len(kept) == len(samples) and all(a is b for a, b in zip(kept, samples, strict=True))


def test_a_stream_fails_after_a_window_of_only_implausible_samples() -> None:
    m = StreamMonitor(1.0)
    assert m.observe("a", 0.0, True)
    assert m.observe("a", 0.1, False)  # a run starts
    assert m.observe("a", 1.0, False)
    assert m.observe("a", 1.05, True)  # one plausible sample ends the run
    assert m.observe("a", 1.2, False)
    assert m.observe("a", 2.1, False)
    assert not m.observe("a", 2.2, False)  # 1 s of nothing plausible
    assert m.failed == ("a",)
    assert not m.observe("a", 2.3, True)  # on probation
    assert not m.observe("a", 2.5, False)  # ends it
    assert not m.observe("a", 2.6, True)
    assert m.observe("b", 2.6, False)  # other streams are their own
    assert not m.observe("a", 3.5, True)
    assert m.observe("a", 3.6, True)  # 1 s of only plausible samples: restored
    assert m.failed == ()


def _round(t: float, pairs: list[list[int]], ranges: list[float]) -> UwbRangeSample:
    return UwbRangeSample(t, np.full(len(ranges), t), np.array(pairs), np.array(ranges))


def test_the_screen_keeps_the_plausible_part_and_fails_a_stuck_module(robot: Any) -> None:
    """Anchor 2 reports 100 m to everything: its ranges are dropped at once, after a
    second it is failed as "uwb/anchor2" alone (the stream as a whole still ranges),
    and once it reports sense again its ranges are held back for a second."""
    d, calibration, b = robot
    n = d.n_nodes
    o = calibration.uwb_offsets
    screen = PlausibilityScreen(d, b, 1.0)
    for k in range(33):
        t = k / 15
        stuck = k < 16
        far = 100.0 if stuck else 2.0 + o[n + 2, 0]
        sample = _round(t, [[n + 2, 0], [n, 0], [1, 0]], [far, 2.0 + o[n, 0], 0.3 + o[1, 0]])
        kept = screen.screen([sample])
        assert len(kept) == 1
        got = kept[0]
        assert isinstance(got, UwbRangeSample)
        expect_failed = 15 <= k < 31  # 1 s of rounds each way
        assert screen.failed == (("uwb/anchor2",) if expect_failed else ()), k
        assert len(got.ranges) == (2 if stuck or expect_failed else 3), k
        if len(got.ranges) == 3:
            assert got is sample  # passed whole
    assert screen.rejected == {"uwb_range_too_long": 16}


def test_the_screen_fails_whole_streams_by_name(robot: Any) -> None:
    """A whole UWB stream in millimetres fails as "uwb" (not once per module); per-rod
    AHRS and IMU streams by rod name; cables; encoders."""
    d, calibration, b = robot
    n = d.n_nodes
    o = calibration.uwb_offsets
    lo, _, _ = d.motor_limits
    screen = PlausibilityScreen(d, b, 1.0)
    for k in range(12):
        t = 0.1 * k
        samples: list[Sample] = [
            _round(t, [[n, 0], [1, 0]], [1000 * (2.0 + o[n, 0]), 1000 * (0.3 + o[1, 0])]),
            AhrsSample(t, 1, np.array([0.0, 0.0, 0.0, 3.0])),
            AhrsSample(t, 2, np.array([0.0, 0.0, 0.0, 1.0])),
            ImuSample(t, 0, np.array([0.0, 0.0, 1e4]), np.zeros(3), np.zeros(3)),
            CableLengthSample(t, np.full(d.n_cables, 7.0)),
            EncoderSample(t, -lo),
        ]
        kept = screen.screen(samples)
        assert [type(s) for s in kept] == [AhrsSample]
    assert screen.failed == ("ahrs/green", "cable_lengths", "encoders", "imu/red", "uwb")
    assert screen.rejected == {
        "uwb_range_too_long": 24,
        "ahrs_not_unit": 12,
        "accel_over_full_scale": 12,
        "cable_too_long": 12 * d.n_cables,
        "encoder_out_of_range": 12,
    }


def test_cable_readings_lose_only_their_implausible_entries(robot: Any) -> None:
    d, _, b = robot
    screen = PlausibilityScreen(d, b, 1.0)
    lengths = np.full(d.n_cables, 0.2)
    lengths[[1, 4]] = [3.0, np.nan]
    (kept,) = screen.screen([CableLengthSample(0.0, lengths)])
    assert isinstance(kept, CableLengthSample)
    expected = lengths.copy()
    expected[1] = np.nan
    np.testing.assert_array_equal(kept.lengths, expected)
    assert screen.screen([CableLengthSample(0.1, np.zeros(3))]) == []
    assert screen.rejected == {"cable_too_long": 1, "cable_wrong_size": 1}


def test_malformed_samples_are_counted_not_raised(robot: Any) -> None:
    d, _, b = robot
    screen = PlausibilityScreen(d, b, 1.0)
    samples: list[Sample] = [
        UwbRangeSample(0.0, np.zeros(2), np.zeros((3, 2), dtype=np.intp), np.ones(2)),
        AhrsSample(0.0, 7, np.array([0.0, 0.0, 0.0, 1.0])),
        AhrsSample(0.0, 0, np.zeros(3)),
        ImuSample(0.0, -1, np.zeros(3), np.zeros(3), np.zeros(3)),
        EncoderSample(0.0, np.zeros(2)),
    ]
    assert screen.screen(samples) == []
    assert screen.rejected == {
        "uwb_malformed_round": 1,
        "ahrs_bad_rod": 1,
        "ahrs_not_finite": 1,
        "imu_bad_rod": 1,
        "encoder_not_finite": 1,
    }


def _millimetres_from(t0: float) -> Any:
    """An edit of a UWB round message: its ranges times 1000 from ``t0`` (s) on, counted
    from the whole second of the first round (the bag's clock origin: a recording is
    stamped from the wall clock)."""
    origin: list[int] = []

    def edit(msg: Any) -> None:
        origin[:] = origin or [msg.header.stamp.sec]
        if msg.header.stamp.sec - origin[0] + 1e-9 * msg.header.stamp.nanosec >= t0:
            for r in msg.ranges:
                r.range *= 1000.0

    return edit


def test_a_replayed_bag_whose_ranges_turn_to_millimetres(tmp_path: Path) -> None:
    """Issue 12: a bag whose UWB ranges are in millimetres from 1 s on, replayed through
    the env and its UKF. Before the screen the CoM went 2.2 km off and the estimator
    unhealthy (the task's reward check zeroed the rewards of the jumps); now the error
    stays that of the filter without UWB (measured at most 1.7 cm), the estimator
    healthy, the rewards small (at most 0.25), and info says "uwb" has failed."""
    env = gym.make(THREE_BAR, estimator="oracle", record_dir=tmp_path, max_episode_steps=25)
    env.action_space.seed(0)
    env.reset(seed=4)
    done = False
    while not done:
        *_, terminated, truncated, _ = env.step(env.action_space.sample())
        done = terminated or truncated
    env.close()
    bag = _rewrite(
        tmp_path / "episode_000",
        tmp_path / "millimetres",
        _edit_every("/uwb/ranges", _millimetres_from(1.0)),
    )
    env = gym.make(THREE_BAR, estimator="ukf", driver=f"bag:{bag}")
    _, info = env.reset(seed=4)
    zeros = np.zeros(env.action_space.shape, dtype=np.float32)
    errors, rewards = [], []
    for _ in range(25):
        _, reward, _, truncated, info = env.step(zeros)
        errors.append(info["estimation_error"])
        rewards.append(reward)
    env.close()
    assert truncated
    assert max(errors) < 0.3, np.round(errors, 3)
    assert np.all(np.isfinite(rewards)) and max(np.abs(rewards)) < 1.0
    assert info["estimator_failed_streams"] == ["uwb"]
    assert info["estimator_rejected"]["uwb_range_too_long"] > 100
    assert info["estimator_healthy"]


def test_a_sample_stamped_far_ahead_or_not_at_all_does_not_stop_the_clock() -> None:
    """One glitched stamp (a second ahead of its period or more, or NaN) is dropped and
    counted: the UKF goes on predicting over the real periods after it."""
    from estimation.ukf import UkfEstimator

    d = load_robot("three_bar")
    backend = SimBackend(d)
    rng = np.random.default_rng(0)
    start = backend.reset(rng)
    ukf = UkfEstimator()
    command = d.rest_lengths[d.actuated]
    first = ukf.reset(d, backend.calibration, start.samples, command, rng)
    times = [first.t]
    for k in range(12):
        samples = list(backend.step(command).samples)
        if k == 3:
            samples.append(EncoderSample(samples[-1].t + 1.0e6, command))
            samples.append(EncoderSample(float("nan"), command))
        estimate = ukf.update(samples, command)
        times.append(estimate.t)
    truth = backend.ground_truth()
    backend.close()
    assert truth is not None
    np.testing.assert_allclose(np.diff(times), 0.1, atol=1e-9)  # every period counted
    assert estimate.rejected is not None
    assert estimate.rejected["stamp_in_future"] == 1 and estimate.rejected["stamp_not_finite"] == 1
    assert np.linalg.norm(estimate.com - truth.com) < 0.05


def test_a_stalled_links_seconds_of_samples_are_kept_whole() -> None:
    # A congested link hands over 3 s of samples at once: no gap in them, so none is
    # "in the future"; a glitch stamp beyond them still is.
    d = load_robot("three_bar")
    backend = SimBackend(d)
    rng = np.random.default_rng(0)
    backend.reset(rng)
    bounds = PlausibilityBounds.from_robot(d, backend.calibration)
    counts: dict[str, int] = {}
    screen = PlausibilityScreen(d, bounds, 1.0, counts)
    command = d.rest_lengths[d.actuated]
    samples = [s for _ in range(30) for s in backend.step(command).samples]
    backend.close()
    assert samples[-1].t - samples[0].t > 2.9
    assert screen.timely(samples) == samples and "stamp_in_future" not in counts
    glitch = EncoderSample(samples[-1].t + 5.0, command)
    assert screen.timely([*samples, glitch]) == samples and counts["stamp_in_future"] == 1


# ------------------------------------------------- readings that contradict the description


def _encoder_stream(d: RobotDescription, channel: int, path: NDArray[np.float64],
                    rate: float = 100.0) -> list[Sample]:  # fmt: skip
    """Encoder samples at ``rate`` Hz: every motor mid-range, ``channel`` along ``path``."""
    lo, hi, _ = d.motor_limits
    out: list[Sample] = []
    for k, value in enumerate(path):
        x = 0.5 * (lo + hi)
        x[channel] = value
        out.append(EncoderSample(k / rate, x))
    return out


def test_a_channel_smoothly_beyond_its_range_is_a_mismatch_kept_and_said_once(
    robot: Any, caplog: pytest.LogCaptureFixture
) -> None:
    """Motor 2 moves at its top speed from mid-range to 6 cm below the description's
    range and stays there (a robot whose motor range the description has wrong): every
    reading is kept, nothing rejected, and one line says which motor, what it reads and
    the description's range."""
    d, _, b = robot
    lo, hi, speed = d.motor_limits
    down = np.arange(0.5 * (lo[2] + hi[2]), lo[2] - 0.06, -speed[2] / 100.0)
    path = np.concatenate([down, np.full(200, lo[2] - 0.06)])
    screen = PlausibilityScreen(d, b, 1.0)
    samples = _encoder_stream(d, 2, path)
    with caplog.at_level("WARNING", logger="estimation.mismatch"):
        kept = [s for k in range(0, len(samples), 10) for s in screen.screen(samples[k : k + 10])]
    assert len(kept) == len(samples) and screen.rejected == {} and screen.failed == ()
    assert screen.beyond_description["encoder"] > 200
    cable = d.cables[int(d.actuated[2])].name
    line = (f"motor 2 (cable {cable!r}) reads {path.min():.3f}-{path.max():.3f} m, the "
            f"description's motor range is {lo[2]:.3f}-{hi[2]:.3f} m")  # fmt: skip
    assert screen.mismatches == (line,)
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and said[0].startswith(f"description mismatch: motor 2 (cable {cable!r})")


def test_a_reading_that_jumps_beyond_or_is_absurd_is_still_a_fault(robot: Any) -> None:
    """A jump from mid-range to just beyond the range, a reading a whole span beyond
    it, a negative one: dropped as out of range, not taken for the description's error;
    and a stuck absurd channel fails the stream as before."""
    d, _, b = robot
    lo, hi, _ = d.motor_limits
    mid = 0.5 * (lo[1] + hi[1])
    for bad in (hi[1] + 0.03, hi[1] + 1.5 * (hi[1] - lo[1]), -0.01):
        screen = PlausibilityScreen(d, b, 1.0)
        path = np.array([mid, mid, bad, mid])
        kept = screen.screen(_encoder_stream(d, 1, path))
        assert [float(s.rest_lengths[1]) for s in kept] == [mid, mid, mid], bad
        assert screen.rejected == {"encoder_out_of_range": 1} and screen.mismatches == ()
    for level in (hi[1] + 0.03, hi[1] + 2.0 * (hi[1] - lo[1])):  # within reach, and not
        screen = PlausibilityScreen(d, b, 1.0)
        stuck = np.concatenate([[mid], np.full(150, level)])
        kept = screen.screen(_encoder_stream(d, 1, stuck))
        assert len(kept) == 1 and screen.mismatches == (), level  # never let in
        assert screen.failed == ("encoders",)


def test_a_channel_beyond_its_range_from_the_start_is_a_mismatch(robot: Any) -> None:
    """No reading in use yet: the first reading beyond the range, within reach, cannot
    be a jump; the channel then moves smoothly and stays in use."""
    d, _, b = robot
    _, hi, speed = d.motor_limits
    path = hi[0] + 0.04 - np.arange(50) * 0.5 * speed[0] / 100.0
    screen = PlausibilityScreen(d, b, 1.0)
    kept = screen.screen(_encoder_stream(d, 0, path))
    assert len(kept) == 50 and screen.rejected == {}
    assert screen.mismatches[0].startswith("motor 0 ")


@pytest.mark.parametrize(
    ("estimator", "preset", "shift"),
    [("ukf", "three_bar", -0.05), ("inekf", "three_bar_large", 0.1)],
)
def test_an_estimator_keeps_the_encoders_of_a_robot_whose_motor_range_differs(
    estimator: str, preset: str, shift: float
) -> None:
    """A robot built with its motors' range ``shift`` m off its description, driven to
    its own limit: the estimator, handed the description, keeps every encoder reading,
    names the motors in ``description_mismatch`` and is on track once the robot rests."""
    from dataclasses import replace

    from tensegrity_gym.model.registry import estimator_spec

    d = load_robot(preset)
    cables = tuple(
        replace(c, motor=replace(c.motor, min_rest_length=c.motor.min_rest_length + shift,
                                 max_rest_length=c.motor.max_rest_length + shift))
        if c.motor is not None else c
        for c in d.cables
    )  # fmt: skip
    robot = replace(d, cables=cables)
    backend = SimBackend(robot)
    rng = np.random.default_rng(0)
    start = backend.reset(rng)
    est = estimator_spec(estimator).create()
    hold = d.rest_lengths[d.actuated]
    est.reset(d, backend.calibration, start.samples, hold, rng)
    limit = robot.motor_limits[0 if shift < 0 else 1]
    errors = []
    for _ in range(40):
        estimate = est.update(list(backend.step(limit).samples), limit)
        errors.append(float(np.linalg.norm(estimate.com - backend.ground_truth().com)))
    assert not any(k.startswith("encoder") for k in (estimate.rejected or {}))
    assert "encoders" not in estimate.failed_streams
    assert len(estimate.description_mismatch) >= d.n_actuated // 2  # (some hold slack)
    assert all("the description's motor range is" in x for x in estimate.description_mismatch)
    true_rest = backend.ground_truth().rest_lengths[d.actuated]  # beyond the description's
    step = d.sensors.encoder.resolution
    np.testing.assert_allclose(estimate.rest_lengths, true_rest, atol=2 * step)
    # The InEKF comes to 1 cm at home on this robot, 2-4 cm here (its cables 10 cm
    # longer than it was built for: a slacker, floppier shape); the UKF stays under 1 cm.
    assert max(errors[-10:]) < (0.05 if estimator == "inekf" else 0.015), errors


def test_a_stream_at_another_rate_than_described_is_said_once_whatever_the_clock(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """An IMU read every 10 ms that the description puts at 200 Hz: after 200 intervals
    one line names the stream, its rate and the description's, once, the same with the
    clock started a day later. The described rate with a fifth of the readings lost and
    1 ms of jitter is no mismatch; a stream the description gives no rate is not judged."""
    rng = np.random.default_rng(0)

    def said(origin: float) -> tuple[str, ...]:
        rates = RateMismatch({"imu/red": 200.0, "imu/green": 200.0})
        t = origin + 0.01 * np.arange(400)
        for k in range(0, 400, 7):
            rates.accept("imu/red", t[k : k + 7])
        kept = (origin + 0.005 * np.arange(800))[rng.random(800) > 0.2]
        kept = kept + rng.uniform(-0.001, 0.001, len(kept))
        rates.accept("imu/green", np.sort(kept))
        rates.accept("uwb", t)
        return rates.mismatches

    with caplog.at_level("WARNING", logger="estimation.mismatch"):
        lines = said(0.0)
    assert lines == ("imu/red reads every 10.0 ms (100 Hz); the description's rate is 200 Hz",)
    assert [r.getMessage() for r in caplog.records] == list(lines)
    assert said(86_400.0) == lines


def test_an_estimator_says_its_imu_comes_at_half_the_described_rate() -> None:
    """The invariant EKF replayed on a run whose IMU gives every other reading: its
    health names the mismatch, as on the clean run it names none."""
    from agents.benchmarks.estimation import record_face_transition
    from agents.benchmarks.streams import STREAM_FAULTS, with_fault
    from agents.recordings.runs import replay
    from estimation.inekf import InekfEstimator

    run = record_face_transition("tensegrity_gym/ThreeBarLargeRoll-v0", 0, 25)
    for fault, expected in (("clean", ()), ("imu_half_rate", ("imu/red reads every 10.0 ms",))):
        est = InekfEstimator()
        replay(with_fault(run, STREAM_FAULTS[fault], 0), est)
        lines = est.health.mismatches
        assert len(lines) == len(expected) and all(
            line.startswith(e) for line, e in zip(lines, expected, strict=True)
        ), (fault, lines)
