"""A native vector env: N robots of one id in one process, as a Gymnasium ``VectorEnv``.

``gym.make_vec(ID, num_envs=N, vectorization_mode="vector_entry_point")`` (or
``make_vector_env``) builds N envs of the id, each with its own world (PyBullet client
or MuJoCo model and data) and estimator, and steps them as one: a batched observation
(N, obs), rewards, terminations and truncations (N,), and Gymnasium's vector ``infos``.
An env whose episode ended is reset as Gymnasium's vector envs do
(``autoreset_mode``): at its next step (``NEXT_STEP``, the default: that step's action is
ignored, its reward 0) or at once (``SAME_STEP``: the last observation and info are in
``infos["final_obs"]`` and ``infos["final_info"]``, what SB3's adapter,
:class:`agents.training.vec_env.Sb3VecEnv`, needs).

Env i is the single env of the same id reset with seed ``seed + i``: the vector env's
episodes are those of N single envs, bit for bit (tested).
"""

from __future__ import annotations

from copy import deepcopy
from typing import TYPE_CHECKING, Any

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space, concatenate, create_empty_array, iterate

from tensegrity_gym.envs.factory import make_env

if TYPE_CHECKING:
    from collections.abc import Sequence

    from numpy.typing import NDArray

    from tensegrity_gym.envs.tensegrity_env import TensegrityEnv

__all__ = ["TensegrityVectorEnv", "make_vector_env"]

_StepResult = tuple[Any, Any, Any, Any, dict[str, Any]]
"""Batched observations (N, obs), rewards (N,), terminations and truncations (N,), infos."""


