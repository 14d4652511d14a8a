"""The contact-aided right-invariant EKF of Tong et al. 2024 section IV (Hartley et al., IJRR
2020; the DRIFT framework), with IMU biases: its filter core.

State. ``X`` in SE_{2+K}(3), (5 + K, 5 + K)::

    X = [[R, v, p, d_1 .. d_K],
         [0, I_{2+K}         ]]

R (3, 3) rotates the body (IMU) frame into the world frame (z up), v (3,) and p (3,) are
the body frame's velocity (m/s) and position (m) in the world, d_k (3,) the world
position (m) of the k-th endcap in contact, in the order the contacts were augmented
(:attr:`RightInvariantEkf.contact_nodes` names their nodes). The IMU biases b_g (rad/s)
and b_a (m/s^2) sit outside the group, as in Hartley's and DRIFT's filters.

Error and covariance. The right-invariant error is ``eta = X_hat X^-1``; the filter
writes the truth as ``X = exp(eps) X_hat`` (so ``eta = exp(-eps)``; exp is the SE_k(3)
exponential of :mod:`tensegrity_gym.model.lie`) and ``b = b_hat + eps_b``, and carries
the covariance P of ``eps ~ N(0, P)``, ordered::

    [rotation 0:3, velocity 3:6, position 6:9, d_1 .. d_K 9:9+3K, b_g, b_a]   (9 + 3K + 6)

The rotation part is in the world frame, so its z entry is the heading (yaw). A
correction ``delta`` is applied as ``X <- exp(delta_X) X_hat``, ``b <- b_hat + delta_b``.

Propagation (eq. 5-8). Mean by the IMU kinematics over dt with the rotation at the start
of the step; covariance ``P <- Phi P Phi^T + Q_d`` with ``Phi = exp(A dt)`` of the
linearised error dynamics ``d eps/dt = A eps + Ad w``, A state-independent except its
bias columns, which are ``-Ad_X_hat`` (gyro and accelerometer columns) taken at the
estimate at the start of the step, and ``Q_d = Phi Ad Q Ad^T Phi^T dt`` (the
approximation of Hartley's and DRIFT's code), Ad = diag(Ad_X_hat, I_6), Q = diag(gyro^2,
accel^2, 0, contact^2 per contact, gyro_bias^2, accel_bias^2) of :class:`InekfNoise`.
A's state part is nilpotent (its cube is zero), so Phi is exact in closed form here.

Correction (eq. 11-14). The forward kinematics measure y_k = R^T (d_k - p) + n_k, body
frame, n_k ~ N(0, cov_k): the left-invariant observation ``Y = X^-1 b``. Its innovation
``z_k = R_hat y_k + p_hat - d_hat_k`` is ``H eps + R_hat n_k`` to first order, with the
constant ``H_k = [0, 0, -I, .., I at d_k, .., 0, 0]`` and ``N_k = R_hat cov_k R_hat^T``.
The gain is the ordinary ``K = P H^T S^-1``, the covariance update the Joseph form.

The kernels are numba-compiled (``cache=True``): a 24 x 24 covariance is too small for
numpy's per-call overhead (measured in :mod:`agents.benchmarks.inekf`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING

import numba
import numpy as np

from tensegrity_gym.model.checks import all_finite

if TYPE_CHECKING:
    from collections.abc import Sequence

    from numpy.typing import ArrayLike, NDArray

__all__ = ["CHI2_3DOF_999", "CorrectionResult", "InekfNoise", "RightInvariantEkf"]

CHI2_3DOF_999 = 16.266236196238129
"""scipy.stats.chi2.ppf(0.999, 3): the default gate on a contact's NIS (3 dof)."""

_SMALL = 1e-4  # rad: below it the series of exp and J (to theta^4) are exact in doubles
_BASE = 15  # the covariance's size without contacts: rotation, velocity, position, biases
_POSE_COLUMNS = np.array([0, 1, 2, 6, 7, 8])  # rotation and position in P
_POSE_ROWS = _POSE_COLUMNS[:, None]


@dataclass(frozen=True)
class InekfNoise:
    """Continuous-time noise densities (standard deviation per sqrt(Hz)); defaults from
    Tong et al. 2024 table I.

    A sensor sampled every dt seconds has a per-sample standard deviation of the density
    over sqrt(dt); a random walk grows by the density times sqrt(dt) in dt.
    """

    gyro: float = 0.002
    """rad/s/sqrt(Hz): angular rate white noise."""
    accel: float = 0.043
    """m/s^2/sqrt(Hz): specific force white noise."""
    gyro_bias: float = 0.001
    """rad/s^2/sqrt(Hz): gyro bias random walk."""
    accel_bias: float = 0.001
    """m/s^3/sqrt(Hz): accelerometer bias random walk."""
    contact_velocity: float = 0.05
    """m/s/sqrt(Hz): velocity noise of an endcap in contact (slip), body frame."""

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            number = isinstance(value, (int, float)) and not isinstance(value, bool)
            if not (number and math.isfinite(value) and value >= 0):
                raise ValueError(f"InekfNoise.{f.name} must be a number >= 0, got {value!r}")

    def variances(self) -> NDArray[np.float64]:
        """(5,): squared densities, in the kernels' order: gyro, accel, contact
        velocity, gyro bias, accel bias."""
        d = np.array(
            [self.gyro, self.accel, self.contact_velocity, self.gyro_bias, self.accel_bias]
        )
        return np.asarray(d * d, dtype=np.float64)


