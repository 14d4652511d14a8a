"""The UKF against its references: filterpy, the plain Kalman filter, the numpy model."""

from __future__ import annotations

import ast
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import scipy.stats
from filterpy.kalman import MerweScaledSigmaPoints
from filterpy.kalman import UnscentedKalmanFilter as FilterpyUKF

from agents.runs import RecordedRun, record_run
from estimation.ukf import (
    SigmaPointParams,
    SpringMassModel,
    UkfConfig,
    UkfEstimator,
    UnscentedKalmanFilter,
)
from estimation.ukf.sigma_points import sigma_points
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.model.samples import AhrsSample
from tensegrity_gym.tasks.gaits import FaceGait

ROOT = Path(__file__).resolve().parents[1]
RNG = np.random.default_rng(0)  # the UKF ignores it: it is deterministic given its samples


@pytest.fixture(scope="module")
def rolling_run() -> RecordedRun:
    """30 control steps of the 3-bar robot rolling under its gait, with the truth."""
    gait: list[FaceGait] = []

    def policy(env, obs, step):  # type: ignore[no-untyped-def]
        if not gait:
            gait.append(FaceGait(env.backend.description, env.task))
        return gait[0](obs)

    return record_run("tensegrity_gym/ThreeBarRoll-v0", policy, 30, seed=3)


@pytest.mark.parametrize("n", [3, 36])
@pytest.mark.parametrize("alpha", [0.0139, 0.5, 1.0])
def test_sigma_points_and_weights_match_filterpy(n: int, alpha: float) -> None:
    rng = np.random.default_rng(n)
    A = rng.standard_normal((n, n))
    P = A @ A.T + n * np.eye(n)
    x = rng.standard_normal(n)
    params = SigmaPointParams(alpha=alpha)
    ref = MerweScaledSigmaPoints(n, alpha, 2.0, 0.0)
    wm, wc = params.weights(n)
    np.testing.assert_allclose(wm, ref.Wm, rtol=1e-14)
    np.testing.assert_allclose(wc, ref.Wc, rtol=1e-14)
    ours, jitter = sigma_points(x, P, params)
    assert jitter == 0.0
    np.testing.assert_allclose(ours, ref.sigma_points(x, P), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(("alpha", "chained", "atol"), [(0.0139, False, 1e-9), (1.0, True, 1e-9)])
def test_fast_filter_matches_filterpy_on_the_spring_mass_model(
    rolling_run: RecordedRun, alpha: float, chained: bool, atol: float
) -> None:
    """Same model, same measurements, four predict-update cycles.

    With the paper's alpha the weights reach |W| ~ 5000, and over a step of contact
    dynamics rounding differences of 1e-16 grow ~100-fold a cycle; each cycle then
    starts both filters from the same mean and covariance. With alpha = 1 the two
    filters run side by side, unsynchronised, for all four cycles.
    """
    run = rolling_run
    config = UkfConfig(gate_probability=None, sigma_points=SigmaPointParams(alpha=alpha))
    est = UkfEstimator(config)
    est.reset(run.description, run.calibration, run.start.samples, run.start.command, RNG)
    n = est.filter.dim
    points = MerweScaledSigmaPoints(n, alpha, 2.0, 0.0)
    ref = FilterpyUKF(n, 1, 0.1, hx=None, fx=None, points=points)
    ref.x, ref.P = est.filter.x.copy(), est.filter.P.copy()
    for step in run.steps[5:9]:
        prepared = est.prepare(step.samples, step.command)
        if not chained:
            ref.x, ref.P = est.filter.x.copy(), est.filter.P.copy()
        est.apply(prepared, est.filter)
        batch = prepared.batch
        ref.Q = np.diag(prepared.process_noise)
        ref.predict(
            dt=prepared.duration,
            fx=lambda s, dt, p=prepared: est.model.propagate(s, dt, p.rest_start, p.rest_end),
        )
        ref.update(
            batch.z,
            R=np.diag(batch.variance),
            hx=lambda s, b=batch: est.measurements.predict(b, s[None])[0],
        )
        assert batch.size > 20
        np.testing.assert_allclose(est.filter.x, ref.x, rtol=0, atol=atol)
        np.testing.assert_allclose(est.filter.P, ref.P, rtol=0, atol=atol)


@pytest.mark.parametrize("alpha", [0.0139, 1.0])
def test_ukf_equals_kalman_filter_on_a_linear_gaussian_model(alpha: float) -> None:
    rng = np.random.default_rng(7)
    n, k = 6, 4
    A = np.eye(n) + 0.1 * rng.standard_normal((n, n))
    H = rng.standard_normal((k, n))
    Q = np.diag(rng.uniform(0.01, 0.1, n))
    R = rng.uniform(0.05, 0.2, k)
    x = rng.standard_normal(n)
    B = rng.standard_normal((n, n))
    P = B @ B.T + np.eye(n)
    ukf = UnscentedKalmanFilter(x, P, SigmaPointParams(alpha=alpha))
    for _ in range(5):
        z = rng.standard_normal(k)
        ukf.predict(lambda s: s @ A.T, Q)
        ukf.update(z, R, lambda s: s @ H.T)
        # The textbook Kalman filter.
        x = A @ x
        P = A @ P @ A.T + Q
        S = H @ P @ H.T + np.diag(R)
        K = P @ H.T @ np.linalg.inv(S)
        x = x + K @ (z - H @ x)
        P = P - K @ S @ K.T
        np.testing.assert_allclose(ukf.x, x, atol=1e-9)
        np.testing.assert_allclose(ukf.P, P, atol=1e-9)


@pytest.mark.parametrize("robot", ["three_bar", "three_bar_large", "superball"])
def test_compiled_model_matches_the_numpy_model(robot: str) -> None:
    d = load_robot(robot)
    model = SpringMassModel(d)
    rng = np.random.default_rng(1)
    x0 = np.concatenate([d.initial_positions.ravel(), np.zeros(3 * d.n_nodes)])
    states = x0 + 0.03 * d.characteristic_length * rng.standard_normal((6, x0.size))
    states[0, 2] -= 0.02  # a node under the ground
    rest = d.rest_lengths[d.actuated]
    states[1, : 3 * d.n_nodes] *= 0.9  # cables slack
    # Two rods pressed together: move rod 1's centre onto rod 0's.
    nodes = states[2, : 3 * d.n_nodes].reshape(-1, 3)
    (a0, a1), (b0, b1) = d.rod_nodes[0], d.rod_nodes[1]
    shift = 0.5 * (nodes[a0] + nodes[a1]) - 0.5 * (nodes[b0] + nodes[b1])
    nodes[[b0, b1]] += shift + np.array([0.0, 0.0, 0.5 * d.rods[0].endcap_radius])
    fast = model.propagate(states, 0.1, rest, 0.95 * rest)
    slow = model.propagate(states, 0.1, rest, 0.95 * rest, compiled=False)
    assert np.all(np.isfinite(fast))
    np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-9)

    # The pressed rods were pushed apart.
    def centre_gap(nodes: np.ndarray) -> float:
        return float(np.linalg.norm(0.5 * (nodes[a0] + nodes[a1] - nodes[b0] - nodes[b1])))

    moved = fast[2, : 3 * d.n_nodes].reshape(-1, 3)
    assert centre_gap(moved) > 2.0 * centre_gap(nodes)


