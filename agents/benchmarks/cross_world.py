"""Every estimator on data from worlds it was not tuned in.

The estimators were built and tuned in the PyBullet world of the nominal descriptions.
Here each one is scored on four worlds, the same seeds and gaits in each:

- ``own``: that world (PyBullet, the description the estimator is handed);
- ``other_engine``: the MuJoCo engine, the robot's MJCF from the same description;
- ``description_error``: PyBullet, the robot built from a description drawn off the
  nominal one (``randomization="description"``: rod lengths, endcaps, motor ranges,
  encoder zeros, stiffness, rest lengths, masses), the estimator keeping the nominal;
- ``stiff_contacts``: MuJoCo with contacts as stiff as it integrates (the engine
  ``mujoco_stiff``), as MuJoCo models written elsewhere set them: hard impacts that clip
  the accelerometer, and more hops.

Each run is recorded once (the gait driven by the true state, RGB-D frames too where
an estimator needs them) and every estimator of that robot is replayed on it with the
world's true UWB calibration, so that the world's departure is all that differs.
Figures per estimator and world, means over runs (``mean``) and their spread (``max``):
CoM RMSE, the rods' mean rotation error, the shape error (endcap distances), the drift
of Tong et al. 2024 (the base rod's frame over its 3-D path), the NEES per degree of
freedom of the node positions where the estimator has a covariance, re-initialisations.
Beside the registered estimators, :data:`VARIANTS` (the UKF taking the description's
lengths as exact: what estimating them buys).
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

import numpy as np

from agents.benchmarks.estimation import record_face_transition
from agents.benchmarks.proprio import drift_metrics
from agents.recordings.runs import replay, trajectory_errors
from estimation.ukf import UkfConfig, UkfEstimator
from tensegrity_gym.model.registry import estimator_spec

if TYPE_CHECKING:
    from collections.abc import Callable

    from hardware.recording import RecordedRun
    from tensegrity_gym.model.estimate import Estimate
    from tensegrity_gym.model.protocols import Estimator

__all__ = [
    "CROSS_WORLD_TARGETS",
    "ESTIMATOR_ROBOTS",
    "VARIANTS",
    "WORLDS",
    "bench_cross_world",
    "nees_per_dof",
    "score_run",
    "summary",
]

WORLDS: dict[str, dict[str, Any]] = {
    "own": {},
    "other_engine": {"engine": "mujoco"},
    "description_error": {"randomization": "description"},
    "stiff_contacts": {"engine": "mujoco_stiff"},
}
"""The worlds by name: the arguments of ``gym.make`` each adds."""

_THREE_BAR = {
    "rolling": ("tensegrity_gym/ThreeBarRoll-v0", "forward"),
    "turning": ("tensegrity_gym/ThreeBarGoTo-v0", "steer"),  # steered to a drawn goal
}
_LARGE = {
    "rolling": ("tensegrity_gym/ThreeBarLargeRoll-v0", "forward"),
    "turning": ("tensegrity_gym/ThreeBarLargeRoll-v0", "left"),
}
ESTIMATOR_ROBOTS: dict[str, dict[str, tuple[str, str]]] = {
    "ukf": _THREE_BAR,
    "ukf_exact_lengths": _THREE_BAR,
    "ukf_large": _LARGE,
    "icp": _THREE_BAR,
    "inekf": _LARGE,
}
"""Each estimator's runs by motion: the env id (its robot, the one the estimator was
built and tuned on; ``ukf_large``: the UKF on the 1.45 m 3-bar, a robot 4.5 times the
size of the one it was tuned on) and the gait."""

VARIANTS: dict[str, Callable[[], Estimator]] = {
    "ukf_exact_lengths": lambda: UkfEstimator(
        UkfConfig(rest_length_error_sigma=None, rod_length_error_sigma=None)
    ),
    "ukf_large": UkfEstimator,
}
"""Estimators scored beside the registered ones: the UKF taking the description's
lengths as exact (what its estimated lengths are measured against), and the UKF as
registered on the 1.45 m robot."""

CROSS_WORLD_TARGETS: dict[str, dict[str, float]] = {
    "ukf": {"com_rmse_m": 0.015, "rod_rotation_mean_deg": 3.0, "reinitialisations": 0.0,
            "nees_per_dof": 2.0},
    "ukf_large": {"rod_rotation_mean_deg": 3.0, "reinitialisations": 0.0, "nees_per_dof": 2.0},
    "inekf": {"drift_percent": 4.2, "rod_rotation_mean_deg": 10.0, "shape_rmse_m": 0.03},
}  # fmt: skip
"""Issue 42's figures on the worlds other than ``own``: each at most this (means)."""


def nees_per_dof(run: RecordedRun, estimates: list[Estimate], settle: float = 2.0) -> float:
    """Mean NEES per degree of freedom of the node positions (their covariance block)
    after ``settle`` s; NaN for an estimator without a covariance."""
    n = run.description.n_nodes
    t0 = estimates[0].t
    values = []
    for e, step in zip(estimates[1:], run.steps, strict=True):
        if step.truth is None or e.t - t0 < settle or e.covariance is None:
            continue
        err = (e.node_positions - step.truth.node_positions).ravel()
        values.append(float(err @ np.linalg.solve(e.covariance[: 3 * n, : 3 * n], err)) / (3 * n))
    return float(np.mean(values)) if values else float("nan")


