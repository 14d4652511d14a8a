"""Rotations and rigid motions: unit quaternions, SO(3), SE(3) and SE_2(3).

Conventions used everywhere in the project:

- Quaternions are (x, y, z, w), Hamilton products, body to world: ``quat_rotate(q, v)``
  takes a body-frame vector into the world frame.
- Tangent vectors put the rotation first: SE(3) ``xi = (phi, rho)``, (..., 6);
  SE_2(3) ``xi = (phi, nu, rho)`` (rotation, velocity, position), (..., 9), the order of
  the right-invariant EKF of Tong et al. 2024.
- Group elements are matrices: SO(3) (..., 3, 3), SE(3) (..., 4, 4), SE_2(3) (..., 5, 5)
  ``[[R, v, p], [0, 1, 0], [0, 0, 1]]``; SE_k(3) (..., 3 + k, 3 + k) ``[[R, t_1 .. t_k],
  [0, I_k]]`` with tangent ``(phi, t_1, ..., t_k)``, (..., 3 + 3k): the contact-aided
  InEKF's SE_{2+K}(3), whose ``t`` are velocity, position and K contact points.

Every function takes leading batch dimensions. Small angles use series expansions, so
``exp`` and ``log`` are accurate down to zero; ``so3_log`` goes through the quaternion
and so stays accurate up to a half turn.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from numpy.typing import ArrayLike, NDArray

__all__ = [
    "hat",
    "matrix_to_quat",
    "quat_conjugate",
    "quat_from_rotvec",
    "quat_multiply",
    "quat_rotate",
    "quat_to_matrix",
    "quat_to_rotvec",
    "se3_adjoint",
    "se3_exp",
    "se3_inverse",
    "se3_log",
    "se23_adjoint",
    "se23_exp",
    "se23_inverse",
    "se23_log",
    "sek3_adjoint",
    "sek3_exp",
    "sek3_inverse",
    "sek3_log",
    "sek3_vee",
    "sek3_wedge",
    "so3_exp",
    "so3_left_jacobian",
    "so3_left_jacobian_inverse",
    "so3_log",
    "vee",
]

_SMALL = 1e-4  # rad: below it the series (to theta^4) are exact to double precision


def _f64(x: ArrayLike) -> NDArray[np.float64]:
    return np.asarray(x, dtype=np.float64)


# ------------------------------------------------------------------ quaternions


def quat_multiply(a: ArrayLike, b: ArrayLike) -> NDArray[np.float64]:
    """Hamilton product a * b of (..., 4) quaternions in (x, y, z, w) order."""
    ax, ay, az, aw = np.moveaxis(_f64(a), -1, 0)
    bx, by, bz, bw = np.moveaxis(_f64(b), -1, 0)
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def quat_conjugate(q: ArrayLike) -> NDArray[np.float64]:
    """The inverse of unit quaternions (..., 4): the vector part negated."""
    return _f64(_f64(q) * np.array([-1.0, -1.0, -1.0, 1.0]))


def quat_rotate(q: ArrayLike, v: ArrayLike) -> NDArray[np.float64]:
    """Rotate vectors v (..., 3) by unit quaternions q (..., 4) in (x, y, z, w) order."""
    q, v = _f64(q), _f64(v)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    vx, vy, vz = v[..., 0], v[..., 1], v[..., 2]
    # v' = v + w t + xyz x t with t = 2 xyz x v; cross products written out, since
    # np.cross costs more than the arithmetic on the small arrays of the sensor models.
    tx = 2.0 * (y * vz - z * vy)
    ty = 2.0 * (z * vx - x * vz)
    tz = 2.0 * (x * vy - y * vx)
    return np.stack(
        [
            vx + w * tx + y * tz - z * ty,
            vy + w * ty + z * tx - x * tz,
            vz + w * tz + x * ty - y * tx,
        ],
        axis=-1,
    )


def quat_to_matrix(q: ArrayLike) -> NDArray[np.float64]:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4)."""
    q = _f64(q)
    x, y, z, w = np.moveaxis(q, -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def matrix_to_quat(R: ArrayLike) -> NDArray[np.float64]:
    """Unit quaternions (..., 4), w >= 0, of rotation matrices (..., 3, 3).

    Shepperd's method: of the four ways to extract it, the one dividing by the largest
    of |w|, |x|, |y|, |z| is taken, so no entry is lost to cancellation.
    """
    R = _f64(R)
    m = R.reshape(-1, 3, 3)
    tr = np.trace(m, axis1=-2, axis2=-1)
    diag = np.diagonal(m, axis1=-2, axis2=-1)
    choice = np.argmax(np.concatenate([diag, tr[:, None]], axis=-1), axis=-1)
    out = np.empty((len(m), 4))
    for k in range(4):
        sel = choice == k
        if not sel.any():
            continue
        s = m[sel]
        if k == 3:
            w = 0.5 * np.sqrt(1.0 + tr[sel])
            f = 0.25 / w
            out[sel] = np.stack(
                [(s[:, 2, 1] - s[:, 1, 2]) * f, (s[:, 0, 2] - s[:, 2, 0]) * f,
                 (s[:, 1, 0] - s[:, 0, 1]) * f, w], axis=-1,
            )  # fmt: skip
            continue
        i, j, c = k, (k + 1) % 3, (k + 2) % 3
        big = 0.5 * np.sqrt(1.0 + s[:, i, i] - s[:, j, j] - s[:, c, c])
        f = 0.25 / big
        q = np.empty((len(s), 4))
        q[:, i] = big
        q[:, j] = (s[:, j, i] + s[:, i, j]) * f
        q[:, c] = (s[:, c, i] + s[:, i, c]) * f
        q[:, 3] = (s[:, c, j] - s[:, j, c]) * f
        out[sel] = q
    out *= np.where(out[:, 3:] < 0.0, -1.0, 1.0)
    out /= np.linalg.norm(out, axis=-1, keepdims=True)
    return out.reshape(*R.shape[:-2], 4)


def quat_from_rotvec(phi: ArrayLike) -> NDArray[np.float64]:
    """Unit quaternions (..., 4) of rotation vectors (..., 3) (axis times angle, rad)."""
    phi = _f64(phi)
    theta = np.linalg.norm(phi, axis=-1, keepdims=True)
    half = 0.5 * theta
    small = theta < _SMALL
    # sin(theta/2)/theta, with its series below _SMALL
    k = np.where(small, 0.5 - theta**2 / 48.0, np.sin(half) / np.where(small, 1.0, theta))
    return np.concatenate([k * phi, np.cos(half)], axis=-1)


def quat_to_rotvec(q: ArrayLike) -> NDArray[np.float64]:
    """Rotation vectors (..., 3), angle in [0, pi], of unit quaternions (..., 4)."""
    q = _f64(q)
    q = q * np.where(q[..., 3:] < 0.0, -1.0, 1.0)  # the shorter way round
    v, w = q[..., :3], q[..., 3:]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, w)
    small = s < _SMALL
    # angle / s = 2 atan(s / w) / s = (2 / w) (1 - s^2 / (3 w^2)) to second order near zero
    k = np.where(small, 2.0 / w * (1.0 - s**2 / (3.0 * w**2)), angle / np.where(small, 1.0, s))
    return _f64(k * v)


