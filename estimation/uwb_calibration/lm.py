"""Levenberg-Marquardt for the joint problem, with the module positions eliminated.

The joint problem has the shape of bundle adjustment: a few hundred global unknowns
(anchor coordinates, offsets, mu; G of them) and many local ones (module positions)
that only couple within one sample, through the bar and robot-robot terms. Each
iteration builds the normal equations with iteratively reweighted robust weights,
eliminates every sample's positions by its own small block (the Schur complement),
solves the dense G x G system and substitutes back: an exact Gauss-Newton step for
the cost of S small solves. (``scipy.optimize.least_squares`` with ``lsmr`` on the
sparse Jacobian converges far more slowly here: its inexact steps crawl along the
poorly conditioned anchor-offset directions.)

The robust losses are those of ``scipy.optimize.least_squares`` (same ``rho`` and
``f_scale``; the cost is ``0.5 * sum(rho)``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from estimation.uwb_calibration.problem import JointState

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from estimation.uwb_calibration.problem import JointProblem, RowBlock

__all__ = [
    "Solution",
    "global_covariance",
    "robust_rho",
    "robust_weight",
    "solve_joint",
    "solve_positions",
]

_MIN_LAMBDA, _MAX_LAMBDA = 1e-9, 1e9
_LOSSES = ("linear", "soft_l1", "huber", "cauchy")


def robust_rho(r: NDArray[np.float64], loss: str, scale: float) -> NDArray[np.float64]:
    """``f_scale**2 * rho((r / f_scale)**2)`` of ``least_squares`` for residuals r."""
    z = (r / scale) ** 2
    if loss == "linear":
        rho = z
    elif loss == "soft_l1":
        rho = 2.0 * (np.sqrt(1.0 + z) - 1.0)
    elif loss == "huber":
        rho = np.where(z <= 1.0, z, 2.0 * np.sqrt(z) - 1.0)
    elif loss == "cauchy":
        rho = np.log1p(z)
    else:
        raise ValueError(f"loss must be one of {_LOSSES}, got {loss!r}")
    return np.asarray(scale**2 * rho)


def robust_weight(r: NDArray[np.float64], loss: str, scale: float) -> NDArray[np.float64]:
    """rho'(z) for residuals r: the weight of each row in a reweighted step."""
    z = (r / scale) ** 2
    if loss == "linear":
        return np.ones_like(r)
    if loss == "soft_l1":
        return np.asarray(1.0 / np.sqrt(1.0 + z))
    if loss == "huber":
        return np.asarray(1.0 / np.sqrt(np.maximum(z, 1.0)))
    if loss == "cauchy":
        return np.asarray(1.0 / (1.0 + z))
    raise ValueError(f"loss must be one of {_LOSSES}, got {loss!r}")


@dataclass(frozen=True)
class Solution:
    """Where a joint solve ended."""

    state: JointState
    cost: float
    """Robust cost per measurement row at the end (dimensionless)."""
    iterations: int


@dataclass(frozen=True)
class _Layout:
    """Each position's sample and its index within it; B = 3 * the most a sample has."""

    local: NDArray[np.intp]
    n_samples: int
    block: int

    @classmethod
    def of(cls, p: JointProblem) -> _Layout:
        s = p.position_sample
        n_samples = int(s.max()) + 1 if len(s) else 0
        counts = np.bincount(s, minlength=n_samples)
        first = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.intp)
        block = 3 * int(counts.max()) if len(s) else 3
        return cls(np.arange(len(s)) - first[s], n_samples, block)


def _cost(blocks: list[RowBlock], loss: str, scale: float) -> float:
    total = 0.0
    for b in blocks:
        rho = robust_rho(b.residual, loss, scale) if b.robust else b.residual**2
        total += 0.5 * float(np.sum(rho))
    return total


