"""Entry points of the registered envs: assemble backend, estimator and task by name."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from tensegrity_gym.envs.roll_env import TensegrityEnv
from tensegrity_gym.model.description import RobotDescription, load_robot
from tensegrity_gym.model.protocols import Estimator
from tensegrity_gym.tasks.roll import RollTask

if TYPE_CHECKING:
    from pathlib import Path

    from tensegrity_gym.model.protocols import Backend

__all__ = ["ESTIMATORS", "make_estimator", "make_roll_env"]

ESTIMATORS = ("oracle", "ukf")
"""Estimator names ``make`` accepts; more join as they are implemented."""


def make_estimator(name: str | Estimator, backend: Backend) -> Estimator:
    """An estimator by name, or the given object if it already is one."""
    if not isinstance(name, str):
        if not isinstance(name, Estimator):
            raise TypeError(
                f"estimator must be one of {list(ESTIMATORS)} or an object with "
                f"reset() and update(); got {type(name).__name__}"
            )
        return name
    if name == "oracle":
        from estimation.oracle import OracleEstimator

        if backend.ground_truth is None:  # pragma: no cover - every backend has the method
            raise ValueError("estimator='oracle' needs a backend with ground truth")
        return OracleEstimator(backend.ground_truth)
    if name == "ukf":
        from estimation.ukf import UkfEstimator

        return UkfEstimator()
    raise ValueError(f"unknown estimator {name!r}; valid choices: {list(ESTIMATORS)}")


def make_roll_env(
    robot: str | Path | RobotDescription = "three_bar",
    *,
    estimator: str | Estimator = "ukf",
    driver: Any = None,
    render_mode: str | None = None,
    goal_heading: float | None = 0.0,
    goal_distance: float | None = None,
    ctrl_cost: float = 0.05,
    spawn_radius: float = 0.0,
    control_period: float = 0.1,
    time_step: float = 0.001,
) -> TensegrityEnv:
    """Build a rolling env.

    Args:
        robot: a preset name, a YAML path or a loaded description.
        estimator: ``"ukf"`` (the unscented Kalman filter of papers/000, the default),
            ``"oracle"`` (ground truth, simulation only) or an Estimator object.
        driver: ``None`` for the PyBullet simulation. Hardware drivers are not part of
            this release; anything else is rejected.
        render_mode: ``None``, ``"rgb_array"`` or ``"human"`` (PyBullet's window).
        goal_heading, goal_distance, ctrl_cost: see :class:`RollTask`.
        spawn_radius: the start position is drawn within this radius (m).
        control_period, time_step: seconds per env step and per physics step.
    """
    description = robot if isinstance(robot, RobotDescription) else load_robot(robot)
    if driver is not None:
        raise ValueError(
            f"driver={driver!r}: no hardware driver is available in this release; "
            "use driver=None for the PyBullet simulation"
        )
    from tensegrity_gym.sim.backend import SimBackend

    est_name = estimator if isinstance(estimator, str) else None
    if est_name is not None and est_name not in ESTIMATORS:
        raise ValueError(f"unknown estimator {est_name!r}; valid choices: {list(ESTIMATORS)}")
    backend = SimBackend(
        description,
        control_period=control_period,
        time_step=time_step,
        gui=render_mode == "human",
        spawn_radius=spawn_radius,
    )
    est = make_estimator(estimator, backend)
    backend.camera = est.needs_camera
    task = RollTask(
        description, goal_heading=goal_heading, goal_distance=goal_distance, ctrl_cost=ctrl_cost
    )
    return TensegrityEnv(backend, est, task, render_mode=render_mode)
