"""A slow, obviously correct contact-aided right-invariant EKF, for the tests to hold
``estimation.inekf.filter.RightInvariantEkf`` to.

Dense matrices throughout, the same conventions (module docstring of
``estimation.inekf.filter``): the truth is ``X = exp(eps) X_hat``, ``b = b_hat + eps_b``,
P the covariance of eps ordered [rotation, velocity, position, d_1 .. d_K, b_g, b_a].
The group exponential is ``scipy.linalg.expm`` of the (5 + K, 5 + K) Lie algebra matrix;
Ad_X is built column by column from its definition ``X wedge(e_i) X^-1``; Phi is
``expm(A dt)`` of the dense A; ``Q_d = Phi Ad Q Ad^T Phi^T dt``; the correction stacks
the dense H and uses ``(I - K H) P (I - K H)^T + K N K^T`` as written.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import expm

from tensegrity_gym.model.lie import hat, sek3_vee, sek3_wedge


def _adjoint(X: np.ndarray) -> np.ndarray:
    """Ad_X (3 + 3k, 3 + 3k) by its definition, one basis vector at a time."""
    n = 3 * (X.shape[0] - 2)
    Xinv = np.linalg.inv(X)
    return np.column_stack([sek3_vee(X @ sek3_wedge(e) @ Xinv) for e in np.eye(n)])


class ReferenceInekf:
    """X (5 + K, 5 + K), b (6,) = (b_g, b_a), P (9 + 3K + 6, same)."""

    def __init__(self, sigmas: tuple[float, float, float, float, float], gravity: np.ndarray):
        """sigmas: the densities of gyro, accel, gyro bias, accel bias, contact velocity."""
        self.sg, self.sa, self.sbg, self.sba, self.sc = sigmas
        self.g = np.asarray(gravity, dtype=float)

    def reset(
        self,
        R: np.ndarray,
        v: np.ndarray,
        p: np.ndarray,
        b_g: np.ndarray,
        b_a: np.ndarray,
        P0: np.ndarray,
    ) -> None:
        self.X = np.eye(5)
        self.X[:3, :3], self.X[:3, 3], self.X[:3, 4] = R, v, p
        self.b = np.concatenate([b_g, b_a]).astype(float)
        self.P = np.array(P0, dtype=float)
        self.nodes: list[int] = []

    @property
    def n_contacts(self) -> int:
        return len(self.nodes)

    def propagate(self, gyro: np.ndarray, accel: np.ndarray, dt: float) -> None:
        X, K = self.X, self.n_contacts
        R, v, p = X[:3, :3], X[:3, 3], X[:3, 4]
        ns, n = 9 + 3 * K, 15 + 3 * K
        Ad = _adjoint(X)
        A = np.zeros((n, n))
        A[3:6, 0:3] = hat(self.g)
        A[6:9, 3:6] = np.eye(3)
        A[:ns, ns : ns + 6] = -Ad[:, 0:6]  # the gyro and accelerometer columns of Ad_X
        Phi = expm(A * dt)
        Q = np.zeros((n, n))
        Q[0:3, 0:3] = self.sg**2 * np.eye(3)
        Q[3:6, 3:6] = self.sa**2 * np.eye(3)
        for k in range(K):
            Q[9 + 3 * k : 12 + 3 * k, 9 + 3 * k : 12 + 3 * k] = self.sc**2 * np.eye(3)
        Q[ns : ns + 3, ns : ns + 3] = self.sbg**2 * np.eye(3)
        Q[ns + 3 :, ns + 3 :] = self.sba**2 * np.eye(3)
        Adf = np.eye(n)
        Adf[:ns, :ns] = Ad
        Qd = Phi @ Adf @ Q @ Adf.T @ Phi.T * dt
        self.P = Phi @ self.P @ Phi.T + Qd
        self.P = 0.5 * (self.P + self.P.T)
        w, a = gyro - self.b[:3], accel - self.b[3:]
        acc = R @ a + self.g
        X_new = X.copy()
        X_new[:3, :3] = R @ expm(hat(w * dt))
        X_new[:3, 3] = v + acc * dt
        X_new[:3, 4] = p + v * dt + 0.5 * acc * dt * dt
        self.X = X_new

    def augment(self, node: int, p_body: np.ndarray, cov_body: np.ndarray) -> None:
        X, K = self.X, self.n_contacts
        R, p = X[:3, :3], X[:3, 4]
        n = self.P.shape[0]
        ns = 9 + 3 * K
        F = np.zeros((n + 3, n))
        F[:ns, :ns] = np.eye(ns)
        F[ns : ns + 3, 6:9] = np.eye(3)
        F[ns + 3 :, ns:] = np.eye(6)
        G = np.zeros((n + 3, 3))
        G[ns : ns + 3] = R
        self.P = F @ self.P @ F.T + G @ cov_body @ G.T
        X_new = np.eye(6 + K)
        X_new[:3, : 5 + K] = X[:3, :]
        X_new[:3, 5 + K] = p + R @ p_body
        self.X = X_new
        self.nodes.append(node)

    def marginalise(self, node: int) -> None:
        k = self.nodes.index(node)
        o = 9 + 3 * k
        self.P = np.delete(np.delete(self.P, range(o, o + 3), axis=0), range(o, o + 3), axis=1)
        self.X = np.delete(np.delete(self.X, 5 + k, axis=0), 5 + k, axis=1)
        del self.nodes[k]

    def correct(
        self, nodes: list[int], p_body: np.ndarray, cov_body: np.ndarray, gate: float | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Returns (per-node NIS, accepted) like the fast filter's result."""
        X, n = self.X, self.P.shape[0]
        R, p = X[:3, :3], X[:3, 4]
        m = len(nodes)
        H = np.zeros((3 * m, n))
        z = np.zeros(3 * m)
        N = np.zeros((3 * m, 3 * m))
        for j, node in enumerate(nodes):
            k = self.nodes.index(node)
            H[3 * j : 3 * j + 3, 6:9] = -np.eye(3)
            H[3 * j : 3 * j + 3, 9 + 3 * k : 12 + 3 * k] = np.eye(3)
            z[3 * j : 3 * j + 3] = R @ p_body[j] + p - X[:3, 5 + k]
            N[3 * j : 3 * j + 3, 3 * j : 3 * j + 3] = R @ cov_body[j] @ R.T
        S = H @ self.P @ H.T + N
        nis = np.array(
            [
                z[3 * j : 3 * j + 3] @ np.linalg.solve(S[3 * j : 3 * j + 3, 3 * j : 3 * j + 3],
                                                       z[3 * j : 3 * j + 3])
                for j in range(m)
            ]
        )  # fmt: skip
        accepted = nis <= (np.inf if gate is None else gate)
        rows = np.repeat(accepted, 3)
        if rows.any():
            H, z, N = H[rows], z[rows], N[np.ix_(rows, rows)]
            S = H @ self.P @ H.T + N
            Kg = self.P @ H.T @ np.linalg.inv(S)
            delta = Kg @ z
            ns = n - 6
            self.X = expm(sek3_wedge(delta[:ns])) @ X
            self.b = self.b + delta[ns:]
            IKH = np.eye(n) - Kg @ H
            self.P = IKH @ self.P @ IKH.T + Kg @ N @ Kg.T
            self.P = 0.5 * (self.P + self.P.T)
        return nis, accepted