@dataclass(frozen=True)
class CorrectionResult:
    """What one contact correction did."""

    nodes: tuple[int, ...]
    """The nodes offered, in the order given."""
    nis: NDArray[np.float64]
    """(K',): each node's normalised innovation squared on its own (chi-square, 3 dof),
    against the prior: what the gate tested."""
    accepted: NDArray[np.bool_]
    """(K',): nodes used; gated nodes are False and did not touch the state."""
    nis_total: float
    """NIS of the accepted nodes all at once (chi-square, 3 x accepted dof); 0 if none."""

    @property
    def n_rejected(self) -> int:
        return int(len(self.nodes) - np.count_nonzero(self.accepted))


# ---------------------------------------------------------------- numba kernels
#
# Scalar loops throughout. An array expression inside a kernel allocates a temporary,
# and at these sizes (3-vectors, a 24 x 24 covariance) the allocations, not the
# arithmetic, were what cost: a first version written with them spent twice as long
# in the correction kernel. Slice assignments and fancy indexing also compile slowly
# (_augment took 8 s to compile with them, 1 s with loops).


@numba.njit(cache=True, nogil=True)
def _exp_so3(
    p0: float, p1: float, p2: float, R: NDArray[np.float64], J: NDArray[np.float64]
) -> None:
    """R (3, 3) <- exp(phi), J (3, 3) <- the left Jacobian J_l(phi), phi = (p0, p1, p2):
    I + a K + b K^2 and I + b K + c K^2 with K = hat(phi), K^2 = phi phi^T - |phi|^2 I."""
    t2 = p0 * p0 + p1 * p1 + p2 * p2
    t = math.sqrt(t2)
    if t < _SMALL:
        a = 1.0 - t2 / 6.0 + t2 * t2 / 120.0
        b = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
        c = 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0
    else:
        s = math.sin(t)
        a, b, c = s / t, (1.0 - math.cos(t)) / t2, (t - s) / (t2 * t)
    ph = (p0, p1, p2)
    K = ((0.0, -p2, p1), (p2, 0.0, -p0), (-p1, p0, 0.0))
    for i in range(3):
        for j in range(3):
            eye = 1.0 if i == j else 0.0
            k2 = ph[i] * ph[j] - eye * t2
            R[i, j] = eye + a * K[i][j] + b * k2
            J[i, j] = eye + b * K[i][j] + c * k2


@numba.njit(cache=True, nogil=True)
def _cross_r(
    w0: float, w1: float, w2: float, T: NDArray[np.float64], F: NDArray[np.float64], r: int
) -> None:
    """F[r:r+3, 0:3] <- -hat(w) R, R = T[:, :3]: a gyro column block of -Ad_X."""
    for c in range(3):
        F[r, c] = w2 * T[1, c] - w1 * T[2, c]
        F[r + 1, c] = w0 * T[2, c] - w2 * T[0, c]
        F[r + 2, c] = w1 * T[0, c] - w0 * T[1, c]


@numba.njit(cache=True, nogil=True)
def _bias_columns(T: NDArray[np.float64], g: NDArray[np.float64], dt: float) -> NDArray[np.float64]:
    """Phi's bias columns (9 + 3K, 6): (I dt + A_s dt^2/2 + A_s^2 dt^3/6) B, B = -Ad_X's
    gyro and accelerometer columns, A_s the state part of A (v' = g x rot, p' = v):
    blocks -R dt; -hat(v dt + g dt^2/2) R, -R dt; -hat(p dt + v dt^2/2 + g dt^3/6) R,
    -R dt^2/2; -hat(d_k dt) R."""
    nc = T.shape[1]
    F = np.zeros((3 * (nc - 2), 6))
    h, h3 = 0.5 * dt * dt, dt * dt * dt / 6.0
    for i in range(3):
        for c in range(3):
            F[i, c] = -T[i, c] * dt
            F[3 + i, 3 + c] = -T[i, c] * dt
            F[6 + i, 3 + c] = -T[i, c] * h
    v0, v1, v2 = T[0, 3], T[1, 3], T[2, 3]
    _cross_r(v0 * dt + g[0] * h, v1 * dt + g[1] * h, v2 * dt + g[2] * h, T, F, 3)
    _cross_r(
        T[0, 4] * dt + v0 * h + g[0] * h3, T[1, 4] * dt + v1 * h + g[1] * h3,
        T[2, 4] * dt + v2 * h + g[2] * h3, T, F, 6,
    )  # fmt: skip
    for k in range(5, nc):
        _cross_r(T[0, k] * dt, T[1, k] * dt, T[2, k] * dt, T, F, 3 * (k - 2))
    return F


@numba.njit(cache=True, nogil=True)
def _phi_rows(
    M: NDArray[np.float64], F: NDArray[np.float64], g: NDArray[np.float64], dt: float
) -> None:
    """M <- Phi M in place, Phi = I + [v <- hat(g) dt rot; p <- hat(g) dt^2/2 rot + dt v;
    state <- F biases]: row operations, since Phi is the identity but for these."""
    ns, n = F.shape[0], M.shape[1]
    h = 0.5 * dt * dt
    for c in range(n):
        r0, r1, r2 = M[0, c], M[1, c], M[2, c]
        gx0, gx1, gx2 = g[1] * r2 - g[2] * r1, g[2] * r0 - g[0] * r2, g[0] * r1 - g[1] * r0
        # position first: it reads the old velocity rows
        M[6, c] += h * gx0 + dt * M[3, c]
        M[7, c] += h * gx1 + dt * M[4, c]
        M[8, c] += h * gx2 + dt * M[5, c]
        M[3, c] += dt * gx0
        M[4, c] += dt * gx1
        M[5, c] += dt * gx2
    for i in range(ns):
        for j in range(6):
            f = F[i, j]
            if f != 0.0:
                for c in range(n):
                    M[i, c] += f * M[ns + j, c]