class TensegrityVectorEnv(VectorEnv[Any, Any, Any]):
    """``num_envs`` envs made by :func:`~tensegrity_gym.envs.factory.make_env` with the
    same ``make_kwargs``, stepped as one.

    Args:
        num_envs: how many robots, >= 1.
        max_episode_steps: an episode is truncated after this many steps (the id's
            limit, as ``gym.make`` applies it); None: never.
        autoreset_mode: ``AutoresetMode.NEXT_STEP`` (default) or ``SAME_STEP``, as
            Gymnasium's vector envs take it (a string works too).
        make_kwargs: ``make_env``'s arguments (the id's ``robot`` and ``task``, and any
            other ``gym.make`` argument: ``engine``, ``estimator``...).
    """

    def __init__(
        self,
        num_envs: int,
        *,
        max_episode_steps: int | None = None,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        **make_kwargs: Any,
    ) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"make_vec: num_envs={num_envs!r} must be an int >= 1")
        mode = AutoresetMode(autoreset_mode)
        if mode == AutoresetMode.DISABLED:
            raise ValueError("make_vec: autoreset_mode must be 'NextStep' or 'SameStep'")
        self.envs: list[TensegrityEnv] = []
        try:
            for _ in range(num_envs):
                self.envs.append(make_env(**make_kwargs))
        except BaseException:
            for env in self.envs:
                env.close()
            raise
        first = self.envs[0]
        self.num_envs = num_envs
        self.max_episode_steps = max_episode_steps
        self.autoreset_mode = mode
        self.metadata = {**first.metadata, "autoreset_mode": mode}
        self.render_mode = first.render_mode
        self.single_observation_space = first.observation_space
        self.single_action_space = first.action_space
        self.observation_space = batch_space(first.observation_space, num_envs)
        self.action_space = batch_space(first.action_space, num_envs)
        self._observations: Any = create_empty_array(first.observation_space, num_envs)
        self._env_obs: list[Any] = [None] * num_envs
        self._rewards = np.zeros(num_envs, dtype=np.float64)
        self._terminations = np.zeros(num_envs, dtype=np.bool_)
        self._truncations = np.zeros(num_envs, dtype=np.bool_)
        self._elapsed = np.zeros(num_envs, dtype=np.int64)
        self._autoreset = np.zeros(num_envs, dtype=np.bool_)

    def reset(
        self,
        *,
        seed: int | Sequence[int | None] | None = None,
        options: dict[str, Any] | None = None,
    ) -> tuple[Any, dict[str, Any]]:
        """Reset every env: env i with ``seed + i`` (an int), ``seed[i]`` (a list) or its
        own generator (None); ``options`` go to each."""
        seeds = _seeds(seed, self.num_envs)
        infos: dict[str, Any] = {}
        for i, (env, s) in enumerate(zip(self.envs, seeds, strict=True)):
            self._env_obs[i], info = env.reset(seed=s, options=options)
            infos = self._add_info(infos, info, i)
        self._elapsed[:] = 0
        self._autoreset[:] = False
        return self._batch(), infos

    def step(
        self, actions: NDArray[np.float32]
    ) -> tuple[
        NDArray[np.float32],
        NDArray[np.float64],
        NDArray[np.bool_],
        NDArray[np.bool_],
        dict[str, Any],
    ]:
        """Step every env with its row of ``actions`` (N, act); reset those whose
        episode ended, as :attr:`autoreset_mode` says."""
        infos: dict[str, Any] = {}
        for i, action in enumerate(iterate(self.action_space, actions)):
            if self.autoreset_mode == AutoresetMode.NEXT_STEP and self._autoreset[i]:
                info = self._reset_one(i)
                self._rewards[i], self._terminations[i], self._truncations[i] = 0.0, False, False
            else:
                info = self._step_one(i, action)
                if self.autoreset_mode == AutoresetMode.SAME_STEP and self._ended(i):
                    final = {"final_obs": self._env_obs[i], "final_info": info}
                    infos = self._add_info(infos, final, i)
                    info = self._reset_one(i)
            infos = self._add_info(infos, info, i)
        self._autoreset = self._terminations | self._truncations
        return (
            self._batch(),
            self._rewards.copy(),
            self._terminations.copy(),
            self._truncations.copy(),
            infos,
        )

    def _step_one(self, i: int, action: Any) -> dict[str, Any]:
        """Step env i; truncate at :attr:`max_episode_steps`. Returns its info."""
        obs, reward, terminated, truncated, info = self.envs[i].step(action)
        self._elapsed[i] += 1
        limit = self.max_episode_steps
        truncated = bool(truncated) or (limit is not None and self._elapsed[i] >= limit)
        self._env_obs[i], self._rewards[i] = obs, reward
        self._terminations[i], self._truncations[i] = terminated, truncated
        return info

    def _reset_one(self, i: int) -> dict[str, Any]:
        """Reset env i from its own generator (no new seed). Returns its info."""
        self._env_obs[i], info = self.envs[i].reset()
        self._elapsed[i] = 0
        return info

    def _ended(self, i: int) -> bool:
        return bool(self._terminations[i] or self._truncations[i])

    def _batch(self) -> Any:
        self._observations = concatenate(
            self.single_observation_space, self._env_obs, self._observations
        )
        return deepcopy(self._observations)

    def render(self) -> tuple[Any, ...] | None:
        """Each env's frame (``render_mode="rgb_array"``), or None."""
        if self.render_mode != "rgb_array":
            return None
        return tuple(env.render() for env in self.envs)

    def close_extras(self, **kwargs: Any) -> None:
        """Close every env (their worlds, estimators and recordings)."""
        for env in self.envs:
            env.close()


def _seeds(seed: int | Sequence[int | None] | None, n: int) -> list[int | None]:
    """Each env's reset seed: ``seed + i``, the list's, or None for all."""
    if seed is None:
        return [None] * n
    if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
        return [int(seed) + i for i in range(n)]
    seeds = list(seed)  # type: ignore[arg-type]
    if len(seeds) != n:
        raise ValueError(f"reset: {len(seeds)} seeds given for {n} envs")
    return seeds


def make_vector_env(num_envs: int = 1, **kwargs: Any) -> TensegrityVectorEnv:
    """The vector entry point of every simulated id (``gym.make_vec``): see
    :class:`TensegrityVectorEnv`."""
    return TensegrityVectorEnv(num_envs, **kwargs)
