"""The unscented Kalman filter with additive noise, on batched process and measurement maps.

The process map takes every sigma point at once, (S, n) -> (S, n), and so does the
measurement map, (S, n) -> (S, k): the filter never calls Python once per sigma point.
The steps are those of filterpy's ``UnscentedKalmanFilter`` (sigma points are redrawn
from the predicted mean and covariance before an update), which the tests hold it to,
plus what a filter on a robot needs: symmetrised covariances, jitter when a Cholesky
factorisation fails, and gating of outlying measurements.
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.linalg
import scipy.stats
from threadpoolctl import ThreadpoolController

from estimation.ukf.sigma_points import SigmaPointParams, robust_cholesky, sigma_points

if TYPE_CHECKING:
    from collections.abc import Callable

    from numpy.typing import NDArray

__all__ = ["UnscentedKalmanFilter", "UpdateResult", "single_threaded_blas"]


@functools.cache
def _blas_controller() -> ThreadpoolController:
    return ThreadpoolController()


def single_threaded_blas() -> Any:
    """A context in which BLAS runs on one thread.

    The filter's matrices are a few hundred rows: threaded BLAS only adds hand-offs
    between threads (measured here: a 300 x 300 Cholesky took 2-60 ms threaded, 0.5 ms
    on one thread), and vectorised envs already keep every core busy.
    """
    return _blas_controller().limit(limits=1, user_api="blas")


@dataclass(frozen=True)
class UpdateResult:
    """What one measurement update did."""

    n_measurements: int
    """Rows offered to the update."""
    accepted: NDArray[np.bool_]
    """(k,): rows used; gated rows are False."""
    nis: float
    """Normalised innovation squared of the accepted rows (chi-square, their count dof)."""
    jitter: float
    """Jitter the factorisations needed (0 when none)."""

    @property
    def n_rejected(self) -> int:
        return int(self.n_measurements - np.count_nonzero(self.accepted))


@functools.lru_cache(maxsize=64)
def _chi2_quantile(probability: float, dof: int) -> float:
    """The Mahalanobis-squared threshold a true measurement of ``dof`` rows passes with
    ``probability``. Cached: scipy's ppf costs tens of microseconds a call, and a filter
    asks for a handful of dofs."""
    return float(scipy.stats.chi2.ppf(probability, dof))


class UnscentedKalmanFilter:
    """Mean x (n,) and covariance P (n, n), advanced by :meth:`predict` and :meth:`update`."""

    def __init__(
        self,
        x: NDArray[np.float64],
        P: NDArray[np.float64],
        params: SigmaPointParams | None = None,
    ) -> None:
        self.params = params if params is not None else SigmaPointParams()
        self.x = np.array(x, dtype=np.float64)
        self.P = np.array(P, dtype=np.float64)
        n = self.x.shape[0]
        if self.P.shape != (n, n):
            raise ValueError(f"P has shape {self.P.shape}, expected {(n, n)} for x of size {n}")
        self.Wm, self.Wc = self.params.weights(n)
        self.last_jitter = 0.0

    @property
    def dim(self) -> int:
        return int(self.x.shape[0])

    def sigma_points(self) -> NDArray[np.float64]:
        """(2 n + 1, n) for the current mean and covariance."""
        sigmas, self.last_jitter = sigma_points(self.x, self.P, self.params)
        return sigmas

    def predict(
        self,
        fx: Callable[[NDArray[np.float64]], NDArray[np.float64]],
        Q: NDArray[np.float64],
    ) -> None:
        """Propagate through ``fx`` (S, n) -> (S, n) and add process noise Q ((n,)
        variances or (n, n))."""
        propagated = fx(self.sigma_points())
        x = self.Wm @ propagated
        d = propagated - x
        P = d.T @ (self.Wc[:, None] * d)
        Q = np.asarray(Q, dtype=np.float64)
        if Q.ndim == 1:
            P[np.diag_indices_from(P)] += Q
        else:
            P += Q
        self.x = x
        self.P = 0.5 * (P + P.T)

    def update(
        self,
        z: NDArray[np.float64],
        R: NDArray[np.float64],
        hx: Callable[[NDArray[np.float64]], NDArray[np.float64]],
        groups: NDArray[np.intp] | None = None,
        gate_probability: float | None = None,
    ) -> UpdateResult:
        """Correct with measurements z (k,) of noise R ((k,) variances or (k, k)).

        Args:
            hx: (S, n) -> (S, k), the predicted measurement of every sigma point.
            groups: (k,) group id of each row; a group is gated as one (the three
                components of a direction, say). None: every row is its own group.
            gate_probability: rows whose group's Mahalanobis distance squared exceeds
                the chi-square quantile of this probability are dropped. None: no gate.
        """
        z = np.asarray(z, dtype=np.float64)
        k = z.shape[0]
        if k == 0:
            return UpdateResult(0, np.zeros(0, dtype=np.bool_), 0.0, 0.0)
        R = np.asarray(R, dtype=np.float64)
        R_full = np.diag(R) if R.ndim == 1 else R
        sigmas = self.sigma_points()
        jitter = self.last_jitter
        predicted = hx(sigmas)
        if predicted.shape != (sigmas.shape[0], k):
            raise ValueError(
                f"hx returned shape {predicted.shape}, expected {(sigmas.shape[0], k)}"
            )
        zp = self.Wm @ predicted
        dz = predicted - zp
        dx = sigmas - self.x
        wdz = self.Wc[:, None] * dz
        S = dz.T @ wdz + R_full
        S = 0.5 * (S + S.T)
        Pxz = dx.T @ wdz
        y = z - zp
        accepted = np.ones(k, dtype=np.bool_)
        if gate_probability is not None:
            accepted = _gate(y, S, groups, gate_probability)
            if not accepted.any():
                return UpdateResult(k, accepted, 0.0, jitter)
            if not accepted.all():
                S = S[np.ix_(accepted, accepted)]
                Pxz = Pxz[:, accepted]
                y = y[accepted]
        L, j2 = robust_cholesky(S)
        jitter = max(jitter, j2)
        # K = Pxz S^-1 by two triangular solves, never an explicit inverse.
        K = scipy.linalg.cho_solve((L, True), Pxz.T, check_finite=False).T
        innovation_w = scipy.linalg.solve_triangular(L, y, lower=True, check_finite=False)
        self.x = self.x + K @ y
        P = self.P - K @ Pxz.T  # = K S K^T, since K S = Pxz
        self.P = 0.5 * (P + P.T)
        return UpdateResult(k, accepted, float(innovation_w @ innovation_w), jitter)


def _gate(
    y: NDArray[np.float64],
    S: NDArray[np.float64],
    groups: NDArray[np.intp] | None,
    probability: float,
) -> NDArray[np.bool_]:
    """(k,) True where the row's group passes the chi-square gate."""
    diag = np.diag(S)
    # Every row alone first; then the few multi-row groups (directions) as blocks.
    accepted = np.asarray(y * y <= _chi2_quantile(probability, 1) * diag)
    if groups is None or len(groups) < 2:
        return accepted
    if np.all(groups[1:] >= groups[:-1]):  # groups in runs, as batches make them: no sort
        bounds = np.concatenate([[0], np.flatnonzero(np.diff(groups)) + 1, [len(groups)]])
        blocks = [np.arange(a, b) for a, b in itertools.pairwise(bounds.tolist()) if b - a > 1]
    else:
        _, inverse, counts = np.unique(groups, return_inverse=True, return_counts=True)
        blocks = [np.flatnonzero(inverse == g) for g in np.flatnonzero(counts > 1)]
    for rows in blocks:
        accepted[rows] = _passes(y, S, rows, probability)
    return accepted


def _passes(
    y: NDArray[np.float64], S: NDArray[np.float64], rows: NDArray[np.intp], probability: float
) -> bool:
    block = S[np.ix_(rows, rows)]
    d2 = float(y[rows] @ np.linalg.solve(block, y[rows]))
    return d2 <= _chi2_quantile(probability, len(rows))
