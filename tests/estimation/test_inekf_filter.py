"""The contact-aided right-invariant EKF (estimation/inekf/filter.py): it agrees with the
dense reference (tests/reference_inekf.py) through propagations, augmentations,
corrections and marginalisations; dead-reckons a known trajectory; on a robot resting on
three endcaps it stays put, finds the biases it can observe and lets the heading's
variance grow; gates outliers; and its NEES over Monte-Carlo runs is near its
dimension."""

from __future__ import annotations

import copy
import dataclasses
import functools

import numpy as np
import pytest
import scipy.stats
from scipy.linalg import expm

from estimation.inekf.filter import (
    CHI2_3DOF_999,
    CorrectionResult,
    InekfNoise,
    RightInvariantEkf,
)
from tensegrity_gym.model.lie import hat, sek3_exp, sek3_log, so3_exp
from tests.conftest import INEKF_GROUP
from tests.reference_inekf import ReferenceInekf

pytestmark = INEKF_GROUP

G = np.array([0.0, 0.0, -9.81])
P0 = np.diag(np.r_[[0.02**2] * 2, 0.2**2, [0.01**2] * 6, [0.01**2] * 3, [0.1**2] * 3])
"""Tilt, yaw, velocity, position, gyro and accelerometer bias variances at reset."""
FEET = np.array([[0.4, 0.0, -0.5], [-0.2, 0.35, -0.5], [-0.2, -0.35, -0.5]])
"""Body-frame endcaps of a robot standing on three of them (m)."""
KIN = 0.01**2 * np.eye(3)  # forward-kinematics covariance, m^2


def _filter(noise: InekfNoise | None = None) -> RightInvariantEkf:
    return RightInvariantEkf(noise, gravity=G)


def _reference(noise: InekfNoise) -> ReferenceInekf:
    n = noise
    return ReferenceInekf((n.gyro, n.accel, n.gyro_bias, n.accel_bias, n.contact_velocity), G)


def _assert_spd(P: np.ndarray) -> None:
    np.testing.assert_array_equal(P, P.T)
    assert np.linalg.eigvalsh(P).min() > 0.0


# ------------------------------------------------------------------ parameters


def test_noise_defaults_are_table_one_and_are_validated() -> None:
    n = InekfNoise()
    assert (n.accel, n.gyro, n.accel_bias, n.gyro_bias, n.contact_velocity) == (
        0.043, 0.002, 0.001, 0.001, 0.05,
    )  # fmt: skip
    for field in dataclasses.fields(InekfNoise):
        for bad in (-1.0, float("nan"), float("inf"), "0.1", True):
            with pytest.raises(ValueError, match=f"InekfNoise.{field.name} "):
                InekfNoise(**{field.name: bad})  # type: ignore[arg-type]
    assert InekfNoise(gyro_bias=0.0).gyro_bias == 0.0
    assert scipy.stats.chi2.ppf(0.999, 3) == pytest.approx(CHI2_3DOF_999, rel=1e-12)


def test_api_refuses_what_it_cannot_use() -> None:
    f = _filter()
    z = np.zeros(3)
    with pytest.raises(ValueError, match="rotation"):
        f.reset(2 * np.eye(3), z, z, z, z, P0)
    with pytest.raises(ValueError, match="reflection"):
        f.reset(-np.eye(3), z, z, z, z, P0)
    with pytest.raises(ValueError, match="P0"):
        f.reset(np.eye(3), z, z, z, z, np.eye(12))
    f.reset(np.eye(3), z, z, z, z, P0)
    for dt in (0.0, -0.01, float("nan")):
        with pytest.raises(ValueError, match="dt"):
            f.propagate(z, z, dt)
    with pytest.raises(ValueError, match="gyro"):
        f.propagate(np.zeros(2), z, 0.01)
    f.augment(4, FEET[0], KIN)
    with pytest.raises(ValueError, match="already"):
        f.augment(4, FEET[0], KIN)
    with pytest.raises(ValueError, match="not in contact"):
        f.correct([5], FEET[:1], KIN)
    with pytest.raises(ValueError, match="not in contact"):
        f.marginalise(5)
    with pytest.raises(ValueError, match="distinct"):
        f.correct([4, 4], FEET[:2], KIN)
    with pytest.raises(ValueError, match="p_body"):
        f.correct([4], FEET[:2], KIN)
    empty = f.correct([], np.zeros((0, 3)), np.zeros((0, 3, 3)))
    assert empty.nodes == () and empty.n_rejected == 0 and empty.nis_total == 0.0


