"""What self-calibration costs the UKF (issue 15): the same recorded runs replayed with
the simulator's own UWB anchors and offsets and with the calibrator's, side by side.

Each run is recorded once with the truth's calibration (``calibration="true"``, world
seed 0); the estimated calibration is the one ``gym.make`` hands the estimators by
default in that world (:func:`tensegrity_gym.envs.calibration_run.estimated_uwb_calibration`, from
its calibration run, cached). Its estimates are in the lab's frame (the floor plan's),
which lies a turn about z and a shift along the floor away from the simulator's (the
anchors stand off the plan; both frames stand on the floor, z = 0 up): they are scored
after the turn and shift that take the calibrated anchors best onto the true ones
(evaluation only), and without it (``..._in_lab_frame``), which is what a policy sees.
A full rigid alignment (tilt and height too) would move the robot by the anchors'
height errors, although the estimators place it on the floor. Scenarios as Caluwaerts et al. 2016's
study
(:mod:`agents.benchmarks.estimation`): SUPERball's face transition and stationary actuation,
and the 3-bar robot rolling under its gait.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np

from agents.benchmarks.estimation import record_face_transition, record_stationary_actuation
from agents.recordings.runs import replay, trajectory_errors
from estimation.ukf import UkfEstimator
from tensegrity_gym.envs.calibration_run import estimated_uwb_calibration
from tensegrity_gym.model.kinematics import yaw_kabsch

if TYPE_CHECKING:
    from agents.recordings.runs import RecordedRun

__all__ = ["SCENARIOS", "bench_calibration_in_loop"]

SCENARIOS: dict[str, tuple[str, Any]] = {
    "superball face transition": ("tensegrity_gym/SuperBallRoll-v0", record_face_transition),
    "superball stationary actuation": (
        "tensegrity_gym/SuperBallRoll-v0",
        record_stationary_actuation,
    ),
    "three_bar face transition": ("tensegrity_gym/ThreeBarRoll-v0", record_face_transition),
}
"""Name: (env id, recorder(env_id, seed, steps, **make_kwargs))."""


def _com_rmse(run: RecordedRun, motion: tuple[Any, Any] | None = None) -> float:
    """The UKF's CoM RMSE on ``run``, its estimates moved by ``motion`` (R, t) first."""
    estimates = replay(run, UkfEstimator())
    if motion is not None:
        R, t = motion
        estimates = [
            replace(e, node_positions=e.node_positions @ R.T + t, com=e.com @ R.T + t)
            for e in estimates
        ]
    return float(trajectory_errors(run, estimates)["com_rmse_m"])


def _scenario_row(
    name: str, seeds: tuple[int, ...], steps: int, world_seeds: tuple[int, ...]
) -> dict[str, Any]:
    """One scenario over every world and seed: mean CoM RMSEs and the ratio, with each
    world's ratio beside them (a world's calibration is one draw of its errors)."""
    env_id, record = SCENARIOS[name]
    true_rmse, estimated_rmse, lab_rmse, per_world = [], [], [], []
    for world in world_seeds:
        t_world, e_world = [], []
        for seed in seeds:
            run = record(env_id, seed, steps, calibration="true", world_seed=world)
            lab = estimated_uwb_calibration(run.description, world_seed=world)
            calibrated = replace(run, calibration=lab.applied_to(run.calibration))
            motion = yaw_kabsch(lab.anchors, run.calibration.anchors)
            t_world.append(_com_rmse(run))
            e_world.append(_com_rmse(calibrated, motion))
            lab_rmse.append(_com_rmse(calibrated))
        true_rmse += t_world
        estimated_rmse += e_world
        per_world.append(round(float(np.mean(e_world) / np.mean(t_world)), 3))
    t, e = float(np.mean(true_rmse)), float(np.mean(estimated_rmse))
    return {
        "scenario": name,
        "com_rmse_true_calibration_m": round(t, 4),
        "com_rmse_estimated_calibration_m": round(e, 4),
        "estimated_over_true": round(e / t, 3) if t > 0 else None,
        "estimated_over_true_per_world": per_world,
        "com_rmse_estimated_calibration_in_lab_frame_m": round(float(np.mean(lab_rmse)), 4),
    }


def bench_calibration_in_loop(
    seeds: tuple[int, ...] = (0, 1), steps: int = 200, world_seeds: tuple[int, ...] = (0, 1, 2)
) -> dict[str, Any]:
    """Per scenario: the UKF's CoM RMSE (m, mean over ``seeds`` in each of the worlds
    ``world_seeds``, each with its own calibration) with the true and with the estimated
    calibration, and their ratio (target: at most 1.1)."""
    rows = [_scenario_row(name, seeds, steps, world_seeds) for name in SCENARIOS]
    return {"world_seeds": list(world_seeds), "seeds": list(seeds), "rows": rows,
            "targets": {"estimated_over_true": 1.1}}  # fmt: skip
