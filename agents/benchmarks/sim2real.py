"""Sim-to-real figures (issue 16): the UKF as the world departs from its model, and
system identification of a robot whose description is off.

``bench_randomized_ukf``: the 3-bar robot rolling under its gait, recorded in worlds
drawn from no, the mild and the strong randomisation (the same seeds), the UKF replayed
on each with the nominal description and the simulator's own UWB calibration (so that
the model's mismatch is all that differs): CoM RMSE, NEES per degree of freedom of the
node positions against its chi-square band, divergences and re-initialisations.

``bench_identify``: a bag of the 3-bar gait recorded with the description's parameter
groups off by up to 30 %, identified from the nominal description (fitted to its IMU
readings, and to its node positions alone, as for a bag without IMU): each factor
found against the truth, the open-loop CoM error over 2 s segments before and after,
the wall time; and the UKF's spring-mass model fitted to the same recording.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.stats

from agents.benchmarks.cross_world import nees_per_dof
from agents.benchmarks.estimation import record_face_transition
from agents.identification.identify import (
    MAX_EVALUATIONS,
    Identification,
    apply_parameters,
    factor_names,
    identify_run,
)
from agents.identification.imu import without_imu
from agents.recordings.runs import replay
from estimation.ukf import UkfEstimator
from hardware.recording import MemorySink, RecordingBackend
from tensegrity_gym.envs.factory import make_env
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.tasks.gaits import FaceGait

if TYPE_CHECKING:
    from hardware.recording import RecordedRun

__all__ = ["PERTURBATION", "TARGETS", "bench_identify", "bench_randomized_ukf"]

TARGETS = {
    "mild_over_nominal_com_rmse": 1.5,
    "identified_factor_error": 0.05,
    "open_loop_error_reduction": 5.0,
    "identify_seconds_60s_bag": 600.0,
}
"""Issue 16's figures to reach."""

PERTURBATION = {
    "actuated_stiffness": 1.3,
    "passive_stiffness": 0.7,
    "damping": 0.7,
    "passive_rest_length": 1.03,
    "friction": 0.7,
    "motor_speed": 1.3,
}
"""The recorded robot's factors against the nominal description (rest lengths by 3 %:
by 30 % the prism would not hold its shape)."""


def _ukf_figures(run: RecordedRun, settle: float = 2.0) -> dict[str, float]:
    estimates = replay(run, UkfEstimator())
    t0 = estimates[0].t
    com = [
        float(np.linalg.norm(e.com - step.truth.com))
        for e, step in zip(estimates[1:], run.steps, strict=True)
        if step.truth is not None and e.t - t0 >= settle and e.covariance is not None
    ]
    return {
        "com_rmse_m": float(np.sqrt(np.mean(np.square(com)))),
        "nees_per_dof": nees_per_dof(run, estimates, settle),
        "reinitialisations": float(sum(e.reinitialised for e in estimates[1:])),
        "unhealthy_steps": float(sum(not e.healthy for e in estimates[1:])),
    }


def bench_randomized_ukf(seeds: tuple[int, ...] = (0, 1, 2), steps: int = 200) -> dict[str, Any]:
    """Per randomisation (none, mild, strong): the UKF's figures, mean over ``seeds``."""
    rows = {}
    n_dof = 3 * load_robot("three_bar").n_nodes
    low, high = scipy.stats.chi2.ppf([0.025, 0.975], len(seeds) * n_dof) / (len(seeds) * n_dof)
    for name in (None, "mild", "strong"):
        figures = [
            _ukf_figures(
                record_face_transition(
                    "tensegrity_gym/ThreeBarRoll-v0",
                    seed,
                    steps,
                    calibration="true",
                    randomization=name,
                )
            )
            for seed in seeds
        ]
        rows[name or "nominal"] = {
            key: round(float(np.mean([f[key] for f in figures])), 4) for key in figures[0]
        } | {"reinitialisations": int(sum(f["reinitialisations"] for f in figures))}
    nominal = rows["nominal"]["com_rmse_m"]
    return {
        "seeds": list(seeds),
        "steps": steps,
        "rows": rows,
        "mild_over_nominal_com_rmse": round(rows["mild"]["com_rmse_m"] / nominal, 3),
        "strong_over_nominal_com_rmse": round(rows["strong"]["com_rmse_m"] / nominal, 3),
        "nees_band_per_dof": [round(float(low), 3), round(float(high), 3)],
        "targets": {"mild_over_nominal_com_rmse": TARGETS["mild_over_nominal_com_rmse"]},
    }


