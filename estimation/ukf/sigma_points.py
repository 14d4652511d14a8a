"""Scaled sigma points (van der Merwe) and a Cholesky factorisation that does not give up."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.linalg

if TYPE_CHECKING:
    from numpy.typing import NDArray

__all__ = ["CholeskyError", "SigmaPointParams", "robust_cholesky", "sigma_points"]


class CholeskyError(np.linalg.LinAlgError):
    """A covariance stayed indefinite after every retry with added jitter."""


@dataclass(frozen=True)
class SigmaPointParams:
    """alpha, beta, kappa of the scaled unscented transform; defaults from Caluwaerts et al.
    2016."""

    alpha: float = 0.0139
    beta: float = 2.0
    kappa: float = 0.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.alpha) and self.alpha > 0):
            raise ValueError(f"SigmaPointParams.alpha must be positive, got {self.alpha}")
        if not np.isfinite(self.beta) or not np.isfinite(self.kappa):
            raise ValueError("SigmaPointParams.beta and kappa must be finite")

    def lambda_(self, n: int) -> float:
        return self.alpha**2 * (n + self.kappa) - n

    def weights(self, n: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Mean and covariance weights (Wm, Wc), each (2 n + 1,)."""
        lam = self.lambda_(n)
        if n + lam <= 0:
            raise ValueError(f"alpha^2 (n + kappa) must be positive; got {n + lam} for n={n}")
        wm = np.full(2 * n + 1, 0.5 / (n + lam))
        wc = wm.copy()
        wm[0] = lam / (n + lam)
        wc[0] = lam / (n + lam) + (1.0 - self.alpha**2 + self.beta)
        return wm, wc


def robust_cholesky(
    P: NDArray[np.float64], max_tries: int = 6
) -> tuple[NDArray[np.float64], float]:
    """Lower Cholesky factor of a covariance, adding jitter and retrying if it fails.

    The jitter starts at 1e-10 of the mean diagonal and grows tenfold each try.

    Returns:
        (L, jitter): L (n, n) lower with L L^T = P + jitter I.
    """
    if not np.all(np.isfinite(P)):
        # LAPACK's potrf does not fail on NaN or inf: it would hand back a NaN factor.
        raise CholeskyError("covariance has non-finite entries")
    try:
        return scipy.linalg.cholesky(P, lower=True, check_finite=False), 0.0
    except np.linalg.LinAlgError:
        pass
    scale = max(float(np.mean(np.abs(np.diag(P)))), 1e-12)
    jitter = 1e-10 * scale
    eye = np.eye(P.shape[0])
    for _ in range(max_tries):
        try:
            return scipy.linalg.cholesky(P + jitter * eye, lower=True, check_finite=False), jitter
        except np.linalg.LinAlgError:
            jitter *= 10.0
    raise CholeskyError(f"covariance not positive definite even with jitter {jitter / 10:.3g}")


def sigma_points(
    x: NDArray[np.float64], P: NDArray[np.float64], params: SigmaPointParams
) -> tuple[NDArray[np.float64], float]:
    """The 2 n + 1 sigma points of mean x (n,) and covariance P (n, n).

    Ordered as filterpy orders them: x, then x + column k of sqrt((n + lambda) P) for
    k = 0..n-1, then x - column k.

    Returns:
        (sigmas, jitter): sigmas (2 n + 1, n); the jitter the factorisation needed.
    """
    n = x.shape[0]
    L, jitter = robust_cholesky((n + params.lambda_(n)) * P)
    out = np.empty((2 * n + 1, n))
    out[0] = x
    out[1 : n + 1] = x + L.T
    out[n + 1 :] = x - L.T
    return out, jitter
