"""SB3's ``VecEnv`` over a Gymnasium vector env: ``PPO("MlpPolicy", Sb3VecEnv(vec))``.

SB3 keeps its own vector API (a list of infos, ``dones``, the last observation in
``info["terminal_observation"]``, a reset at once). :class:`Sb3VecEnv` speaks it over a
Gymnasium ``VectorEnv`` that resets in the same step
(``gym.make_vec(ID, num_envs=N, vectorization_mode="vector_entry_point",
autoreset_mode="SameStep")``), so that the native vector env of
:mod:`tensegrity_gym.envs.vector` trains with SB3 as ``DummyVecEnv`` would over N single
envs, with the same episodes.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.vec_env import VecEnv

if TYPE_CHECKING:
    import gymnasium as gym
    from numpy.typing import NDArray
    from stable_baselines3.common.vec_env.base_vec_env import VecEnvObs, VecEnvStepReturn

__all__ = ["Sb3VecEnv"]


class Sb3VecEnv(VecEnv):
    """SB3's vector API over ``vector_env``, a Gymnasium ``VectorEnv`` whose
    ``metadata["autoreset_mode"]`` is ``SAME_STEP`` and which holds its single envs in
    ``envs`` (for ``get_attr``, ``set_attr`` and ``env_method``)."""

    def __init__(self, vector_env: gym.vector.VectorEnv[Any, Any, Any]) -> None:
        mode = vector_env.metadata.get("autoreset_mode")
        if mode != AutoresetMode.SAME_STEP:
            raise ValueError(
                f"Sb3VecEnv needs a vector env that resets in the same step "
                f"(autoreset_mode='SameStep'), got {mode!r}"
            )
        self.vector_env = vector_env
        super().__init__(
            vector_env.num_envs,
            vector_env.single_observation_space,
            vector_env.single_action_space,
        )
        self._actions: NDArray[Any] | None = None

    def reset(self) -> VecEnvObs:
        seeds: Any = list(self._seeds)  # one per env (Gymnasium's vector envs take a list)
        options = self._options[0] if self._options and self._options[0] else None
        if any(o != self._options[0] for o in self._options):
            raise ValueError("Sb3VecEnv: the vector env takes one set of reset options")
        obs, infos = self.vector_env.reset(seed=seeds, options=options)
        self.reset_infos = _per_env(infos, self.num_envs)
        self._reset_seeds()
        self._reset_options()
        return obs  # type: ignore[no-any-return]

    def step_async(self, actions: NDArray[Any]) -> None:
        self._actions = actions

    def step_wait(self) -> VecEnvStepReturn:
        obs, rewards, terminated, truncated, infos = self.vector_env.step(self._actions)
        dones = terminated | truncated
        per_env = _per_env(infos, self.num_envs)
        # As DummyVecEnv: an ended env's info is its last step's, the last observation in
        # it; the new episode's first info goes to reset_infos.
        final_info = _per_env(infos.get("final_info", {}), self.num_envs)
        for ended in np.flatnonzero(dones).tolist():
            self.reset_infos[ended] = per_env[ended]
            per_env[ended] = final_info[ended]
            per_env[ended]["terminal_observation"] = infos["final_obs"][ended]
        for i, info in enumerate(per_env):
            info["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
        return obs, rewards.astype(np.float32), dones, per_env

    def close(self) -> None:
        self.vector_env.close()

    def _envs(self, indices: Any) -> list[Any]:
        envs = self.vector_env.envs  # type: ignore[attr-defined]
        return [envs[i] for i in self._get_indices(indices)]

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        return [getattr(env, attr_name) for env in self._envs(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        for env in self._envs(indices):
            setattr(env, attr_name, value)

    def env_method(
        self, method_name: str, *method_args: Any, indices: Any = None, **method_kwargs: Any
    ) -> list[Any]:
        return [
            getattr(env, method_name)(*method_args, **method_kwargs) for env in self._envs(indices)
        ]

    def env_is_wrapped(self, wrapper_class: type[Any], indices: Any = None) -> list[bool]:
        return [isinstance(env, wrapper_class) for env in self._envs(indices)]


def _per_env(infos: dict[str, Any], n: int) -> list[dict[str, Any]]:
    """Gymnasium's vector ``infos`` (a value array and a ``_key`` mask per key) as a dict
    per env; ``final_obs`` and ``final_info`` left out (SB3 has its own)."""
    out: list[dict[str, Any]] = [{} for _ in range(n)]
    for key, values in infos.items():
        if key.startswith("_") or key in ("final_obs", "final_info"):
            continue
        mask = infos.get(f"_{key}", np.ones(n, dtype=bool))
        for i in range(n):
            if mask[i]:
                out[i][key] = _item(values, i)
    return out


def _item(values: Any, i: int) -> Any:
    """Env i's value of one key: a nested dict's entries, or the array's row."""
    if isinstance(values, dict):
        mask_of: dict[str, Any] = {k: values.get(f"_{k}") for k in values if not k.startswith("_")}
        return {
            k: _item(v, i)
            for k, v in values.items()
            if not k.startswith("_") and (mask_of[k] is None or mask_of[k][i])
        }
    if isinstance(values, (np.ndarray, Sequence)) and not isinstance(values, str):
        return values[i]
    return values