def _accumulate(
    blocks: list[RowBlock], lay: _Layout, p: JointProblem, loss: str, scale: float
) -> tuple[NDArray[np.float64], ...]:
    """Normal equations of the reweighted problem: local blocks (S, B, B), local
    gradient (S, B), global block (G, G), coupling (S, G, B), global gradient (G,)."""
    S, B, G = lay.n_samples, lay.block, p.n_global
    Hll, gl = np.zeros(S * B * B), np.zeros(S * B)
    Hgg, gg, Hgl = np.zeros(G * G), np.zeros(G), np.zeros(S * G * B)
    for b in blocks:
        if len(b.residual) == 0:
            continue  # no rows of this kind (a recording without robot-robot ranges)
        w = robust_weight(b.residual, loss, scale) if b.robust else np.ones_like(b.residual)
        cols, gv = np.maximum(b.global_columns, 0), b.global_values * w[:, None]
        coupled = G > 0 and bool(np.any(b.global_columns >= 0))
        if coupled:
            outer = gv[:, :, None] * b.global_values[:, None, :]
            Hgg += np.bincount(
                (cols[:, :, None] * G + cols[:, None, :]).ravel(), outer.ravel(), G * G
            )
            gg += np.bincount(cols.ravel(), (gv * b.residual[:, None]).ravel(), G)
        if b.positions.shape[1] == 0:
            continue
        smp = p.position_sample[b.positions[:, 0]]
        flat = (3 * lay.local[b.positions][:, :, None] + np.arange(3)).reshape(len(w), -1)
        lv = b.position_values.reshape(len(w), -1)  # (k, 3 l), as flat
        wl = lv * w[:, None]
        idx = (smp[:, None, None] * B + flat[:, :, None]) * B + flat[:, None, :]
        Hll += np.bincount(idx.ravel(), (wl[:, :, None] * lv[:, None, :]).ravel(), S * B * B)
        gl += np.bincount(
            (smp[:, None] * B + flat).ravel(), (wl * b.residual[:, None]).ravel(), S * B
        )
        if coupled:
            idx = (smp[:, None, None] * G + cols[:, :, None]) * B + flat[:, None, :]
            Hgl += np.bincount(idx.ravel(), (gv[:, :, None] * lv[:, None, :]).ravel(), S * G * B)
    return Hll.reshape(S, B, B), gl.reshape(S, B), Hgg.reshape(G, G), Hgl.reshape(S, G, B), gg