def test_augment_then_marginalise_is_the_identity_and_keeps_the_order_of_the_slots() -> None:
    rng = np.random.default_rng(3)
    f = _filter()
    f.reset(so3_exp(rng.normal(size=3)), rng.normal(size=3), rng.normal(size=3),
            np.zeros(3), np.zeros(3), P0)  # fmt: skip
    for node, foot in zip((7, 2, 5), FEET, strict=True):
        f.augment(node, foot, KIN)
        f.propagate(rng.normal(size=3), rng.normal(size=3) - G, 0.01)
    assert f.contact_nodes == (7, 2, 5)
    assert f.covariance.shape == (24, 24)
    X, P = f.state_matrix, f.covariance
    f.augment(9, FEET[0], KIN)
    f.marginalise(9)
    np.testing.assert_array_equal(f.state_matrix, X)
    np.testing.assert_array_equal(f.covariance, P)
    f.marginalise(2)
    assert f.contact_nodes == (7, 5)
    keep = np.r_[0:12, 15:24]
    np.testing.assert_array_equal(f.covariance, P[np.ix_(keep, keep)])
    np.testing.assert_array_equal(f.contact_positions, X[:3, [5, 7]].T)
    np.testing.assert_array_equal(f.pose_covariance, P[np.ix_(np.r_[0:3, 6:9], np.r_[0:3, 6:9])])
    # correct_all corrects each contact by its slot in the state, not by its node number
    f.augment(4, FEET[1], KIN)
    assert f.contact_nodes == (7, 5, 4)
    y = FEET[[2, 0, 1]] + rng.normal(scale=0.02, size=(3, 3))
    fast = copy.deepcopy(f)
    result = f.correct([7, 5, 4], y, KIN)
    accepted = fast.correct_all(y, np.repeat(KIN[None], 3, axis=0), CHI2_3DOF_999)
    np.testing.assert_array_equal(accepted, result.accepted)
    np.testing.assert_array_equal(fast.state_matrix, f.state_matrix)
    np.testing.assert_array_equal(fast.covariance, f.covariance)


# ------------------------------------------------------------------ the reference


def _reference_script(rng: np.random.Generator, steps: int) -> list[tuple]:
    """Random IMU steps with contacts coming, correcting (errors about the predicted
    measurement, some of 1 m) and going: what both filters are put through."""
    ops: list[tuple] = []
    in_contact: list[int] = []
    for step in range(steps):
        dt = float(rng.uniform(0.002, 0.02))
        ops.append(("propagate", rng.normal(0, 0.8, 3), rng.normal(0, 2.0, 3) - G, dt))
        if step % 7 == 0 and len(in_contact) < 4:
            node = int(rng.choice(sorted(set(range(6)) - set(in_contact))))
            in_contact.append(node)
            A = rng.normal(size=(3, 3)) * 0.03
            ops.append(("augment", node, rng.normal(0, 0.5, 3), A @ A.T + 1e-4 * np.eye(3)))
        if step % 3 == 0 and in_contact:
            nodes = [int(n) for n in rng.permutation(in_contact)[: rng.integers(1, 4)]]
            error = rng.normal(0, 0.05, (len(nodes), 3))  # about the predicted y
            if step % 12 == 0:
                error[0] += 1.0
            A = rng.normal(size=(len(nodes), 3, 3)) * 0.05
            ops.append(("correct", nodes, error, A @ A.transpose(0, 2, 1) + 1e-3 * np.eye(3)))
        if step % 11 == 10 and in_contact:
            ops.append(("marginalise", in_contact.pop(int(rng.integers(len(in_contact))))))
    return ops