@numba.njit(cache=True, nogil=True)
def _add_process_noise(
    T: NDArray[np.float64], P: NDArray[np.float64], dt: float, q: NDArray[np.float64]
) -> None:
    """P += Ad Q Ad^T dt. Ad's gyro columns are L R with L = [I; hat(v); hat(p);
    hat(d_k)], so the gyro term is q_g L L^T; the others are isotropic, so R drops out."""
    nc = T.shape[1]
    ns = 3 * (nc - 2)
    L = np.zeros((ns, 3))
    L[0, 0] = L[1, 1] = L[2, 2] = 1.0
    for k in range(3, nc):
        r = 3 * (k - 2)
        L[r, 1], L[r, 2], L[r + 1, 2] = -T[2, k], T[1, k], -T[0, k]
        L[r + 1, 0], L[r + 2, 0], L[r + 2, 1] = T[2, k], -T[1, k], T[0, k]
    qg = q[0] * dt
    for i in range(ns):
        for j in range(ns):
            P[i, j] += qg * (L[i, 0] * L[j, 0] + L[i, 1] * L[j, 1] + L[i, 2] * L[j, 2])
    for i in range(3):
        P[3 + i, 3 + i] += q[1] * dt
        P[ns + i, ns + i] += q[3] * dt
        P[ns + 3 + i, ns + 3 + i] += q[4] * dt
    for i in range(9, ns):
        P[i, i] += q[2] * dt


@numba.njit(cache=True, nogil=True)
def _symmetrise_into(A: NDArray[np.float64], out: NDArray[np.float64]) -> None:
    """out <- (A + A^T) / 2; A and out may be the same array."""
    n = A.shape[0]
    for i in range(n):
        out[i, i] = A[i, i]
        for j in range(i + 1, n):
            s = 0.5 * (A[i, j] + A[j, i])
            out[i, j] = s
            out[j, i] = s


@numba.njit(cache=True, nogil=True)
def _propagate(
    T: NDArray[np.float64],
    b: NDArray[np.float64],
    P: NDArray[np.float64],
    gyro: NDArray[np.float64],
    accel: NDArray[np.float64],
    dt: float,
    g: NDArray[np.float64],
    q: NDArray[np.float64],
) -> None:
    """One IMU step of dt seconds on T (3, 5 + K) = [R | v | p | d_k], b (6,) and P
    (n, n), in place. P <- Phi (P + Ad Q Ad^T dt) Phi^T, all at the start estimate."""
    _add_process_noise(T, P, dt, q)
    F = _bias_columns(T, g, dt)
    _phi_rows(P, F, g, dt)
    M = P.T.copy()  # (Phi P)^T = P Phi^T, P symmetric: Phi M = Phi P Phi^T
    _phi_rows(M, F, g, dt)
    _symmetrise_into(M, P)
    f0, f1, f2 = accel[0] - b[3], accel[1] - b[4], accel[2] - b[5]
    for i in range(3):
        acc = T[i, 0] * f0 + T[i, 1] * f1 + T[i, 2] * f2 + g[i]
        T[i, 4] += T[i, 3] * dt + 0.5 * dt * dt * acc
        T[i, 3] += acc * dt
    dR = np.empty((2, 3, 3))  # exp, and a Jacobian not needed here
    _exp_so3((gyro[0] - b[0]) * dt, (gyro[1] - b[1]) * dt, (gyro[2] - b[2]) * dt, dR[0], dR[1])
    for i in range(3):  # R <- R dR, row by row
        r0, r1, r2 = T[i, 0], T[i, 1], T[i, 2]
        for j in range(3):
            T[i, j] = r0 * dR[0, 0, j] + r1 * dR[0, 1, j] + r2 * dR[0, 2, j]


@numba.njit(cache=True, nogil=True)
def _propagate_reading(
    T: NDArray[np.float64],
    b: NDArray[np.float64],
    P: NDArray[np.float64],
    gyro: NDArray[np.float64],
    accel: NDArray[np.float64],
    dt: float,
    g: NDArray[np.float64],
    q: NDArray[np.float64],
    slip: NDArray[np.float64],
    velocity_variance: float,
    roll_radii: NDArray[np.float64],
    rotation_variance: float,
) -> None:
    """:func:`_propagate` with what an estimator adds per reading, in one call: the slip
    variance q[2] from the angular rate (slip: density at rest, growth per rad/s, cap;
    no growth keeps q[2]), ``velocity_variance`` on the velocity and
    ``rotation_variance`` on the rotation, and each contact's
    point rolled by ``roll_radii[k]`` m times the turn about body z over dt, along the
    ground: d_k += (R e_z) (turn r_k) x e_z, with R after the step."""
    if slip[1] > 0.0:
        w0, w1, w2 = gyro[0] - b[0], gyro[1] - b[1], gyro[2] - b[2]
        density = min(slip[0] + slip[1] * math.sqrt(w0 * w0 + w1 * w1 + w2 * w2), slip[2])
        q[2] = density * density
    _propagate(T, b, P, gyro, accel, dt, g, q)
    for i in range(3):
        P[i, i] += rotation_variance
        P[3 + i, 3 + i] += velocity_variance
    spin = (gyro[2] - b[2]) * dt
    for k in range(roll_radii.shape[0]):
        if roll_radii[k] != 0.0:
            arc = spin * roll_radii[k]
            T[0, 5 + k] += T[1, 2] * arc
            T[1, 5 + k] -= T[0, 2] * arc