def _position_scale(Hll: NDArray[np.float64]) -> NDArray[np.float64]:
    """(S, B) Levenberg damping scale of each position coordinate: the mean of its
    position's three diagonal entries (1 for padding), the same along every axis, so
    that a position poorly fixed along a slanted direction is damped along it too."""
    S, B = Hll.shape[0], Hll.shape[1]
    diag = np.einsum("sii->si", Hll).reshape(S, B // 3, 3)
    mean = np.repeat(diag.mean(axis=2), 3, axis=1)
    return np.where(mean > 0.0, mean, 1.0)


def _step(
    normal: tuple[NDArray[np.float64], ...], lay: _Layout, p: JointProblem, lam: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The damped Gauss-Newton step, global (G,) and positions (V, 3), by the Schur
    complement of the positions."""
    Hll, gl, Hgg, Hgl, gg = normal
    S, B, G = lay.n_samples, lay.block, p.n_global
    damped = Hll + np.einsum("si,ij->sij", lam * _position_scale(Hll) + 1e-9, np.eye(B))
    rhs = np.concatenate([gl[:, :, None], Hgl.transpose(0, 2, 1)], axis=2)
    sol = np.linalg.solve(damped, rhs)  # (S, B, 1 + G)
    z, Y = sol[:, :, 0], sol[:, :, 1:]
    if G == 0:
        return np.zeros(0), (-z).reshape(S, B // 3, 3)[p.position_sample, lay.local]
    gdiag = np.diag(Hgg)
    reduced = Hgg + np.diag(lam * gdiag + 1e-9 + (gdiag == 0.0))
    reduced -= Hgl.transpose(1, 0, 2).reshape(G, S * B) @ Y.reshape(S * B, G)
    step_g = np.linalg.solve(reduced, -gg + np.einsum("sgb,sb->g", Hgl, z))
    local = -z - np.einsum("sbg,g->sb", Y, step_g)
    return step_g, local.reshape(S, B // 3, 3)[p.position_sample, lay.local]


def solve_joint(
    p: JointProblem,
    start: JointState,
    loss: str,
    scale: float,
    max_iterations: int = 50,
    ftol: float = 1e-5,
) -> Solution:
    """Minimise the robust cost of ``p`` (``loss``, ``scale`` as ``least_squares``'s
    ``loss``, ``f_scale``) from ``start``; held anchor coordinates keep their values."""
    lay = _Layout.of(p)
    state = start
    blocks = p.rows(state)
    cost = _cost(blocks, loss, scale)
    lam, iterations = 1e-3, 0
    for iterations in range(1, max_iterations + 1):  # noqa: B007
        normal = _accumulate(blocks, lay, p, loss, scale)
        while lam < _MAX_LAMBDA:
            trial = p.moved(state, *_step(normal, lay, p, lam))
            trial_blocks = p.rows(trial)
            new = _cost(trial_blocks, loss, scale)
            if np.isfinite(new) and new <= cost:
                break
            lam *= 10.0
        else:
            break
        done = cost - new <= ftol * cost
        state, blocks, cost, lam = trial, trial_blocks, new, max(lam / 3.0, _MIN_LAMBDA)
        if done:
            break
    rows = max(sum(len(b.residual) for b in blocks if b.robust), 1)
    return Solution(state, cost / rows, iterations)


def _sample_costs(blocks: list[RowBlock], p: JointProblem, n: int, loss: str,
                  scale: float) -> NDArray[np.float64]:  # fmt: skip
    """Robust cost of each sample's rows, (n,)."""
    out = np.zeros(n)
    for b in blocks:
        if b.positions.shape[1] == 0:
            continue
        rho = robust_rho(b.residual, loss, scale) if b.robust else b.residual**2
        out += 0.5 * np.bincount(p.position_sample[b.positions[:, 0]], rho, n)
    return out


def solve_positions(
    p: JointProblem,
    start: JointState,
    loss: str,
    scale: float,
    iterations: int = 30,
    ftol: float = 1e-6,
) -> JointState:
    """The module positions alone (anchors and offsets held: ``p.n_global == 0``), each
    sample its own Levenberg-Marquardt with its own damping, all at once; stops when
    an iteration lowers the total cost by less than ``ftol`` of it."""
    if p.n_global:
        raise ValueError("solve_positions needs every anchor and offset held")
    lay = _Layout.of(p)
    S, B = lay.n_samples, lay.block
    state = start
    blocks = p.rows(state)
    cost = _sample_costs(blocks, p, S, loss, scale)
    lam = np.full(S, 1e-3)
    for _ in range(iterations):
        Hll, gl, *_ = _accumulate(blocks, lay, p, loss, scale)
        scale_s = lam[:, None] * _position_scale(Hll) + 1e-9
        damped = Hll + np.einsum("si,ij->sij", scale_s, np.eye(B))
        step = -np.linalg.solve(damped, gl[:, :, None])[:, :, 0]
        trial = p.moved(
            state, np.zeros(0), step.reshape(S, B // 3, 3)[p.position_sample, lay.local]
        )
        trial_blocks = p.rows(trial)
        new = _sample_costs(trial_blocks, p, S, loss, scale)
        better = np.isfinite(new) & (new <= cost)
        take = better[p.position_sample]
        positions = np.where(take[:, None], trial.positions, state.positions)
        state = JointState(state.anchors, state.offsets, state.mean_offset, positions)
        blocks = p.rows(state)
        gain = np.where(better, cost - new, 0.0)
        cost = np.where(better, new, cost)
        lam = np.clip(np.where(better, lam / 3.0, lam * 10.0), _MIN_LAMBDA, _MAX_LAMBDA)
        if gain.sum() <= ftol * cost.sum():
            break
    return state


def global_covariance(
    p: JointProblem, state: JointState, loss: str, scale: float
) -> NDArray[np.float64]:
    """Covariance (G, G) of the global unknowns at ``state`` (m^2; the Gauss-Newton
    inverse of the reduced normal matrix, positions eliminated), for residuals of unit
    variance over their sigmas: how well the data fix the anchors and offsets."""
    lay = _Layout.of(p)
    Hll, _, Hgg, Hgl, _ = _accumulate(p.rows(state), lay, p, loss, scale)
    S, B, G = lay.n_samples, lay.block, p.n_global
    damped = Hll + np.einsum("si,ij->sij", 1e-9 * _position_scale(Hll) + 1e-12, np.eye(B))
    Y = np.linalg.solve(damped, Hgl.transpose(0, 2, 1))
    reduced = Hgg - Hgl.transpose(1, 0, 2).reshape(G, S * B) @ Y.reshape(S * B, G)
    return np.asarray(np.linalg.pinv(reduced, rcond=1e-12, hermitian=True))