def test_fast_filter_matches_the_dense_reference() -> None:
    """Over 300 random steps the states, biases, covariances and gate decisions agree to
    1e-9; the covariance stays symmetric positive definite throughout."""
    rng = np.random.default_rng(11)
    noise = InekfNoise(gyro=0.01, accel=0.1, gyro_bias=0.003, accel_bias=0.01)
    fast, ref = _filter(noise), _reference(noise)
    start = (so3_exp(rng.normal(size=3)), rng.normal(size=3), rng.normal(size=3),
             rng.normal(0, 0.01, 3), rng.normal(0, 0.1, 3), P0)  # fmt: skip
    fast.reset(*start)
    ref.reset(*start)
    counts = {"rejected": 0, "accepted": 0}
    for op, *args in _reference_script(rng, 300):
        if op == "correct":
            nodes, error, cov = args
            X = fast.state_matrix
            slots = [5 + fast.contact_nodes.index(n) for n in nodes]
            args = [nodes, (X[:3, slots] - X[:3, 4:5]).T @ X[:3, :3] + error, cov]
            result = fast.correct(*args)
            nis, accepted = ref.correct(*args, CHI2_3DOF_999)
            np.testing.assert_allclose(result.nis, nis, rtol=1e-9)
            np.testing.assert_array_equal(result.accepted, accepted)
            counts["rejected"] += result.n_rejected
            counts["accepted"] += int(result.accepted.sum())
        else:
            getattr(fast, op)(*args)
            getattr(ref, op)(*args)
        np.testing.assert_allclose(fast.state_matrix, ref.X, rtol=0, atol=1e-9)
        np.testing.assert_allclose(np.r_[fast.gyro_bias, fast.accel_bias], ref.b, atol=1e-9)
        np.testing.assert_allclose(fast.covariance, ref.P, rtol=1e-9, atol=1e-9)
        assert fast.contact_nodes == tuple(ref.nodes)
        _assert_spd(fast.covariance)
    assert counts["rejected"] > 0 and counts["accepted"] > 20


# ------------------------------------------------------------------ dead reckoning