@numba.njit(cache=True, nogil=True)
def _cholesky(A: NDArray[np.float64]) -> bool:
    """A <- its lower Cholesky factor, in place (upper triangle left as is); False if a
    pivot is not positive (A not positive definite)."""
    n = A.shape[0]
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= A[j, k] * A[j, k]
        if not s > 0.0:
            return False
        A[j, j] = math.sqrt(s)
        for i in range(j + 1, n):
            t = A[i, j]
            for k in range(j):
                t -= A[i, k] * A[j, k]
            A[i, j] = t / A[j, j]
    return True


@numba.njit(cache=True, nogil=True)
def _forward(L: NDArray[np.float64], B: NDArray[np.float64]) -> None:
    """B (m, c) <- L^-1 B in place, L (m, m) lower; row-wise, along B's contiguous rows."""
    m, c = B.shape
    for i in range(m):
        for k in range(i):
            f = L[i, k]
            for j in range(c):
                B[i, j] -= f * B[k, j]
        f = 1.0 / L[i, i]
        for j in range(c):
            B[i, j] *= f


@numba.njit(cache=True, nogil=True)
def _backward(L: NDArray[np.float64], B: NDArray[np.float64]) -> None:
    """B (m, c) <- L^-T B in place, L (m, m) lower."""
    m, c = B.shape
    for i in range(m - 1, -1, -1):
        for k in range(i + 1, m):
            f = L[k, i]
            for j in range(c):
                B[i, j] -= f * B[k, j]
        f = 1.0 / L[i, i]
        for j in range(c):
            B[i, j] *= f


@numba.njit(cache=True, nogil=True)
def _rotate_cov(T: NDArray[np.float64], cov: NDArray[np.float64], out: NDArray[np.float64]) -> None:
    """out (3, 3) <- R cov R^T, R = T[:, :3]: a body-frame covariance in the world frame;
    exactly symmetric (the upper triangle mirrored) for the symmetric P it joins."""
    for r in range(3):
        for q in range(r, 3):
            s = 0.0
            for k in range(3):
                for e in range(3):
                    s += T[r, k] * cov[k, e] * T[q, e]
            out[r, q] = s
            out[q, r] = s