def score_run(run: RecordedRun, estimator: str, seed: int) -> dict[str, Any]:
    """One estimator replayed on one run: its figures, the path the robot's CoM took
    (m, in the ground plane) and why the estimator re-initialised (``reasons``)."""
    made = VARIANTS[estimator]() if estimator in VARIANTS else estimator_spec(estimator).create()
    estimates = replay(run, made, seed)
    health = getattr(made, "health", None)
    reasons = dict(health.reinitialisations_by_reason) if health is not None else {}
    errors = trajectory_errors(run, estimates)
    truths = [run.start.truth] + [s.truth for s in run.steps]
    if any(t is None for t in truths):
        raise ValueError("cross-world runs are recorded with their truth")
    drift = drift_metrics(truths, estimates, run.description.cable_nodes)  # type: ignore[arg-type]
    # The invariant EKF's contact heights used (one a touch-down): a flickering contact
    # sensor would correct the same floor again and again.
    corrections = getattr(made, "floor_corrections", None)
    floor = {} if corrections is None else {"floor_corrections": float(corrections)}
    return {
        "reasons": reasons,
        "com_path_m": drift["com_ground_length_m"],
        "com_rmse_m": errors["com_rmse_m"],
        "rod_rotation_mean_deg": errors["rod_rotation_mean_deg"],
        "shape_error_mean_m": errors["shape_error_mean_m"],
        "shape_rmse_m": drift["shape_rmse_m"],
        "drift_percent": drift["drift_percent"],
        "nees_per_dof": round(nees_per_dof(run, estimates), 3),
        "reinitialisations": float(errors["reinitialisations"]),
        "finite": float(errors["finite"]),
        **floor,
    }


def _reduce(values: list[float], how: Any) -> float:
    """``how`` (np.mean, np.max) of the finite values, NaN where there is none."""
    finite = [v for v in values if np.isfinite(v)]
    return round(float(how(finite)), 4) if finite else float("nan")


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Means and maxima of the runs' figures, and their re-initialisations by reason."""
    keys = [k for k in rows[0] if k != "reasons"]
    reasons: dict[str, int] = {}
    for r in rows:
        for why, n in r["reasons"].items():
            reasons[why] = reasons.get(why, 0) + int(n)
    return {
        "mean": {k: _reduce([r[k] for r in rows], np.mean) for k in keys},
        "max": {k: _reduce([r[k] for r in rows], np.max) for k in keys},
        "reinitialisations_by_reason": reasons,
        "runs": len(rows),
    }


def _runs(
    motions: dict[str, tuple[str, str]], world: dict[str, Any], seeds: tuple[int, ...],
    steps: int, camera: bool,
) -> dict[tuple[str, int], RecordedRun]:  # fmt: skip
    """The world's recorded runs of each motion and seed."""
    return {
        (motion, seed): record_face_transition(
            env_id, seed, steps, gait=gait, camera=camera, calibration="true", **world
        )
        for motion, (env_id, gait) in motions.items()
        for seed in seeds
    }


def bench_cross_world(
    estimators: tuple[str, ...] = ("ukf", "ukf_exact_lengths", "ukf_large", "inekf", "icp"),
    worlds: tuple[str, ...] = tuple(WORLDS),
    seeds: tuple[int, ...] = (0, 1, 2),
    steps: int = 300,
) -> dict[str, Any]:
    """Each estimator on each world (:data:`WORLDS`), both motions, ``seeds``:
    ``rows[estimator][world]`` the means and maxima over the runs, ``by_motion`` the
    means per motion; the targets of :data:`CROSS_WORLD_TARGETS` checked on the worlds
    other than ``own``."""
    start = time.perf_counter()
    rows: dict[str, dict[str, Any]] = {e: {} for e in estimators}
    groups: dict[int, list[str]] = {}  # estimators sharing their runs
    for e in estimators:
        groups.setdefault(id(ESTIMATOR_ROBOTS[e]), []).append(e)
    for mine in groups.values():
        camera = any(e not in VARIANTS and estimator_spec(e).camera for e in mine)
        motions = ESTIMATOR_ROBOTS[mine[0]]
        for world in worlds:
            runs = _runs(motions, WORLDS[world], seeds, steps, camera)
            for e in mine:
                scores = {key: score_run(run, e, key[1]) for key, run in runs.items()}
                rows[e][world] = summary(list(scores.values())) | {
                    "by_motion": {
                        m: summary([s for (mm, _), s in scores.items() if mm == m])["mean"]
                        for m in motions
                    }
                }
    return {
        "seeds": list(seeds),
        "steps": steps,
        "rows": rows,
        "targets": _check_targets(rows),
        "wall_s": round(time.perf_counter() - start, 1),
    }


def _check_targets(rows: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per estimator with targets, per world but its own: each figure against it."""
    out: dict[str, dict[str, Any]] = {}
    for estimator, targets in CROSS_WORLD_TARGETS.items():
        for world, row in rows.get(estimator, {}).items():
            if world == "own":
                continue
            out.setdefault(estimator, {})[world] = {
                k: {"value": row["mean"][k], "target": v, "met": bool(row["mean"][k] <= v)}
                for k, v in targets.items()
            }
    return out