def test_model_holds_a_resting_robot_still() -> None:
    d = load_robot("three_bar")
    model = SpringMassModel(d)
    x0 = np.concatenate([d.initial_positions.ravel(), np.zeros(3 * d.n_nodes)])
    x = model.propagate(x0, 5.0, d.rest_lengths[d.actuated])
    drift = np.linalg.norm((x[: x.size // 2] - x0[: x.size // 2]).reshape(-1, 3), axis=1)
    assert drift.max() < 0.02  # metres: it settles, it does not bounce or fly off
    assert np.abs(x[x.size // 2 :]).max() < 1e-3


def _replay(run: RecordedRun, est: UkfEstimator, steps: list) -> list:  # type: ignore[type-arg]
    out = []
    for step in steps:
        out.append(est.update(step.samples, step.command))
    return out


def test_a_spurious_imu_value_is_gated_out(rolling_run: RecordedRun) -> None:
    run = rolling_run
    est = UkfEstimator()
    est.reset(run.description, run.calibration, run.start.samples, run.start.command, RNG)
    _replay(run, est, run.steps[:10])
    step = run.steps[10]
    last_t = max(s.t for s in step.samples)
    # One AHRS reading of rod 0 upside down: its axis flipped (papers/000 fig. 8).
    bad = AhrsSample(last_t, 0, np.array([1.0, 0.0, 0.0, 0.0]))
    wrong = [*step.samples, bad]
    # Only the flipped reading is the newest of rod 0: it replaces the good ones.
    est.update(wrong, step.command)
    assert est.diagnostics.rejected_by_kind.get("rod_axis", 0) == 3
    after = _replay(run, est, run.steps[11:13])
    truth = run.steps[12].truth
    assert truth is not None
    assert np.linalg.norm(after[-1].com - truth.com) < 0.03
    assert not any(e.reinitialised for e in after)


def test_divergence_reinitialises_with_a_flag(rolling_run: RecordedRun) -> None:
    run = rolling_run
    est = UkfEstimator()
    est.reset(run.description, run.calibration, run.start.samples, run.start.command, RNG)
    _replay(run, est, run.steps[:10])
    est.filter.x[:] = np.nan
    est_11 = est.update(run.steps[10].samples, run.steps[10].command)
    assert est_11.reinitialised and not est_11.healthy
    assert est_11.is_finite()
    later = _replay(run, est, run.steps[11:16])
    assert all(e.healthy and not e.reinitialised for e in later)
    truth = run.steps[15].truth
    assert truth is not None
    assert np.linalg.norm(later[-1].com - truth.com) < 0.05
    assert est.diagnostics.reinitialisations == 1


def test_start_from_a_given_pose(rolling_run: RecordedRun) -> None:
    run = rolling_run
    truth = run.start.truth
    assert truth is not None
    pose = tuple(map(tuple, truth.node_positions.tolist()))
    est = UkfEstimator(UkfConfig(initial_positions=pose))  # type: ignore[arg-type]
    first = est.reset(run.description, run.calibration, run.start.samples, run.start.command, RNG)
    np.testing.assert_array_equal(first.node_positions, truth.node_positions)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("range_sigma", -1.0),
        ("axis_sigma", 0.0),
        ("gate_probability", 1.5),
        ("divergence_window", 0),
    ],
)
def test_bad_config_names_the_field(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=field):
        UkfConfig(**{field: value})


def test_bad_inputs_give_clear_errors(rolling_run: RecordedRun) -> None:
    run = rolling_run
    with pytest.raises(RuntimeError, match="reset"):
        UkfEstimator().update([], np.zeros(6))
    with pytest.raises(ValueError, match="anchors"):
        UkfEstimator(UkfConfig(anchors=(0, 99))).reset(
            run.description, run.calibration, run.start.samples, run.start.command, RNG
        )
    with pytest.raises(ValueError, match="initial_positions"):
        UkfEstimator(UkfConfig(initial_positions=((0.0, 0.0, 0.0),))).reset(
            run.description, run.calibration, run.start.samples, run.start.command, RNG
        )
    bad = replace(run.calibration, uwb_offsets=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="uwb_offsets"):
        UkfEstimator().reset(run.description, bad, run.start.samples, run.start.command, RNG)


def test_the_filter_never_sees_the_simulator() -> None:
    """estimation/ imports no simulator and no pybullet, and the env hands the UKF
    only samples: with the backend's truth made to fail, the UKF still runs."""
    for file in (ROOT / "estimation").rglob("*.py"):
        for node in ast.walk(ast.parse(file.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            for name in names:
                assert not name.startswith(("pybullet", "tensegrity_gym.sim")), (file, name)

    import gymnasium as gym

    env = gym.make("tensegrity_gym/ThreeBarRoll-v0")
    backend = env.unwrapped.backend  # type: ignore[attr-defined]
    obs, _ = env.reset(seed=0)

    def no_truth() -> None:
        return None  # a robot without motion capture

    backend.ground_truth = no_truth
    for _ in range(5):
        obs, _, _, _, info = env.step(env.action_space.sample())
    assert np.all(np.isfinite(obs))
    assert "com_true" not in info and info["estimator_healthy"]
    env.close()


def test_consistency_on_a_quiet_trajectory() -> None:
    """NEES of the node positions over seeded runs of a resting robot, in its band.

    Within a run the errors are correlated in time, so each run's average counts as
    one chi-square sample of 3 n degrees of freedom: the band is that of 5 x 18 dof.
    """

    def hold(env, obs, step):  # type: ignore[no-untyped-def]
        d = env.backend.description
        return env.targets_to_action(d.rest_lengths[d.actuated])

    nees, nis = [], []
    for seed in range(5):
        run = record_run("tensegrity_gym/ThreeBarRoll-v0", hold, 30, seed=seed)
        est = UkfEstimator()
        estimates = [
            est.reset(run.description, run.calibration, run.start.samples, run.start.command, RNG)
        ]
        estimates += _replay(run, est, run.steps)
        n = run.description.n_nodes
        for e, step in zip(estimates[11:], run.steps[10:], strict=True):
            assert step.truth is not None and e.covariance is not None
            err = (e.node_positions - step.truth.node_positions).ravel()
            nees.append(err @ np.linalg.solve(e.covariance[: 3 * n, : 3 * n], err) / (3 * n))
        nis += list(est.diagnostics.nis_history)[10:]
        # A first fit from one UWB round may be re-done once the filter has more.
        assert est.diagnostics.reinitialisations <= 1
    dof = 5 * 3 * 6
    low, high = scipy.stats.chi2.ppf([0.025, 0.975], dof) / dof
    assert low < float(np.mean(nees)) < high, (low, float(np.mean(nees)), high)
    assert 0.3 < float(np.mean(nis)) < 2.0