def _perturbed_run(seconds: float, seed: int) -> RecordedRun:
    """``seconds`` of the 3-bar gait by a robot whose factors are :data:`PERTURBATION`."""
    nominal = load_robot("three_bar")
    names = list(PERTURBATION)
    robot = apply_parameters(nominal, names, np.log([PERTURBATION[n] for n in names]))
    env = make_env(robot, estimator="oracle", calibration="true")
    sink = MemorySink()
    env.backend = RecordingBackend(env.backend, sink)
    obs, _ = env.reset(seed=seed)
    gait = FaceGait(robot, env.task)
    for _ in range(round(seconds / env.backend.control_period)):
        obs, *_ = env.step(gait(obs))
    env.close()
    return sink.run


def _identify_figures(result: Identification, wall: float) -> dict[str, Any]:
    """Each factor found against :data:`PERTURBATION`, the open-loop CoM error before and
    after, the evaluations and the wall time (s) of one fit."""
    factors = {
        name: {
            "true": PERTURBATION[name],
            "found": round(float(f), 4),
            "error": round(float(f / PERTURBATION[name] - 1.0), 4),
        }
        for name, f in zip(result.names, result.factors, strict=True)
    }
    before, after = float(result.com_before.mean()), float(result.com_after.mean())
    return {
        "imu_windows": len(result.imu_before),
        "evaluations": result.evaluations,
        "identify_seconds": round(wall, 1),
        "factors": factors,
        "largest_factor_error": max(abs(f["error"]) for f in factors.values()),
        "open_loop_com_error_m": {"before": round(before, 4), "after": round(after, 4)},
        "open_loop_error_reduction": round(before / after, 2) if after > 0 else None,
    }


def bench_identify(
    seconds: float = 60.0,
    seed: int = 0,
    max_evaluations: int = MAX_EVALUATIONS,
    nodes_only: bool = True,
) -> dict[str, Any]:
    """Identification of a robot :data:`PERTURBATION` away from the description, fitted
    to its IMU readings; with ``nodes_only``, also the same bag without its IMU topic,
    fitted to its node positions alone."""
    nominal = load_robot("three_bar")
    run = _perturbed_run(seconds, seed)
    groups = ["stiffness", "damping", "rest", "friction", "motor"]
    assert factor_names(groups, nominal) == list(PERTURBATION)
    fits = {}
    bags = {"imu": run, "nodes_only": without_imu(run)}
    for name in ("imu", "nodes_only") if nodes_only else ("imu",):
        clock = time.perf_counter()
        result = identify_run(bags[name], groups, description=nominal,
                              max_evaluations=max_evaluations)  # fmt: skip
        fits[name] = _identify_figures(result, time.perf_counter() - clock)
    ukf = identify_run(
        run,
        ["stiffness", "damping"],
        description=nominal,
        model="ukf",
        max_evaluations=max_evaluations // 4,
    )
    return {
        "bag_seconds": seconds,
        "segments": len(ukf.segments),
        **fits.pop("imu"),
        **({"nodes_only": fits["nodes_only"]} if fits else {}),
        "ukf_model": {
            "factors": dict(zip(ukf.names, np.round(ukf.factors, 4).tolist(), strict=True)),
            "open_loop_com_error_m": {
                "before": round(float(ukf.com_before.mean()), 4),
                "after": round(float(ukf.com_after.mean()), 4),
            },
        },
        "targets": {k: v for k, v in TARGETS.items() if k != "mild_over_nominal_com_rmse"},
    }
