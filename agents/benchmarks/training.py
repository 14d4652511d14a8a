"""Where a training run's time goes: PPO and SAC with the UKF in the loop.

Each algorithm trains through :func:`agents.training.train.train` (its shipped config,
one env in this process), with :class:`TimeShares` timing, inside the same run, the
physics (the world's ``advance``: the engine and the cable forces), the sensor models
(the backend's sampling), the estimator's ``update`` and the policy update (the
algorithm's ``train``); the rest is the env's own Python (task, observation, wrappers),
the policy's inference and SB3's buffers. The env steps a second are set against the
1,000 that a million-step run in a few hours on 2 cores would need.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from stable_baselines3.common.callbacks import BaseCallback

if TYPE_CHECKING:
    from collections.abc import Callable

__all__ = ["TARGET_ENV_STEPS_PER_S", "TimeShares", "bench_training"]

TARGET_ENV_STEPS_PER_S = 1000.0
"""Training throughput with the UKF in the loop that the learning issue asks for."""

_BUDGET: dict[str, dict[str, Any]] = {
    "ppo": {"n_steps": 512, "batch_size": 128},
    "sac": {"learning_starts": 256},
}
"""Hyperparameters put over the shipped config so that a short run updates the policy
in proportion to its steps (PPO: a rollout of 512 steps; SAC: updates from step 256,
not 2,000); the rest is the config's."""

PARTS = ("physics", "sensors", "estimator", "policy_update")
"""What :class:`TimeShares` times, beside the whole."""


class TimeShares(BaseCallback):
    """Times the parts of :data:`PARTS` while a run learns (its one env in this
    process), by wrapping the methods that do them; ``seconds`` holds each part's and
    the whole's (``total``) wall time once learning ends."""

    def __init__(self) -> None:
        super().__init__()
        self.seconds: dict[str, float] = dict.fromkeys((*PARTS, "total"), 0.0)
        self._undo: list[Callable[[], None]] = []
        self._start = 0.0

    def _wrap(self, owner: Any, name: str, part: str) -> None:
        method = getattr(owner, name)
        seconds = self.seconds

        def timed(*args: Any, **kwargs: Any) -> Any:
            start = time.perf_counter()
            try:
                return method(*args, **kwargs)
            finally:
                seconds[part] += time.perf_counter() - start

        setattr(owner, name, timed)
        self._undo.append(lambda: delattr(owner, name))

    def _on_training_start(self) -> None:
        venv: Any = self.training_env
        while hasattr(venv, "venv"):  # VecNormalize and the like over the DummyVecEnv
            venv = venv.venv
        env = venv.envs[0].unwrapped
        backend = env.backend
        self._wrap(backend.world, "advance", "physics")
        self._wrap(backend, "_sample", "sensors")
        self._wrap(env.estimator, "update", "estimator")
        self._wrap(self.model, "train", "policy_update")
        self._start = time.perf_counter()

    def _on_step(self) -> bool:
        return True

    def _on_training_end(self) -> None:
        self.seconds["total"] = time.perf_counter() - self._start
        for undo in reversed(self._undo):
            undo()
        self._undo.clear()


def _row(algo: str, env_id: str, estimator: str, steps: int, seed: int) -> dict[str, Any]:
    """One algorithm's run: env steps a second and each part's share of the wall time."""
    from agents.training.train import train

    shares = TimeShares()
    with tempfile.TemporaryDirectory(prefix="tensegrity-bench-train-") as out:
        train(env_id, algo, estimator, Path(out), timesteps=steps, seed=seed, n_envs=1,
              hyperparams=_BUDGET[algo], progress_bar=False, checkpoint_every=10 * steps,
              callbacks=[shares])  # fmt: skip
    total = shares.seconds["total"]
    parts = {p: round(shares.seconds[p] / total, 3) for p in PARTS}
    parts["rest"] = round(1.0 - sum(parts.values()), 3)
    return {
        "env_steps_per_s": round(steps / total, 1),
        "wall_s": round(total, 1),
        "shares": parts,
        "over_target": round(steps / total / TARGET_ENV_STEPS_PER_S, 3),
        "budget_hyperparams": _BUDGET[algo],
    }


def bench_training(
    algos: tuple[str, ...] = ("ppo", "sac"),
    steps: int = 4096,
    env_id: str = "tensegrity_gym/ThreeBarRoll-v0",
    estimator: str = "ukf",
    seed: int = 0,
) -> dict[str, Any]:
    """Each algorithm trained ``steps`` env steps on ``env_id`` with ``estimator`` in the
    loop, one env in this process: its env steps a second, the share of the wall time
    in physics, sensors, estimator, policy update and the rest, and the ratio to
    :data:`TARGET_ENV_STEPS_PER_S`."""
    rows = {algo: _row(algo, env_id, estimator, steps, seed) for algo in algos}
    return {
        "env_id": env_id,
        "estimator": estimator,
        "steps": steps,
        "rows": rows,
        "target_env_steps_per_s": TARGET_ENV_STEPS_PER_S,
    }