def _exact_motion(
    R0: np.ndarray, v0: np.ndarray, p0: np.ndarray, omega: np.ndarray, accel_body: np.ndarray,
    t: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """The pose at t of a body turning at omega (3,) rad/s with constant specific force
    accel_body (3,) m/s^2, both body frame: the top-right blocks of expm(M t), M =
    [[hat(omega), f, 0], [0, 0, 1], [0, 0, 0]], are the single and double integrals of
    the body's rotation applied to f."""
    M = np.zeros((5, 5))
    M[:3, :3], M[:3, 3], M[3, 4] = hat(omega), accel_body, 1.0
    E = expm(M * t)
    return (R0 @ E[:3, :3], v0 + R0 @ E[:3, 3] + G * t,
            p0 + v0 * t + R0 @ E[:3, 4] + 0.5 * G * t * t)  # fmt: skip


def test_noise_free_imu_follows_the_true_trajectory() -> None:
    """Constant rotation rate and world acceleration: the filter's kinematics are exact,
    whatever the step. Constant body-frame specific force: they are first order, the
    error halving with the step."""
    R0, v0, p0 = so3_exp([0.3, -0.2, 1.0]), np.array([0.5, -0.2, 0.1]), np.array([1.0, 2, 0.3])
    omega, a_world = np.array([0.4, -0.3, 0.9]), np.array([0.2, -0.1, 0.3])
    f = _filter()
    f.reset(R0, v0, p0, np.zeros(3), np.zeros(3), P0)
    dt, steps = 0.01, 300
    R = R0
    for _ in range(steps):
        f.propagate(omega, R.T @ (a_world - G), dt)  # what an ideal IMU reads
        R = R @ so3_exp(omega * dt)
    t = steps * dt
    np.testing.assert_allclose(f.rotation, R0 @ so3_exp(omega * t), atol=1e-12)
    np.testing.assert_allclose(f.velocity, v0 + a_world * t, atol=1e-12)
    np.testing.assert_allclose(f.position, p0 + v0 * t + 0.5 * a_world * t * t, atol=1e-10)

    accel_body = np.array([0.5, 0.2, 9.6])
    R_true, v_true, p_true = _exact_motion(R0, v0, p0, omega, accel_body, 2.0)
    errors = []
    for dt in (0.01, 0.005):
        f.reset(R0, v0, p0, np.zeros(3), np.zeros(3), P0)
        for _ in range(round(2.0 / dt)):
            f.propagate(omega, accel_body, dt)
        np.testing.assert_allclose(f.rotation, R_true, atol=1e-12)
        errors.append(np.linalg.norm(f.position - p_true) + np.linalg.norm(f.velocity - v_true))
    assert errors[0] < 0.1
    assert errors[1] == pytest.approx(errors[0] / 2, rel=0.1)


# ------------------------------------------------------------------ simulated robot


@functools.cache
def _motion(steps: int, dt: float, moving: bool) -> tuple[np.ndarray, ...]:
    """The true body rate omega (S, 3) rad/s, world acceleration (S, 3) m/s^2 and step
    rotations exp(omega dt) (S, 3, 3): a sway, or rest; the same for every run."""
    t = np.arange(steps)[:, None] * dt
    if not moving:
        return np.zeros((steps, 3)), np.zeros((steps, 3)), np.broadcast_to(np.eye(3), (steps, 3, 3))
    omega = np.c_[0.3 * np.sin(t), 0.2 * np.cos(1.3 * t), np.full_like(t, 0.4)]
    a_w = np.c_[0.3 * np.cos(t), 0.2 * np.sin(2 * t), 0.1 * np.sin(t)]
    return omega, a_w, so3_exp(omega * dt)


def _simulate(f: RightInvariantEkf, rng: np.random.Generator, steps: int, dt: float,
              truth: dict, moving: bool) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Run the true robot (``truth``: R, v, p, b (6,), d (3, 3) updated in place) on
    FEET and the filter on its noisy IMU and forward kinematics, both by the filter's
    discrete model; ``moving``: the body sways and the endcaps slip as the filter's
    contact velocity noise says (else the robot rests and the endcaps stay). Returns the
    filter's covariance (S, 24, 24) and its position and velocity errors (S, 6) after
    every step."""
    n = f.noise
    covariances, errors = [], []
    walk = np.sqrt(dt) * np.repeat([n.gyro_bias, n.accel_bias], 3)
    for omega, a_w, dR in zip(*_motion(steps, dt, moving), strict=True):
        R, v = truth["R"], truth["v"]
        gyro = omega + truth["b"][:3] + rng.normal(0, n.gyro / np.sqrt(dt), 3)
        accel = R.T @ (a_w - G) + truth["b"][3:] + rng.normal(0, n.accel / np.sqrt(dt), 3)
        f.propagate(gyro, accel, dt)
        truth["p"] = truth["p"] + v * dt + 0.5 * a_w * dt * dt
        truth["v"] = v + a_w * dt
        truth["R"] = R @ dR
        if moving:
            truth["d"] += rng.normal(0, n.contact_velocity * np.sqrt(dt), (3, 3))
        truth["b"] += rng.normal(0, 1.0, 6) * walk
        y = (truth["d"] - truth["p"]) @ truth["R"] + rng.normal(0, np.sqrt(KIN[0, 0]), (3, 3))
        f.correct(list(range(3)), y, KIN)
        covariances.append(f.covariance)
        errors.append(np.r_[f.position - truth["p"], f.velocity - truth["v"]])
    return np.array(covariances), np.array(errors)


def _start(rng: np.random.Generator, f: RightInvariantEkf, R: np.ndarray, b: np.ndarray,
           perturb: bool) -> dict:  # fmt: skip
    """Truth at R, at rest, standing on FEET with biases b; the filter reset about it
    (at an error drawn from P0 if ``perturb``) and its contacts augmented."""
    p = np.array([0.0, 0.0, 0.5])
    truth = {"R": R, "v": np.zeros(3), "p": p, "b": b.copy(), "d": p + FEET @ R.T}
    # the truth is exp(e) times the estimate: the estimate is exp(-e) X, b - e_b
    e = rng.multivariate_normal(np.zeros(15), P0) if perturb else np.r_[np.zeros(9), b]
    X = np.eye(5)
    X[:3, :3], X[:3, 4] = R, p
    Xhat = sek3_exp(-e[:9]) @ X
    f.reset(Xhat[:3, :3], Xhat[:3, 3], Xhat[:3, 4], b[:3] - e[9:12], b[3:] - e[12:], P0)
    for node in range(3):
        y = (truth["d"][node] - p) @ R + rng.multivariate_normal(np.zeros(3), KIN)
        f.augment(node, y, KIN)
    return truth


def test_resting_robot_stays_put_and_finds_the_observable_biases() -> None:
    """20 s at rest on three endcaps with the paper's noise and a biased IMU. Position
    and velocity stay near the truth. Observable: the tilt (roll, pitch), the gyro bias
    across the up axis (it would tilt the robot against gravity) and the accelerometer
    bias along it; their variances shrink and the estimates converge. Unobservable at
    rest: the heading, whose variance only grows, and the accelerometer bias across up
    (it trades against the tilt), left consistent with its variance."""
    rng = np.random.default_rng(5)
    f = _filter()
    R = so3_exp([0.1, -0.2, 0.5])
    b = np.array([0.02, -0.015, 0.01, 0.15, -0.12, 0.2])
    truth = _start(rng, f, R, b, perturb=False)
    P, errors = _simulate(f, rng, 4000, 0.005, truth, moving=False)
    assert f.is_finite()
    assert np.abs(errors[:, :3]).max() < 0.05 and np.abs(errors[:, 3:]).max() < 0.15
    speed_var = np.trace(P[:, 3:6, 3:6], axis1=1, axis2=2)
    assert speed_var[-1] < 1.5 * speed_var[200]  # bounded after the first second
    up = R.T @ np.array([0.0, 0.0, 1.0])  # body frame
    across = np.eye(3) - np.outer(up, up)
    bg_err, ba_err = f.gyro_bias - truth["b"][:3], f.accel_bias - truth["b"][3:]
    P_bg, P_ba = P[-1, 18:21, 18:21], P[-1, 21:24, 21:24]
    assert np.linalg.norm(across @ bg_err) < 0.25 * np.linalg.norm(across @ b[:3])
    assert np.linalg.norm(across @ P_bg @ across) < 0.25 * P0[9, 9]
    assert abs(up @ ba_err) < 0.1 * abs(up @ b[3:])
    assert up @ P_ba @ up < 0.1 * P0[12, 12]
    # the rest agrees with the filter's own uncertainty
    for err, cov in ((bg_err, P_bg), (ba_err, P_ba)):
        assert err @ np.linalg.solve(cov, err) < scipy.stats.chi2.ppf(0.999, 3)
    yaw, tilt = P[:, 2, 2], P[:, 0, 0] + P[:, 1, 1]
    assert np.all(np.diff(yaw) >= 0.0) and yaw[-1] > 1.2 * P0[2, 2]
    assert tilt[-1] < 0.6 * tilt[0] and tilt.max() < 1.01 * tilt[0]  # bounded, falling
    _assert_spd(P[-1])


def test_chi_square_gate_rejects_a_one_metre_outlier() -> None:
    rng = np.random.default_rng(8)
    f = _filter()
    R = so3_exp([0.05, 0.1, -0.3])
    truth = _start(rng, f, R, np.zeros(6), perturb=False)
    _simulate(f, rng, 200, 0.005, truth, moving=False)
    y = (truth["d"] - truth["p"]) @ truth["R"]
    y[1] += np.array([0.0, 0.6, 0.8])  # 1 m off
    good, fast = copy.deepcopy(f), copy.deepcopy(f)
    result = f.correct([0, 1, 2], y, KIN)
    assert isinstance(result, CorrectionResult)
    np.testing.assert_array_equal(result.accepted, [True, False, True])
    assert result.n_rejected == 1 and result.nis[1] > CHI2_3DOF_999 > result.nis[[0, 2]].max()
    # the outlier did not touch the state: the same as correcting with the others alone
    alone = good.correct([0, 2], y[[0, 2]], KIN)
    np.testing.assert_allclose(result.nis_total, alone.nis_total, rtol=1e-12)
    np.testing.assert_allclose(f.state_matrix, good.state_matrix, atol=1e-14)
    np.testing.assert_allclose(f.covariance, good.covariance, atol=1e-16)
    # without the gate it would have been used
    ungated = copy.deepcopy(good).correct([1], y[[1]], KIN, gate=None)
    assert ungated.accepted.all()
    # the hot path refuses the same outlier, bit for bit
    accepted = fast.correct_all(y, np.repeat(KIN[None], 3, axis=0), CHI2_3DOF_999)
    np.testing.assert_array_equal(accepted, [True, False, True])
    np.testing.assert_array_equal(fast.state_matrix, f.state_matrix)
    np.testing.assert_array_equal(fast.covariance, f.covariance)


def test_nees_is_near_the_dimension_over_monte_carlo_runs() -> None:
    """40 runs of 2 s swaying on three slipping endcaps, each started at an error drawn
    from P0, truth and filter on the same noise model: the mean NEES of the 24-dim error
    at the end lies near 24 (bounds loose: the filter linearises)."""
    rng = np.random.default_rng(21)
    nees = []
    for _ in range(40):
        f = _filter()
        b = rng.multivariate_normal(np.zeros(6), P0[9:, 9:])
        truth = _start(rng, f, so3_exp(rng.normal(0, 0.3, 3)), b, perturb=True)
        _simulate(f, rng, 400, 0.005, truth, moving=True)
        X = np.eye(8)
        X[:3, :3], X[:3, 3], X[:3, 4], X[:3, 5:] = truth["R"], truth["v"], truth["p"], truth["d"].T
        err = np.r_[sek3_log(X @ np.linalg.inv(f.state_matrix)),
                    truth["b"] - np.r_[f.gyro_bias, f.accel_bias]]  # fmt: skip
        nees.append(err @ np.linalg.solve(f.covariance, err))
    mean = float(np.mean(nees))
    print(f"mean NEES {mean:.2f} (dim 24)")
    assert 0.6 * 24 < mean < 1.5 * 24, mean


def test_bench_reports_every_step() -> None:
    from agents.benchmarks.inekf import bench_inekf

    out = bench_inekf(n=20)
    assert out["state_dim"] == 24.0
    for step in ("propagate", "correct", "augment", "marginalise"):
        assert 0.0 < out[f"{step}_us"] <= out[f"{step}_mean_us"] * 20


def _two_contacts(rng: np.random.Generator) -> RightInvariantEkf:
    """A filter at a random pose, velocity and position, nodes 3 and 1 in contact."""
    f = _filter()
    f.reset(so3_exp(rng.normal(size=3)), rng.normal(size=3), rng.normal(size=3),
            np.zeros(3), np.zeros(3), P0)  # fmt: skip
    for node, foot in zip((3, 1), FEET[:2], strict=True):
        f.augment(node, foot, KIN)
    return f


def test_a_contact_moves_by_its_shift_alone_and_velocity_variance_adds() -> None:
    f = _two_contacts(np.random.default_rng(4))
    X, P = f.state_matrix, f.covariance
    f.move_contact(1, [0.05, -0.02, 0.0])
    moved = X.copy()
    moved[:3, 6] += [0.05, -0.02, 0.0]
    np.testing.assert_array_equal(f.state_matrix, moved)
    np.testing.assert_array_equal(f.covariance, P)  # a known motion, not a measurement
    f.add_velocity_variance(0.25)
    np.testing.assert_array_equal(np.diag(f.covariance)[3:6], np.diag(P)[3:6] + 0.25)
    np.testing.assert_array_equal(np.delete(f.covariance, [3, 4, 5], 0), np.delete(P, [3, 4, 5], 0))
    with pytest.raises(ValueError, match="node 4 is not in contact"):
        f.move_contact(4, np.zeros(3))
    with pytest.raises(ValueError, match="variance must be a finite number >= 0"):
        f.add_velocity_variance(float("nan"))


def test_a_height_correction_is_the_scalar_joseph_update_of_the_contacts_z() -> None:
    """Each contact's height corrects by the dense Kalman update with the row e_z at its
    z (the rotation's lever left out, on purpose): the covariance is the Joseph form,
    the contact moves toward the measured height, and so does what is correlated with
    it; a variance that is not a number > 0 is refused."""
    f = _two_contacts(np.random.default_rng(6))
    var = 0.05**2
    P, z_before = f.covariance, f.contact_positions[:, 2].copy()
    heights = z_before + np.array([0.2, -0.1])  # the floor, off each estimate
    # the mean: X <- exp(K z) X, b <- b + K z, for the first contact (node 3) alone
    one = copy.deepcopy(f)
    one.correct_heights([3], heights[:1].copy(), var)
    delta = P[:, 11] / (P[11, 11] + var) * 0.2
    np.testing.assert_allclose(one.state_matrix, sek3_exp(delta[:-6]) @ f.state_matrix,
                               atol=1e-12)  # fmt: skip
    np.testing.assert_allclose(np.r_[one.gyro_bias, one.accel_bias], delta[-6:], atol=1e-15)
    f.correct_heights([3, 1], heights.copy(), var)
    expected = P  # dense, as a textbook writes it: one contact's row after the other
    for row in (11, 14):
        h = np.zeros(P.shape[0])
        h[row] = 1.0
        k = expected @ h / (h @ expected @ h + var)
        a = np.eye(P.shape[0]) - np.outer(k, h)
        expected = a @ expected @ a.T + var * np.outer(k, k)
    np.testing.assert_allclose(f.covariance, expected, atol=1e-15)
    _assert_spd(f.covariance)
    moved = f.contact_positions[:, 2] - z_before
    assert 0.0 < moved[0] < 0.2 and -0.1 < moved[1] < 0.0  # toward the floor, not past it
    assert np.all(np.diag(f.covariance)[[11, 14]] < np.diag(P)[[11, 14]])
    with pytest.raises(ValueError, match="variance must be a finite number > 0"):
        f.correct_heights([3, 1], heights, 0.0)
    with pytest.raises(ValueError, match=r"heights must have shape \(2,\)"):
        f.correct_heights([3, 1], heights[:1], var)
    with pytest.raises(ValueError, match="node 4 is not in contact"):
        f.correct_heights([4], heights[:1], var)
    with pytest.raises(ValueError, match="nodes must be distinct"):
        f.correct_heights([3, 3], heights, var)


def test_the_contacts_slip_density_can_change_between_propagations() -> None:
    # Two filters alike but for the slip density: only the contacts' own variance grows
    # by the difference of the densities' squares times dt.
    rng = np.random.default_rng(6)
    pair = [_filter(), _filter()]
    R, v, p = so3_exp(rng.normal(size=3)), rng.normal(size=3), rng.normal(size=3)
    for f in pair:
        f.reset(R, v, p, np.zeros(3), np.zeros(3), P0)
        f.augment(2, FEET[0], KIN)
    pair[1].set_contact_velocity_noise(0.3)
    for f in pair:
        f.propagate([0.1, -0.2, 0.3], -G, 0.01)
    grown = pair[1].covariance - pair[0].covariance
    expected = np.zeros_like(grown)
    expected[9:12, 9:12] = np.eye(3) * (0.3**2 - InekfNoise().contact_velocity ** 2) * 0.01
    np.testing.assert_allclose(grown, expected, atol=1e-15)
    with pytest.raises(ValueError, match="density must be a finite number >= 0"):
        pair[0].set_contact_velocity_noise(-1.0)


def test_one_reading_step_is_the_steps_it_fuses() -> None:
    # propagate_reading = set the slip density by the rate, propagate, add the velocity
    # variance, roll the rolling contacts: bit for bit, contact by contact.
    rng = np.random.default_rng(8)
    pair = [_filter(), _filter()]
    R, v, p = so3_exp(rng.normal(size=3)), rng.normal(size=3), rng.normal(size=3)
    b_g = np.array([0.01, -0.02, 0.005])
    for f in pair:
        f.reset(R, v, p, b_g, np.zeros(3), P0)
        for node, foot in zip((3, 1, 5), FEET, strict=True):
            f.augment(node, foot, KIN)
    gyro, accel, dt = np.array([0.4, -1.2, 2.5]), np.array([0.3, 0.1, 9.9]), 0.005
    slip = np.array([0.005, 0.05, 0.05])
    radii = np.array([0.06, 0.0, 0.06])
    pair[0].propagate_reading(gyro, accel, dt, slip, 1e-3, radii)
    rate = float(np.linalg.norm(gyro - b_g))
    ref = pair[1]
    ref.set_contact_velocity_noise(min(slip[0] + slip[1] * rate, slip[2]))
    ref.propagate(gyro, accel, dt)
    ref.add_velocity_variance(1e-3)
    turn = ref.rotation[:, 2] * ((gyro[2] - b_g[2]) * dt * 0.06)
    for node in (3, 5):
        ref.move_contact(node, [turn[1], -turn[0], 0.0])
    np.testing.assert_array_equal(pair[0].state_matrix, ref.state_matrix)
    np.testing.assert_array_equal(pair[0].covariance, ref.covariance)
    # A turn the gyro missed (a reading at its full scale) adds to the rotation alone.
    turned = copy.deepcopy(pair[0])
    pair[0].propagate_reading(gyro, accel, dt, slip, 0.0, radii)
    turned.propagate_reading(gyro, accel, dt, slip, 0.0, radii, rotation_variance=4e-4)
    grown = turned.covariance - pair[0].covariance
    np.testing.assert_allclose(np.diag(grown)[:3], 4e-4, rtol=1e-12)
    grown[:3, :3] -= np.eye(3) * 4e-4
    np.testing.assert_allclose(grown, 0.0, atol=1e-15)
    with pytest.raises(ValueError, match=r"roll_radii must have shape \(3,\)"):
        pair[0].propagate_reading(gyro, accel, dt, slip, 0.0, np.zeros(2))
    with pytest.raises(ValueError, match="dt must be a finite number"):
        pair[0].propagate_reading(gyro, accel, 0.0, slip, 0.0, radii)


def test_a_filter_is_finite_unless_an_entry_is_not() -> None:
    f = _filter()
    f.reset(np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), P0 * 1e300)
    assert f.is_finite()  # its sum overflows; every entry is finite
    f.reset(np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), P0)
    f.augment(0, FEET[0], KIN)
    f.move_contact(0, [np.inf, 0.0, 0.0])
    assert not f.is_finite()