# ------------------------------------------------------------------------ SO(3)


def hat(w: ArrayLike) -> NDArray[np.float64]:
    """Skew-symmetric matrices (..., 3, 3) of vectors (..., 3): hat(a) b = a x b."""
    w = _f64(w)
    z = np.zeros(w.shape[:-1])
    x, y, zz = w[..., 0], w[..., 1], w[..., 2]
    return np.stack(
        [np.stack([z, -zz, y], -1), np.stack([zz, z, -x], -1), np.stack([-y, x, z], -1)], -2
    )


def vee(W: ArrayLike) -> NDArray[np.float64]:
    """The vectors (..., 3) of skew-symmetric matrices (..., 3, 3); inverse of :func:`hat`."""
    W = _f64(W)
    return np.stack([W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]], axis=-1)


def _series(theta: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
    """a = sin(t)/t, b = (1 - cos t)/t^2, c = (t - sin t)/t^3, each (..., 1, 1)."""
    t = theta[..., None, None]
    small = t < _SMALL
    ts = np.where(small, 1.0, t)
    t2 = t * t
    a = np.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, np.sin(ts) / ts)
    b = np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - np.cos(ts)) / ts**2)
    c = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (ts - np.sin(ts)) / ts**3)
    return a, b, c


def so3_exp(phi: ArrayLike) -> NDArray[np.float64]:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) (Rodrigues)."""
    phi = _f64(phi)
    a, b, _ = _series(np.linalg.norm(phi, axis=-1))
    K = hat(phi)
    return np.eye(3) + a * K + b * (K @ K)


def so3_log(R: ArrayLike) -> NDArray[np.float64]:
    """Rotation vectors (..., 3), angle in [0, pi], of rotation matrices (..., 3, 3)."""
    return quat_to_rotvec(matrix_to_quat(R))


def so3_left_jacobian(phi: ArrayLike) -> NDArray[np.float64]:
    """The left Jacobian J(phi) (..., 3, 3) of SO(3): exp(phi + d) ~ exp(J d) exp(phi)."""
    phi = _f64(phi)
    _, b, c = _series(np.linalg.norm(phi, axis=-1))
    K = hat(phi)
    return np.eye(3) + b * K + c * (K @ K)


def so3_left_jacobian_inverse(phi: ArrayLike) -> NDArray[np.float64]:
    """The inverse of :func:`so3_left_jacobian`, (..., 3, 3)."""
    phi = _f64(phi)
    theta = np.linalg.norm(phi, axis=-1)[..., None, None]
    small = theta < _SMALL
    ts = np.where(small, 1.0, theta)
    # (1/t^2) (1 - (t/2) cot(t/2)), series 1/12 + t^2/720 near zero
    d = np.where(
        small,
        1.0 / 12.0 + theta**2 / 720.0,
        (1.0 - 0.5 * ts / np.tan(np.where(small, 1.0, 0.5 * ts))) / ts**2,
    )
    K = hat(phi)
    return _f64(np.eye(3) - 0.5 * K + d * (K @ K))


# ------------------------------------------------------------- SE(3), SE_2(3)


def _sek3_exp(xi: NDArray[np.float64], k: int) -> NDArray[np.float64]:
    """exp of SE_k(3): xi (..., 3 + 3k) = (phi, t_1, ..., t_k) -> (..., 3 + k, 3 + k)."""
    phi = xi[..., :3]
    J = so3_left_jacobian(phi)
    X = np.zeros((*xi.shape[:-1], 3 + k, 3 + k))
    X[..., :3, :3] = so3_exp(phi)
    for i in range(k):
        X[..., :3, 3 + i] = np.einsum("...ij,...j->...i", J, xi[..., 3 + 3 * i : 6 + 3 * i])
        X[..., 3 + i, 3 + i] = 1.0
    return X


def _sek3_log(X: NDArray[np.float64], k: int) -> NDArray[np.float64]:
    phi = so3_log(X[..., :3, :3])
    Jinv = so3_left_jacobian_inverse(phi)
    parts = [phi] + [np.einsum("...ij,...j->...i", Jinv, X[..., :3, 3 + i]) for i in range(k)]
    return np.concatenate(parts, axis=-1)


def _sek3_inverse(X: NDArray[np.float64], k: int) -> NDArray[np.float64]:
    Rt = np.swapaxes(X[..., :3, :3], -1, -2)
    out = np.zeros_like(X)
    out[..., :3, :3] = Rt
    for i in range(k):
        out[..., :3, 3 + i] = -np.einsum("...ij,...j->...i", Rt, X[..., :3, 3 + i])
        out[..., 3 + i, 3 + i] = 1.0
    return out


def _sek3_adjoint(X: NDArray[np.float64], k: int) -> NDArray[np.float64]:
    """Ad_X (..., 3 + 3k, 3 + 3k): X exp(xi) X^-1 = exp(Ad_X xi)."""
    R = X[..., :3, :3]
    n = 3 + 3 * k
    A = np.zeros((*X.shape[:-2], n, n))
    for i in range(k + 1):
        A[..., 3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = R
    for i in range(k):
        A[..., 3 + 3 * i : 6 + 3 * i, :3] = hat(X[..., :3, 3 + i]) @ R
    return A


def se3_exp(xi: ArrayLike) -> NDArray[np.float64]:
    """Rigid motions (..., 4, 4) of twists xi = (phi, rho), (..., 6)."""
    return _sek3_exp(_f64(xi), 1)


def se3_log(T: ArrayLike) -> NDArray[np.float64]:
    """Twists (..., 6) = (phi, rho) of rigid motions (..., 4, 4); inverse of :func:`se3_exp`."""
    return _sek3_log(_f64(T), 1)


def se3_inverse(T: ArrayLike) -> NDArray[np.float64]:
    """Inverses (..., 4, 4) of rigid motions, without a general matrix inverse."""
    return _sek3_inverse(_f64(T), 1)


def se3_adjoint(T: ArrayLike) -> NDArray[np.float64]:
    """Adjoints (..., 6, 6) of rigid motions (..., 4, 4), for twists (phi, rho)."""
    return _sek3_adjoint(_f64(T), 1)


def se23_exp(xi: ArrayLike) -> NDArray[np.float64]:
    """Extended poses (..., 5, 5) of xi = (phi, nu, rho), (..., 9)."""
    return _sek3_exp(_f64(xi), 2)


def se23_log(X: ArrayLike) -> NDArray[np.float64]:
    """xi (..., 9) = (phi, nu, rho) of extended poses (..., 5, 5)."""
    return _sek3_log(_f64(X), 2)


def se23_inverse(X: ArrayLike) -> NDArray[np.float64]:
    """Inverses (..., 5, 5) of extended poses."""
    return _sek3_inverse(_f64(X), 2)


def se23_adjoint(X: ArrayLike) -> NDArray[np.float64]:
    """Adjoints (..., 9, 9) of extended poses (..., 5, 5), for xi = (phi, nu, rho)."""
    return _sek3_adjoint(_f64(X), 2)


# ------------------------------------------------------------------- SE_k(3)


def _k_of_tangent(xi: NDArray[np.float64]) -> int:
    n = int(xi.shape[-1])
    if n < 6 or n % 3:
        raise ValueError(f"an SE_k(3) tangent has 3 + 3k >= 6 entries, got {n}")
    return n // 3 - 1


def _k_of_group(X: NDArray[np.float64]) -> int:
    if X.ndim < 2 or X.shape[-1] != X.shape[-2] or X.shape[-1] < 4:
        raise ValueError(f"an SE_k(3) element is (..., 3 + k, 3 + k), k >= 1; got {X.shape}")
    return int(X.shape[-1]) - 3


def sek3_wedge(xi: ArrayLike) -> NDArray[np.float64]:
    """Lie algebra matrices (..., 3 + k, 3 + k) ``[[hat(phi), t_1 .. t_k], [0, 0]]`` of
    tangents xi = (phi, t_1, ..., t_k), (..., 3 + 3k); k is read off the size."""
    xi = _f64(xi)
    k = _k_of_tangent(xi)
    out = np.zeros((*xi.shape[:-1], 3 + k, 3 + k))
    out[..., :3, :3] = hat(xi[..., :3])
    out[..., :3, 3:] = np.swapaxes(xi[..., 3:].reshape(*xi.shape[:-1], k, 3), -1, -2)
    return out


def sek3_vee(A: ArrayLike) -> NDArray[np.float64]:
    """Tangents (..., 3 + 3k) of Lie algebra matrices (..., 3 + k, 3 + k); inverse of
    :func:`sek3_wedge`."""
    A = _f64(A)
    k = _k_of_group(A)
    t = np.swapaxes(A[..., :3, 3:], -1, -2).reshape(*A.shape[:-2], 3 * k)
    return np.concatenate([vee(A[..., :3, :3]), t], axis=-1)


def sek3_exp(xi: ArrayLike) -> NDArray[np.float64]:
    """SE_k(3) elements (..., 3 + k, 3 + k) of tangents (..., 3 + 3k)."""
    xi = _f64(xi)
    return _sek3_exp(xi, _k_of_tangent(xi))


def sek3_log(X: ArrayLike) -> NDArray[np.float64]:
    """Tangents (..., 3 + 3k) of SE_k(3) elements (..., 3 + k, 3 + k); inverse of
    :func:`sek3_exp` for rotations below a half turn."""
    X = _f64(X)
    return _sek3_log(X, _k_of_group(X))


def sek3_inverse(X: ArrayLike) -> NDArray[np.float64]:
    """Inverses (..., 3 + k, 3 + k) of SE_k(3) elements, without a general inverse."""
    X = _f64(X)
    return _sek3_inverse(X, _k_of_group(X))


def sek3_adjoint(X: ArrayLike) -> NDArray[np.float64]:
    """Adjoints (..., 3 + 3k, 3 + 3k) of SE_k(3) elements: ``X wedge(xi) X^-1 =
    wedge(Ad_X xi)``."""
    X = _f64(X)
    return _sek3_adjoint(X, _k_of_group(X))
