"""The speed of the contact-aided right-invariant EKF's steps (Tong et al. 2024 section VI-D:
its C++ propagated in 11.3 us and corrected in 17.5 us).

A robot rests on three endcaps; the filter propagates through noisy IMU readings at
200 Hz and corrects with the three contacts after each, and separately augments and
marginalises a fourth contact. Every call is timed on its own; the figures are medians
(a shared machine's scheduler adds long tails to a mean) with the means beside them.
The first calls, which load or compile the numba kernels, are left out.
"""

from __future__ import annotations

import time

import numpy as np

from estimation.inekf.filter import InekfNoise, RightInvariantEkf

__all__ = ["bench_inekf"]

_FEET = np.array([[0.4, 0.0, -0.5], [-0.2, 0.35, -0.5], [-0.2, -0.35, -0.5]])
"""Body-frame endcaps in contact (m)."""
_KIN = 0.01**2 * np.eye(3)
"""Forward-kinematics covariance (m^2)."""


def _resting_filter() -> RightInvariantEkf:
    f = RightInvariantEkf(InekfNoise())
    P0 = np.diag(np.r_[[1e-4] * 2, 0.04, [1e-4] * 6, [1e-4] * 3, [1e-2] * 3])
    f.reset(np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), P0)
    for node, foot in enumerate(_FEET):
        f.augment(node, foot, _KIN)
    return f


def _summary(name: str, seconds: list[float]) -> dict[str, float]:
    us = 1e6 * np.asarray(seconds)
    return {f"{name}_us": round(float(np.median(us)), 2),
            f"{name}_mean_us": round(float(np.mean(us)), 2)}  # fmt: skip


def bench_inekf(n: int = 2000) -> dict[str, float]:
    """Microseconds per call of ``propagate``, of ``correct`` with three contacts (a
    24-dim covariance) and of ``augment`` and ``marginalise`` (three contacts to four
    and back), medians and means over ``n`` calls each."""
    rng = np.random.default_rng(0)
    f = _resting_filter()
    dt, noise = 0.005, f.noise
    gyro = rng.normal(0.0, noise.gyro / np.sqrt(dt), (n + 1, 3))
    accel = np.array([0.0, 0.0, 9.81]) + rng.normal(0.0, noise.accel / np.sqrt(dt), (n + 1, 3))
    y = _FEET + rng.normal(0.0, 0.01, (n + 1, 3, 3))
    nodes, cov = [0, 1, 2], np.repeat(_KIN[None], 3, axis=0)
    f.propagate(gyro[n], accel[n], dt)  # the first calls load (or compile) the kernels
    f.correct(nodes, y[n], cov)
    times: dict[str, list[float]] = {"propagate": [], "correct": [], "augment": [],
                                     "marginalise": []}  # fmt: skip
    clock = time.perf_counter
    for k in range(n):
        t0 = clock()
        f.propagate(gyro[k], accel[k], dt)
        t1 = clock()
        f.correct(nodes, y[k], cov)
        t2 = clock()
        f.augment(3, _FEET[0], _KIN)
        t3 = clock()
        f.marginalise(3)
        t4 = clock()
        for name, took in zip(times, (t1 - t0, t2 - t1, t3 - t2, t4 - t3), strict=True):
            times[name].append(took)
    out: dict[str, float] = {"state_dim": float(f.covariance.shape[0])}
    for name, seconds in times.items():
        out |= _summary(name, seconds)
    if not f.is_finite():
        raise RuntimeError("the benchmarked filter diverged")
    return out
