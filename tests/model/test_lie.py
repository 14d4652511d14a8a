"""The Lie-group module, held to the group axioms, exp/log round trips, the adjoint
identity and scipy's rotations, at ordinary, tiny and half-turn angles."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tensegrity_gym.model import lie

RNG = np.random.default_rng(7)


def _rotvecs(n: int) -> np.ndarray:
    """Random rotation vectors with angles across (0, pi), plus tiny and near-half-turn."""
    axes = RNG.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate(
        [RNG.uniform(0.0, np.pi, n - 6), [0.0, 1e-12, 1e-7, 1e-4, np.pi - 1e-7, np.pi]]
    )
    return axes * angles[:, None]


PHI = _rotvecs(64)


def _tangent(n: int, k: int) -> np.ndarray:
    return np.concatenate([PHI[:n], RNG.normal(size=(n, 3 * k))], axis=1)


def test_quaternions_agree_with_scipy() -> None:
    q = lie.quat_from_rotvec(PHI)
    ref = Rotation.from_rotvec(PHI)
    np.testing.assert_allclose(lie.quat_to_matrix(q), ref.as_matrix(), atol=1e-12)
    v = RNG.normal(size=(len(PHI), 3))
    np.testing.assert_allclose(lie.quat_rotate(q, v), ref.apply(v), atol=1e-12)
    R = ref.as_matrix()
    q_back = lie.matrix_to_quat(R)
    np.testing.assert_allclose(lie.quat_to_matrix(q_back), R, atol=1e-12)
    assert np.all(q_back[:, 3] >= 0.0)
    a, b = Rotation.random(10, random_state=1), Rotation.random(10, random_state=2)
    np.testing.assert_allclose(
        lie.quat_to_matrix(lie.quat_multiply(a.as_quat(), b.as_quat())),
        (a * b).as_matrix(),
        atol=1e-12,
    )
    identity = lie.quat_multiply(q, lie.quat_conjugate(q))
    np.testing.assert_allclose(identity, np.tile([0.0, 0.0, 0.0, 1.0], (len(q), 1)), atol=1e-12)


def test_so3_exp_log_round_trip_and_scipy() -> None:
    R = lie.so3_exp(PHI)
    np.testing.assert_allclose(R, Rotation.from_rotvec(PHI).as_matrix(), atol=1e-12)
    back = lie.so3_log(R)
    # at exactly a half turn phi and -phi are the same rotation
    np.testing.assert_allclose(lie.so3_exp(back), R, atol=1e-12)
    np.testing.assert_allclose(back[:-2], PHI[:-2], atol=1e-9)
    np.testing.assert_allclose(lie.quat_to_rotvec(lie.quat_from_rotvec(PHI[:-2])), PHI[:-2],
                               atol=1e-12)  # fmt: skip
    np.testing.assert_allclose(lie.vee(lie.hat(PHI)), PHI)
    v = RNG.normal(size=PHI.shape)
    np.testing.assert_allclose(
        np.einsum("nij,nj->ni", lie.hat(PHI), v), np.cross(PHI, v), atol=1e-12
    )


def test_left_jacobian_is_the_derivative_and_has_its_inverse() -> None:
    phi = PHI[:-3]  # not at a half turn, where the inverse does not exist
    J = lie.so3_left_jacobian(phi)
    np.testing.assert_allclose(J @ lie.so3_left_jacobian_inverse(phi),
                               np.broadcast_to(np.eye(3), J.shape), atol=1e-9)  # fmt: skip
    d = 1e-6 * RNG.normal(size=phi.shape)
    lhs = lie.so3_exp(phi + d)
    rhs = lie.so3_exp(np.einsum("nij,nj->ni", J, d)) @ lie.so3_exp(phi)
    np.testing.assert_allclose(lhs, rhs, atol=1e-10)


@pytest.mark.parametrize(
    ("exp", "log", "inverse", "adjoint", "k"),
    [
        (lie.se3_exp, lie.se3_log, lie.se3_inverse, lie.se3_adjoint, 1),
        (lie.se23_exp, lie.se23_log, lie.se23_inverse, lie.se23_adjoint, 2),
        (lie.sek3_exp, lie.sek3_log, lie.sek3_inverse, lie.sek3_adjoint, 1),
        (lie.sek3_exp, lie.sek3_log, lie.sek3_inverse, lie.sek3_adjoint, 5),
    ],
    ids=["SE(3)", "SE_2(3)", "SE_k(3), k=1", "SE_k(3), k=5"],
)
def test_sek3_group_axioms_round_trips_and_adjoint(exp, log, inverse, adjoint, k) -> None:
    n = len(PHI) - 2  # log is unique below a half turn
    xi, eta, zeta = _tangent(n, k), _tangent(n, k)[::-1], _tangent(n, k)
    X, Y, Z = exp(xi), exp(eta), exp(zeta)
    eye = np.broadcast_to(np.eye(3 + k), X.shape)
    np.testing.assert_allclose((X @ Y) @ Z, X @ (Y @ Z), atol=1e-9)  # associativity
    np.testing.assert_allclose(X @ inverse(X), eye, atol=1e-9)
    np.testing.assert_allclose(inverse(X) @ X, eye, atol=1e-9)
    np.testing.assert_allclose(inverse(X), np.linalg.inv(X), atol=1e-9)
    np.testing.assert_allclose(exp(np.zeros(3 + 3 * k)), np.eye(3 + k))
    np.testing.assert_allclose(log(X), xi, atol=1e-8)
    np.testing.assert_allclose(exp(log(Y)), Y, atol=1e-9)
    lhs = X @ exp(eta) @ inverse(X)
    rhs = exp(np.einsum("nij,nj->ni", adjoint(X), eta))
    np.testing.assert_allclose(lhs, rhs, atol=1e-8)
    np.testing.assert_allclose(adjoint(X @ Y), adjoint(X) @ adjoint(Y), atol=1e-9)


@pytest.mark.parametrize("k", [1, 2])
def test_exp_matches_the_matrix_exponential(k: int) -> None:
    from scipy.linalg import expm

    exp = lie.se3_exp if k == 1 else lie.se23_exp
    for xi in _tangent(8, k):
        A = np.zeros((3 + k, 3 + k))
        A[:3, :3] = lie.hat(xi[:3])
        for i in range(k):
            A[:3, 3 + i] = xi[3 + 3 * i : 6 + 3 * i]
        np.testing.assert_allclose(exp(xi), expm(A), atol=1e-10)


@pytest.mark.parametrize("k", [1, 2, 5])
def test_sek3_wedge_vee_and_the_adjoint_in_the_algebra(k: int) -> None:
    """wedge/vee invert each other, exp is the matrix exponential of the wedge, and
    Ad_X xi^ = X xi^ X^-1, for the generic SE_k(3) functions."""
    from scipy.linalg import expm

    xi, eta = _tangent(16, k), _tangent(16, k)[::-1]
    A = lie.sek3_wedge(xi)
    assert A.shape == (16, 3 + k, 3 + k)
    np.testing.assert_array_equal(lie.sek3_vee(A), xi)
    np.testing.assert_array_equal(A[:, 3:, :], 0.0)
    for one, a in zip(xi[:6], A[:6], strict=True):
        np.testing.assert_allclose(lie.sek3_exp(one), expm(a), atol=1e-10)
    X = lie.sek3_exp(xi)
    lhs = lie.sek3_wedge(np.einsum("nij,nj->ni", lie.sek3_adjoint(X), eta))
    rhs = X @ lie.sek3_wedge(eta) @ lie.sek3_inverse(X)
    np.testing.assert_allclose(lhs, rhs, atol=1e-9)
    if k == 2:  # the generic functions are the SE_2(3) ones
        np.testing.assert_array_equal(lie.sek3_exp(xi), lie.se23_exp(xi))
        np.testing.assert_array_equal(lie.sek3_adjoint(X), lie.se23_adjoint(X))


def test_sek3_rejects_sizes_of_no_group() -> None:
    with pytest.raises(ValueError, match="3 \\+ 3k"):
        lie.sek3_exp(np.zeros(7))
    with pytest.raises(ValueError, match="3 \\+ k"):
        lie.sek3_log(np.eye(3))