@numba.njit(cache=True, nogil=True)
def _innovations(
    T: NDArray[np.float64],
    P: NDArray[np.float64],
    slots: NDArray[np.int64],
    y: NDArray[np.float64],
    cov: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """z (3m,), Ut = H P (3m, n), S = H P H^T + N (3m, 3m), N (m, 3, 3) of the nodes in
    ``slots`` (m,), with H's rows -I at position and I at the node's contact."""
    m, n = slots.shape[0], P.shape[0]
    z, Ut = np.empty(3 * m), np.empty((3 * m, n))
    S, N = np.empty((3 * m, 3 * m)), np.empty((m, 3, 3))
    for j in range(m):
        o, col = 9 + 3 * slots[j], 5 + slots[j]
        _rotate_cov(T, cov[j], N[j])
        for r in range(3):
            z[3 * j + r] = (T[r, 0] * y[j, 0] + T[r, 1] * y[j, 1] + T[r, 2] * y[j, 2]
                            + T[r, 4] - T[r, col])  # fmt: skip
            for c in range(n):  # P symmetric: its rows are its columns
                Ut[3 * j + r, c] = P[o + r, c] - P[6 + r, c]
    for i in range(m):
        o = 9 + 3 * slots[i]
        for a in range(3):
            for c in range(3 * m):
                S[c, 3 * i + a] = Ut[c, o + a] - Ut[c, 6 + a]
            for e in range(3):
                S[3 * i + e, 3 * i + a] += N[i, e, a]
    return z, Ut, S, N


@numba.njit(cache=True, nogil=True)
def _nis3(S: NDArray[np.float64], o: int, z: NDArray[np.float64]) -> float:
    """z[o:o+3]^T S[o:o+3, o:o+3]^-1 z[o:o+3] by a 3 x 3 Cholesky; -1 if the block is
    not positive definite."""
    d0 = S[o, o]
    if not d0 > 0.0:
        return -1.0
    l00 = math.sqrt(d0)
    l10, l20 = S[o + 1, o] / l00, S[o + 2, o] / l00
    d1 = S[o + 1, o + 1] - l10 * l10
    if not d1 > 0.0:
        return -1.0
    l11 = math.sqrt(d1)
    l21 = (S[o + 2, o + 1] - l20 * l10) / l11
    d2 = S[o + 2, o + 2] - l20 * l20 - l21 * l21
    if not d2 > 0.0:
        return -1.0
    u0 = z[o] / l00
    u1 = (z[o + 1] - l10 * u0) / l11
    u2 = (z[o + 2] - l20 * u0 - l21 * u1) / math.sqrt(d2)
    return float(u0 * u0 + u1 * u1 + u2 * u2)


@numba.njit(cache=True, nogil=True)
def _joseph(
    P: NDArray[np.float64],
    Kt: NDArray[np.float64],
    Ut: NDArray[np.float64],
    N: NDArray[np.float64],
    cols: NDArray[np.int64],
) -> None:
    """P <- (I - K H) P (I - K H)^T + K N K^T, in place and symmetrised. Kt = K^T
    (3m, n), Ut = H P (3m, n), N (m, 3, 3), cols (m,) the contacts' first columns."""
    m3, n = Kt.shape
    M = P.copy()
    for i in range(n):  # M = P - K (H P)
        for r in range(m3):
            k = Kt[r, i]
            for c in range(n):
                M[i, c] -= k * Ut[r, c]
    E = np.empty((n, m3))  # M H^T - K N
    for i in range(n):
        for j in range(cols.shape[0]):
            for a in range(3):
                s = M[i, cols[j] + a] - M[i, 6 + a]
                for e in range(3):
                    s -= Kt[3 * j + e, i] * N[j, e, a]
                E[i, 3 * j + a] = s
    for i in range(n):  # M (I - K H)^T + K N K^T = M - E K^T
        for r in range(m3):
            f = E[i, r]
            for c in range(n):
                M[i, c] -= f * Kt[r, c]
    _symmetrise_into(M, P)


@numba.njit(cache=True, nogil=True)
def _apply(
    T: NDArray[np.float64], b: NDArray[np.float64], Kt: NDArray[np.float64], z: NDArray[np.float64]
) -> None:
    """X <- exp(delta_X) X, b <- b + delta_b with delta = K z: exp(delta_X) = [[dR, J
    delta_t]], so R becomes dR R and each other column t of X's top rows dR t + J delta_t."""
    m3, n = Kt.shape
    nc = T.shape[1]
    delta = np.zeros(n)
    for r in range(m3):
        for c in range(n):
            delta[c] += Kt[r, c] * z[r]
    dR = np.empty((2, 3, 3))
    _exp_so3(delta[0], delta[1], delta[2], dR[0], dR[1])
    for c in range(nc):
        t0, t1, t2 = T[0, c], T[1, c], T[2, c]
        for i in range(3):
            T[i, c] = dR[0, i, 0] * t0 + dR[0, i, 1] * t1 + dR[0, i, 2] * t2
            if c >= 3:
                o = 3 * (c - 2)
                T[i, c] += (
                    dR[1, i, 0] * delta[o] + dR[1, i, 1] * delta[o + 1] + dR[1, i, 2] * delta[o + 2]
                )
    for i in range(6):
        b[i] += delta[n - 6 + i]


@numba.njit(cache=True, nogil=True)
def _accepted_rows(
    z: NDArray[np.float64],
    Ut: NDArray[np.float64],
    S: NDArray[np.float64],
    N: NDArray[np.float64],
    slots: NDArray[np.int64],
    accepted: NDArray[np.bool_],
) -> tuple[
    NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64],
    NDArray[np.int64],
]:  # fmt: skip
    """What :func:`_innovations` gave, kept to the accepted nodes: z (3a,), H P (3a, n),
    S (3a, 3a), N (a, 3, 3), and their contacts' first rows of P (a,). Loops, not fancy
    indexing: numba compiles these in a fraction of the time."""
    keep = np.empty(accepted.shape[0], dtype=np.int64)
    ma = 0
    for j in range(accepted.shape[0]):
        if accepted[j]:
            keep[ma] = j
            ma += 1
    n = Ut.shape[1]
    za, Ua, Sa = np.empty(3 * ma), np.empty((3 * ma, n)), np.empty((3 * ma, 3 * ma))
    Na, cols = np.empty((ma, 3, 3)), np.empty(ma, dtype=np.int64)
    for jj in range(ma):
        j = keep[jj]
        cols[jj] = 9 + 3 * slots[j]
        for a in range(3):
            r, rr = 3 * j + a, 3 * jj + a
            za[rr] = z[r]
            for e in range(3):
                Na[jj, a, e] = N[j, a, e]
            for c in range(n):
                Ua[rr, c] = Ut[r, c]
            for kk in range(ma):
                for e in range(3):
                    Sa[rr, 3 * kk + e] = S[r, 3 * keep[kk] + e]
    return za, Ua, Sa, Na, cols


@numba.njit(cache=True, nogil=True)
def _correct(
    T: NDArray[np.float64],
    b: NDArray[np.float64],
    P: NDArray[np.float64],
    slots: NDArray[np.int64],
    y: NDArray[np.float64],
    cov: NDArray[np.float64],
    gate: float,
    nis: NDArray[np.float64],
    accepted: NDArray[np.bool_],
) -> float:
    """Gate each node, then update T, b, P in place with the accepted ones at once.
    Returns their joint NIS, or -1 if an innovation covariance is not positive
    definite (nothing is then changed)."""
    z, Ut, S, N = _innovations(T, P, slots, y, cov)
    for j in range(slots.shape[0]):
        nis[j] = _nis3(S, 3 * j, z)
        if nis[j] < 0.0:
            return -1.0
        accepted[j] = nis[j] <= gate
    za, Ua, L, Na, cols = _accepted_rows(z, Ut, S, N, slots, accepted)
    m3 = za.shape[0]
    if m3 == 0:
        return 0.0
    if not _cholesky(L):
        return -1.0
    Kt = Ua.copy()
    _forward(L, Kt)
    _backward(L, Kt)  # K^T = S^-1 H P
    _joseph(P, Kt, Ua, Na, cols)
    _apply(T, b, Kt, za)
    w = np.empty((m3, 1))
    for r in range(m3):
        w[r, 0] = za[r]
    _forward(L, w)
    total = 0.0
    for r in range(m3):
        total += w[r, 0] * w[r, 0]
    return total


