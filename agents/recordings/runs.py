"""Recorded runs in memory: what a backend produced, replayed through any estimator.

An estimator study runs every variant on the same samples (as Caluwaerts et al. 2016 does), so the
run is recorded once, by a wrapper around the env's backend, and replayed after.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, cast

import gymnasium as gym
import numpy as np

import tensegrity_gym  # noqa: F401  (registers the envs)
from estimation.metrics import com_errors, rod_errors, shape_errors
from hardware.recording import MemorySink, RecordedRun, RecordingBackend

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

    from numpy.typing import NDArray

    from tensegrity_gym.envs.tensegrity_env import TensegrityEnv
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.estimate import Estimate
    from tensegrity_gym.model.protocols import Estimator
    from tensegrity_gym.model.samples import GroundTruth

__all__ = [
    "RecordedRun",
    "estimation_errors",
    "record_run",
    "replay",
    "trajectory_errors",
]


def record_run(
    env_id: str,
    policy: Callable[[TensegrityEnv, NDArray[np.float32], int], NDArray[np.float32]],
    steps: int,
    seed: int = 0,
    camera: bool = False,
    **make_kwargs: Any,
) -> RecordedRun:
    """Run ``policy(env, observation, step)`` for ``steps`` control steps; keep everything.

    The env runs with the oracle so that the recorded samples do not depend on any
    estimator; estimators are replayed on them afterwards. ``camera`` records RGB-D
    frames too.
    """
    env = gym.make(env_id, estimator="oracle", max_episode_steps=steps + 1, **make_kwargs)
    inner = cast("TensegrityEnv", env.unwrapped)
    sink = MemorySink()
    inner.backend.camera = camera  # type: ignore[attr-defined]
    inner.backend = RecordingBackend(inner.backend, sink)
    obs, _ = env.reset(seed=seed)
    for k in range(steps):
        obs, _, terminated, truncated, _ = env.step(policy(inner, obs, k))
        if terminated or truncated:
            break
    env.close()
    return sink.run


def replay(
    run: RecordedRun,
    estimator: Estimator,
    seed: int = 0,
    on_update: Callable[[], None] | None = None,
) -> list[Estimate]:
    """The estimates ``estimator`` gives on the recorded samples: the start, then one a step."""
    rng = np.random.default_rng(seed)
    start = run.start
    out = [estimator.reset(run.description, run.calibration, start.samples, start.command, rng)]
    for step in run.steps:
        out.append(estimator.update(step.samples, step.command))
    return out


def trajectory_errors(
    run: RecordedRun, estimates: Sequence[Estimate], settle: float = 2.0
) -> dict[str, Any]:
    """:func:`estimation_errors` of ``estimates`` replayed on ``run``."""
    truths = [run.start.truth] + [s.truth for s in run.steps]
    return estimation_errors(run.description, estimates, truths, settle)


def estimation_errors(
    description: RobotDescription,
    estimates: Sequence[Estimate],
    truths: Sequence[GroundTruth | None],
    settle: float = 2.0,
) -> dict[str, Any]:
    """CoM, node, rod and shape errors of ``estimates`` against the truth of the same
    steps, after ``settle`` s (:mod:`estimation.metrics`); steps without truth are left out."""
    t0 = estimates[0].t
    pairs = [
        (est, truth)
        for est, truth in zip(estimates, truths, strict=True)
        if truth is not None and est.t - t0 >= settle
    ]
    if not pairs:
        raise ValueError("no step with ground truth after the settling time")
    est_nodes = np.array([e.node_positions for e, _ in pairs])
    true_nodes = np.array([t.node_positions for _, t in pairs])
    com = com_errors(np.array([e.com for e, _ in pairs]), np.array([t.com for _, t in pairs]))
    nodes = np.linalg.norm(est_nodes - true_nodes, axis=-1)
    rods = rod_errors(est_nodes, true_nodes, description.rod_nodes)
    return {
        "com_rmse_m": round(float(np.sqrt(np.mean(com**2))), 4),
        "com_max_m": round(float(com.max()), 4),
        "node_rmse_m": round(float(np.sqrt(np.mean(nodes**2))), 4),
        "node_max_m": round(float(nodes.max()), 4),
        "rod_translation_mean_m": round(float(rods.translation.mean()), 4),
        "rod_rotation_mean_deg": round(float(np.degrees(rods.rotation.mean())), 2),
        "rods_within_2cm_5deg": round(rods.share_within(), 3),
        "shape_error_mean_m": round(float(shape_errors(est_nodes, true_nodes).mean()), 4),
        "finite": bool(all(e.is_finite() for e in estimates)),
        "reinitialisations": int(sum(e.reinitialised for e in estimates)),
        "steps_scored": len(pairs),
    }
