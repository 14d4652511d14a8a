"""The demo: a scripted rolling gait on the 3-bar robot, with a plot of where it went."""

from __future__ import annotations

import json
import logging
from typing import TYPE_CHECKING, Any, cast

import gymnasium as gym
import numpy as np

import tensegrity_gym  # noqa: F401  (registers the envs)
from agents.plots import plot_com_paths
from tensegrity_gym.tasks.gaits import FaceGait

if TYPE_CHECKING:
    from pathlib import Path

    from tensegrity_gym.envs.roll_env import TensegrityEnv

log = logging.getLogger(__name__)

__all__ = ["run_gait"]


def run_gait(
    env_id: str = "tensegrity_gym/ThreeBarRoll-v0",
    *,
    steps: int = 300,
    seed: int = 0,
    estimator: str = "ukf",
    out: Path | None = None,
) -> dict[str, Any]:
    """Roll the robot with its scripted gait for ``steps`` control steps.

    Returns a summary (start and end of the true CoM, distance, support-face changes)
    and, if ``out`` is given, writes ``com_path.png`` and ``summary.json`` there.
    """
    env = gym.make(env_id, estimator=estimator, max_episode_steps=steps)
    inner = cast("TensegrityEnv", env.unwrapped)
    gait = FaceGait(inner.backend.description, inner.task)
    obs, info = env.reset(seed=seed)
    true_path = [info["com_true"]]
    errors = [info["estimation_error"]]
    est_path = [info["com_estimate"]]
    faces = [gait.support_face(obs)]
    diverged = False
    for _ in range(steps):
        obs, _, terminated, truncated, info = env.step(gait(obs))
        est_path.append(info["com_estimate"])
        if "com_true" in info:
            true_path.append(info["com_true"])
            errors.append(info["estimation_error"])
        face = gait.support_face(obs)
        if face != faces[-1]:
            faces.append(face)
        if terminated or truncated:
            diverged = bool(info.get("sim_diverged", False))
            break
    env.close()
    path = np.array(true_path)
    start, end = path[0], path[-1]
    summary: dict[str, Any] = {
        "env": env_id,
        "seed": seed,
        "steps": len(est_path) - 1,
        "seconds": (len(est_path) - 1) * inner.backend.control_period,
        "com_start": start.round(4).tolist(),
        "com_end": end.round(4).tolist(),
        "distance": float(np.linalg.norm(end[:2] - start[:2])),
        "path_length": float(np.linalg.norm(np.diff(path[:, :2], axis=0), axis=1).sum()),
        "face_changes": len(faces) - 1,
        "estimator": estimator,
        "estimation_error_rms": float(np.sqrt(np.mean(np.square(errors)))),
        "estimation_error_max": float(np.max(errors)),
        "diverged": diverged,
    }
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        plot_com_paths(path, np.array(est_path), out / "com_path.png", env_id.split("/")[-1])
        (out / "summary.json").write_text(json.dumps(summary, indent=2))
        summary["plot"] = str(out / "com_path.png")
    return summary