@numba.njit(cache=True, nogil=True)
def _augment(
    T: NDArray[np.float64],
    P: NDArray[np.float64],
    y: NDArray[np.float64],
    cov: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(T, P) with one contact more, at d = p + R y (eq. 9): P <- F P F^T + G cov G^T,
    F copying the position's rows and columns into the new contact's (its error starts
    as the position's), just before the biases; G = [0; R; 0]."""
    nc, n = T.shape[1], P.shape[0]
    ns = n - 6
    T2 = np.empty((3, nc + 1))
    for r in range(3):
        for c in range(nc):
            T2[r, c] = T[r, c]
    src = np.empty(n + 3, dtype=np.int64)  # the row of P each row of the new P copies
    for i in range(n + 3):
        src[i] = i if i < ns else (6 + i - ns if i < ns + 3 else i - 3)
    P2 = np.empty((n + 3, n + 3))
    for i in range(n + 3):
        for j in range(n + 3):
            P2[i, j] = P[src[i], src[j]]
    C = np.empty((3, 3))
    _rotate_cov(T, cov, C)
    for r in range(3):
        T2[r, nc] = T[r, 4] + T[r, 0] * y[0] + T[r, 1] * y[1] + T[r, 2] * y[2]
        for q in range(3):
            P2[ns + r, ns + q] += C[r, q]
    return T2, P2


@numba.njit(cache=True, nogil=True)
def _marginalise(
    T: NDArray[np.float64], P: NDArray[np.float64], k: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(T, P) without the k-th contact: its column of T, its rows and columns of P."""
    nc, n = T.shape[1], P.shape[0]
    o = 9 + 3 * k
    T2 = np.empty((3, nc - 1))
    for r in range(3):
        for c in range(nc - 1):
            T2[r, c] = T[r, c if c < 5 + k else c + 1]
    P2 = np.empty((n - 3, n - 3))
    for i in range(n - 3):
        si = i if i < o else i + 3
        for j in range(n - 3):
            P2[i, j] = P[si, j if j < o else j + 3]
    return T2, P2


# ------------------------------------------------------------------ the filter


def _writable(x: ArrayLike) -> NDArray[np.float64]:
    """x as a C-contiguous, writable float64 array: a read-only one (a broadcast view)
    would make numba compile the kernels once more, for that type."""
    out = np.ascontiguousarray(x, dtype=np.float64)
    return out if out.flags.writeable else out.copy()


def _vector(x: ArrayLike, name: str, n: int = 3) -> NDArray[np.float64]:
    out = _writable(x)
    if out.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {out.shape}")
    return out


class RightInvariantEkf:
    """The contact-aided right-invariant EKF with IMU biases; see the module docstring
    for the state, the error convention and the equations.

    Until :meth:`reset` the robot sits at the origin, at rest, unbiased, with a zero
    covariance.
    """

    def __init__(self, noise: InekfNoise | None = None, gravity: ArrayLike = (0.0, 0.0, -9.81)):
        self.noise = noise if noise is not None else InekfNoise()
        self.gravity = _vector(gravity, "gravity")
        """(3,) m/s^2, world frame (z up)."""
        if not np.all(np.isfinite(self.gravity)):
            raise ValueError(f"gravity must be finite, got {self.gravity}")
        self._q = self.noise.variances()
        self._T = np.zeros((3, 5))  # [R | v | p | d_1 .. d_K]: X's top rows
        self._T[:, :3] = np.eye(3)
        self._b = np.zeros(6)  # [b_g, b_a]
        self._P = np.zeros((_BASE, _BASE))
        self._nodes: list[int] = []

    def reset(
        self,
        R: ArrayLike,
        v: ArrayLike,
        p: ArrayLike,
        b_g: ArrayLike,
        b_a: ArrayLike,
        P0: ArrayLike,
    ) -> None:
        """Start from R (3, 3), v, p, b_g, b_a (3,) each and P0 (15, 15) ordered
        [rotation, velocity, position, b_g, b_a]; no contacts."""
        R = np.asarray(R, dtype=np.float64)
        if R.shape != (3, 3) or not np.allclose(R.T @ R, np.eye(3), atol=1e-6):
            raise ValueError("R must be a (3, 3) rotation matrix (orthonormal)")
        if np.linalg.det(R) <= 0:
            raise ValueError("R must be a proper rotation (det +1), not a reflection")
        P0 = np.asarray(P0, dtype=np.float64)
        if P0.shape != (_BASE, _BASE) or not np.all(np.isfinite(P0)):
            raise ValueError(f"P0 must be a finite ({_BASE}, {_BASE}) covariance")
        vectors = [_vector(x, name) for x, name in ((v, "v"), (p, "p"), (b_g, "b_g"), (b_a, "b_a"))]
        self._T = np.column_stack([R, *vectors[:2]])
        self._b = np.concatenate(vectors[2:])
        self._P = 0.5 * (P0 + P0.T)
        self._nodes = []

    def set_gyro_bias(self, b_g: ArrayLike) -> None:
        """Replace the gyro bias estimate (3,) rad/s, e.g. by a rest phase's mean rate;
        the covariance is left as it is."""
        self._b[:3] = _vector(b_g, "b_g")

    def propagate(self, gyro: ArrayLike, accel: ArrayLike, dt: float) -> None:
        """Advance by dt seconds with the IMU's angular rate ``gyro`` (3,) rad/s and
        specific force ``accel`` (3,) m/s^2, body frame, held over the step."""
        if not (dt > 0.0 and math.isfinite(dt)):
            raise ValueError(f"dt must be a finite number of seconds > 0, got {dt!r}")
        _propagate(
            self._T, self._b, self._P, _vector(gyro, "gyro"), _vector(accel, "accel"),
            float(dt), self.gravity, self._q,
        )  # fmt: skip

    def propagate_reading(
        self,
        gyro: NDArray[np.float64],
        accel: NDArray[np.float64],
        dt: float,
        slip: NDArray[np.float64],
        velocity_variance: float,
        roll_radii: NDArray[np.float64],
        rotation_variance: float = 0.0,
    ) -> None:
        """:meth:`propagate` with an estimator's per-reading additions, in one compiled
        call (the estimator's hot path: arrays are taken as they are, float64).

        Args:
            gyro, accel: (3,) the reading, as in :meth:`propagate`.
            dt: s.
            slip: (3,) the contacts' slip density (m/s/sqrt(Hz)) at rest, its growth per
                rad/s of angular rate (less the gyro bias) and its cap; a growth of 0
                keeps the density as it is (:meth:`set_contact_velocity_noise`).
            velocity_variance: (m/s)^2 per axis added to the velocity's error after the
                step (:meth:`add_velocity_variance`).
            roll_radii: (K,) m, per contact in state order: an endcap of that radius
                rolling with the body's turn about its z axis (0: not rolling); its point
                moves by (R e_z) (turn r) x e_z (:meth:`move_contact`).
            rotation_variance: rad^2 per axis added to the rotation's error after the
                step (a turn the gyro did not measure: a reading at its full scale).
        """
        if not (dt > 0.0 and math.isfinite(dt)):
            raise ValueError(f"dt must be a finite number of seconds > 0, got {dt!r}")
        if roll_radii.shape != (len(self._nodes),):
            raise ValueError(
                f"roll_radii must have shape ({len(self._nodes)},), got {roll_radii.shape}"
            )
        for variance in (velocity_variance, rotation_variance):
            if not (variance >= 0.0 and math.isfinite(variance)):
                raise ValueError(f"a variance must be finite and >= 0, got {variance!r}")
        _propagate_reading(
            self._T, self._b, self._P, gyro, accel, float(dt), self.gravity, self._q, slip,
            float(velocity_variance), roll_radii, float(rotation_variance),
        )  # fmt: skip

    def augment(self, node: int, p_body: ArrayLike, cov_body: ArrayLike) -> None:
        """Add node's contact at d = p + R p_body (p_body (3,) m, body frame), its error
        that of the position plus R cov_body R^T (cov_body (3, 3) m^2), eq. 9."""
        node = int(node)
        if node in self._nodes:
            raise ValueError(f"node {node} is already in contact")
        cov = _writable(cov_body)
        if cov.shape != (3, 3):
            raise ValueError(f"cov_body must have shape (3, 3), got {cov.shape}")
        self._T, self._P = _augment(self._T, self._P, _vector(p_body, "p_body"), cov)
        self._nodes.append(node)

    def marginalise(self, node: int) -> None:
        """Drop node's contact, its rows and columns of P (eq. 10)."""
        k = self._slot(node)
        self._T, self._P = _marginalise(self._T, self._P, k)
        del self._nodes[k]

    def move_contact(self, node: int, shift: ArrayLike) -> None:
        """Move node's contact point by ``shift`` (3,) m, world frame: a known motion of
        the endcap on the ground (its sphere rolling), not a measurement, so P is kept."""
        self._T[:, 5 + self._slot(node)] += _vector(shift, "shift")

    def set_contact_velocity_noise(self, density: float) -> None:
        """Set the contacts' slip density (m/s/sqrt(Hz), ``InekfNoise.contact_velocity``)
        for the propagations from now on: an estimator that knows when the endcaps slide
        more (the robot tipping over) says so."""
        if not (density >= 0.0 and math.isfinite(density)):
            raise ValueError(f"density must be a finite number >= 0, got {density!r}")
        self._q[2] = density * density

    def add_velocity_variance(self, variance: float) -> None:
        """Add ``variance`` (m/s)^2 per axis to the velocity's error: a step whose
        acceleration the IMU did not measure (a reading clipped at its full scale)."""
        if not (variance >= 0.0 and math.isfinite(variance)):
            raise ValueError(f"variance must be a finite number >= 0, got {variance!r}")
        for i in range(3, 6):
            self._P[i, i] += variance

    def correct(
        self,
        nodes: Sequence[int],
        p_body: ArrayLike,
        cov_body: ArrayLike,
        gate: float | None = CHI2_3DOF_999,
    ) -> CorrectionResult:
        """Correct with the forward kinematics of the contacts ``nodes`` (K',), each
        augmented before: p_body (K', 3) m, their body-frame positions, cov_body
        (K', 3, 3) or (3, 3) m^2 their covariances.

        A node whose NIS on its own exceeds ``gate`` (a chi-square quantile, 3 dof; None:
        no gate) is rejected and not used; the others update at once.
        """
        key = tuple(map(int, nodes))
        m = len(key)
        if len(set(key)) != m:
            raise ValueError(f"nodes must be distinct, got {key}")
        y = _writable(p_body)
        if y.shape != (m, 3):
            raise ValueError(f"p_body must have shape ({m}, 3), got {y.shape}")
        cov = _writable(cov_body)
        if cov.shape == (3, 3):
            cov = np.repeat(cov[None], m, axis=0)
        elif cov.shape != (m, 3, 3):
            raise ValueError(f"cov_body must have shape ({m}, 3, 3) or (3, 3), got {cov.shape}")
        nis, accepted = np.zeros(m), np.zeros(m, dtype=np.bool_)
        if m == 0:
            return CorrectionResult(key, nis, accepted, 0.0)
        slots = np.array([self._slot(n) for n in key], dtype=np.int64)
        threshold = math.inf if gate is None else float(gate)
        total = self._correct(slots, y, cov, threshold, nis, accepted)
        return CorrectionResult(key, nis, accepted, total)

    def correct_all(
        self, p_body: NDArray[np.float64], cov_body: NDArray[np.float64], gate: float
    ) -> NDArray[np.bool_]:
        """:meth:`correct` with every contact, in state order (:attr:`contact_nodes`):
        the estimator's hot path, its arrays taken as they are (p_body (K, 3), cov_body
        (K, 3, 3), float64, C-contiguous; K >= 1). Returns which were accepted, (K,)."""
        m = len(self._nodes)
        nis, accepted = np.empty(m), np.empty(m, dtype=np.bool_)
        self._correct(np.arange(m, dtype=np.int64), p_body, cov_body, gate, nis, accepted)
        return accepted

    def correct_heights(
        self, nodes: Sequence[int], heights: NDArray[np.float64], variance: float
    ) -> None:
        """Correct with the world heights of the contacts ``nodes`` (K',), distinct: each
        measured at z = ``heights[j]`` (m), (K',), with ``variance`` (m^2); one after
        the other, by the scalar Kalman update in Joseph form, applied as every
        correction is.

        To first order the truth's contact is ``d = d_hat + rho x d_hat + eps_d`` (rho
        the rotation error of ``X = exp(eps) X_hat``), so its height's row would be
        ``[(d_hat x e_z)^T at the rotation, e_z^T at the contact]``. The rotation's part
        is left out: it is the lever of the world's origin, metres long once the robot
        has rolled away from where the filter started, and through it a few centimetres
        of height tilted the whole estimate (the 1.45 m robot rolling on MuJoCo, seed 0,
        0.05 m floor, every contact corrected at every stamp: 33.6 % drift with it,
        11.9 % without; one-off replays at 22d8591). The row ``e_z`` at the contact
        moves the height, and the rest through the covariance."""
        if not (variance > 0.0 and math.isfinite(variance)):
            raise ValueError(f"variance must be a finite number > 0, got {variance!r}")
        if len(set(nodes)) != len(nodes):
            raise ValueError(f"nodes must be distinct, got {tuple(nodes)}")
        if heights.shape != (len(nodes),):
            raise ValueError(f"heights must have shape ({len(nodes)},), got {heights.shape}")
        for node, height in zip(nodes, heights.tolist(), strict=True):
            k = self._slot(node)
            row = 11 + 3 * k  # the contact's z in P
            ph = self._P[:, row].copy()  # P h^T
            s = ph[row] + variance
            gain = ph / s
            # Joseph's (I - K h) P (I - K h)^T + K r K^T, for h one row of the identity
            self._P += s * np.outer(gain, gain) - np.outer(gain, ph) - np.outer(ph, gain)
            _symmetrise_into(self._P, self._P)
            _apply(self._T, self._b, gain[None, :], np.array([height - self._T[2, 5 + k]]))

    def _correct(
        self,
        slots: NDArray[np.int64],
        y: NDArray[np.float64],
        cov: NDArray[np.float64],
        gate: float,
        nis: NDArray[np.float64],
        accepted: NDArray[np.bool_],
    ) -> float:
        """The correction kernel on the state; its joint NIS of the accepted contacts."""
        total = _correct(self._T, self._b, self._P, slots, y, cov, gate, nis, accepted)
        if total < 0.0:
            raise np.linalg.LinAlgError("innovation covariance not positive definite")
        return total

    def _slot(self, node: int) -> int:
        try:
            return self._nodes.index(int(node))
        except ValueError:
            raise ValueError(f"node {node} is not in contact (augment it first)") from None

    def is_finite(self) -> bool:
        """True if the state and the covariance are free of NaN and inf."""
        return all_finite(self._T, self._b, self._P)

    @property
    def rotation(self) -> NDArray[np.float64]:
        """(3, 3) body to world."""
        return self._T[:, :3].copy()

    @property
    def velocity(self) -> NDArray[np.float64]:
        """(3,) m/s, world frame."""
        return self._T[:, 3].copy()

    @property
    def position(self) -> NDArray[np.float64]:
        """(3,) m, the body frame's origin (the IMU) in the world."""
        return self._T[:, 4].copy()

    @property
    def gyro_bias(self) -> NDArray[np.float64]:
        """(3,) rad/s."""
        return self._b[:3].copy()

    @property
    def accel_bias(self) -> NDArray[np.float64]:
        """(3,) m/s^2."""
        return self._b[3:].copy()

    @property
    def contact_nodes(self) -> tuple[int, ...]:
        """The nodes in contact, in state order (d_1 .. d_K)."""
        return tuple(self._nodes)

    @property
    def contact_positions(self) -> NDArray[np.float64]:
        """(K, 3) m, world frame, in the order of :attr:`contact_nodes`."""
        return self._T[:, 5:].T.copy()

    @property
    def state_matrix(self) -> NDArray[np.float64]:
        """X (5 + K, 5 + K) in SE_{2+K}(3)."""
        nc = self._T.shape[1]
        X = np.eye(nc)
        X[:3] = self._T
        return X

    @property
    def covariance(self) -> NDArray[np.float64]:
        """P (9 + 3K + 6, 9 + 3K + 6), ordered [rotation, velocity, position, d_1 .. d_K,
        b_g, b_a]: a copy."""
        return self._P.copy()

    @property
    def pose_covariance(self) -> NDArray[np.float64]:
        """(6, 6): the rotation and position block of P, in that order (rad, m)."""
        return np.asarray(self._P[_POSE_ROWS, _POSE_COLUMNS])
