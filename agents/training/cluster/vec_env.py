"""SB3's ``VecEnv`` over Ray actors: a training run's envs spread over a cluster.

Each worker is a Ray actor holding a few envs (built from the env id, as ``train``
builds them, the estimator included) in a ``DummyVecEnv`` and stepping them where it
runs; per step it receives its envs' actions and returns their observations, rewards,
dones and infos as numpy arrays. The learner, ``VecNormalize`` and the Monitor log stay
in the training process.

Env ``i`` of the run (over all workers) is reset with seed ``seed + i``, as
``make_vec_env`` seeds a single-machine run, so a run is reproducible for a given
number of envs whatever the number of workers.

A worker that dies (its node lost, its process killed) is restarted by Ray, up to
``max_restarts`` times; the current episodes of its envs end there, truncated, with
``info["worker_restarted"] = True`` and their last observation as
``info["terminal_observation"]`` (the step they were given is lost: reward 0), and its
envs start new episodes from seeds drawn from the run's seed, the worker's index and the
restart count. :attr:`RayVecEnv.restarts` counts them.
"""

from __future__ import annotations

import logging
import os
import time
from functools import partial
from typing import TYPE_CHECKING, Any

import numpy as np
from gymnasium import spaces as gym_spaces
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv

from agents.training.cluster import require_ray

if TYPE_CHECKING:
    from collections.abc import Sequence

    import gymnasium as gym
    from numpy.typing import NDArray
    from stable_baselines3.common.vec_env.base_vec_env import (
        VecEnvIndices,
        VecEnvObs,
        VecEnvStepReturn,
    )

__all__ = ["EnvWorker", "RayVecEnv"]

log = logging.getLogger(__name__)

START_TIMEOUT_S = 600.0
"""How long the workers may take to start and build their envs (s): a node's first
env compiles the filter's kernels."""
RESTART_POLLS = 60
"""Tries (one a second) to reach a restarting worker before it counts as lost."""


def _make_env(env_id: str, env_kwargs: dict[str, Any], action_seed: int) -> gym.Env[Any, Any]:
    """One env of a worker: ``gym.make``, its action space seeded (as ``make_vec_env``)."""
    import gymnasium as gym

    env = gym.make(env_id, **env_kwargs)
    env.action_space.seed(action_seed)
    return env


class EnvWorker:
    """Some envs of a run, stepped in this process: the body of a Ray actor.

    ``seeds`` (one per env) seed the action spaces; the envs' resets are seeded by the
    driver (:meth:`reset`).
    """

    def __init__(self, env_id: str, env_kwargs: dict[str, Any], seeds: Sequence[int]) -> None:
        self.venv = DummyVecEnv([partial(_make_env, env_id, env_kwargs, s) for s in seeds])

    def spaces(self) -> tuple[gym.Space[Any], gym.Space[Any]]:
        """(observation space, action space) of the envs."""
        return self.venv.observation_space, self.venv.action_space

    def reset(
        self, seeds: Sequence[int | None], options: Sequence[dict[str, Any]]
    ) -> tuple[VecEnvObs, list[dict[str, Any]]]:
        """Reset every env with its seed and options: (observations (k, ...), infos)."""
        self.venv._seeds = list(seeds)
        self.venv._options = [dict(o) for o in options]
        obs = self.venv.reset()
        return obs, self.venv.reset_infos

    def step(self, actions: NDArray[Any]) -> VecEnvStepReturn:
        """One step of every env, ``actions`` (k, ...): SB3's (obs, rewards, dones, infos),
        with an ended episode's env reset at once (DummyVecEnv's conventions)."""
        return self.venv.step(actions)

    def call(self, method: str, *args: Any, **kwargs: Any) -> Any:
        """A ``VecEnv`` method of the worker's envs (``get_attr``, ``set_attr``,
        ``env_method``, ``env_is_wrapped``, ``get_images``), ``indices`` local."""
        if method not in ("get_attr", "set_attr", "env_method", "env_is_wrapped", "get_images"):
            raise ValueError(f"EnvWorker.call: {method!r} is not a VecEnv query")
        return getattr(self.venv, method)(*args, **kwargs)

    def where(self) -> tuple[int, str]:
        """(process id, Ray node id) of this worker."""
        import ray

        return os.getpid(), ray.get_runtime_context().get_node_id()

    def close(self) -> None:
        self.venv.close()


class RayVecEnv(VecEnv):
    """``n_envs`` envs of ``env_id`` on ``workers`` Ray actors (the first ones get one
    env more where ``n_envs`` does not divide), spread over the nodes of the connected
    cluster (Ray's ``SPREAD`` scheduling), each actor taking ``num_cpus`` CPUs. The
    observations are Box arrays, (n_envs, *shape) as SB3 has them.

    Needs ``ray.init`` done (:func:`agents.training.cluster.cluster_session`).
    """

    def __init__(
        self,
        env_id: str,
        n_envs: int,
        seed: int,
        env_kwargs: dict[str, Any] | None = None,
        *,
        workers: int,
        max_restarts: int = 3,
        num_cpus: float = 1.0,
    ) -> None:
        ray = require_ray()
        if not 1 <= workers <= n_envs:
            raise ValueError(f"workers ({workers}) must be between 1 and n_envs ({n_envs})")
        cpus = ray.cluster_resources().get("CPU", 0.0)
        if workers * num_cpus > cpus:
            raise ValueError(
                f"{workers} workers of {num_cpus:g} CPU each do not fit the cluster's "
                f"{cpus:g} CPUs: fewer --workers, or more nodes"
            )
        self.slices = [
            slice(int(part[0]), int(part[-1]) + 1)
            for part in np.array_split(np.arange(n_envs), workers)
        ]
        self.max_restarts = max_restarts
        self.restarts = 0
        """Worker deaths survived so far."""
        actor = ray.remote(EnvWorker).options(
            num_cpus=num_cpus, max_restarts=max_restarts, scheduling_strategy="SPREAD"
        )
        kwargs = dict(env_kwargs or {})
        self.workers = [
            actor.remote(env_id, kwargs, list(range(seed + s.start, seed + s.stop)))
            for s in self.slices
        ]
        try:
            spaces = ray.get([w.spaces.remote() for w in self.workers], timeout=START_TIMEOUT_S)
        except ray.exceptions.GetTimeoutError:
            self.close()
            raise TimeoutError(
                f"the {workers} Ray workers did not start within {START_TIMEOUT_S:g} s"
            ) from None
        if not isinstance(spaces[0][0], gym_spaces.Box):
            self.close()
            raise ValueError(f"{env_id}: the Ray vec env takes Box observations only")
        self._base_seed = seed
        self._last_obs: NDArray[Any] | None = None
        self._pending: list[Any] = []
        self.num_envs = n_envs  # the base class asks the envs their render mode
        super().__init__(n_envs, *spaces[0])
        self.seed(seed)

    # ------------------------------------------------------------------ stepping

    def seed(self, seed: int | None = None) -> Sequence[int | None]:
        """Seeds ``seed + i`` for env ``i``'s next reset (SB3's ``VecEnv.seed``)."""
        seeds = super().seed(seed)
        self._base_seed = int(seeds[0]) if seeds and seeds[0] is not None else 0
        return seeds

    def reset(self) -> VecEnvObs:
        """Reset every env with the seeds and options set for it: observations (n, ...)."""
        ray = require_ray()
        refs = [
            w.reset.remote(self._seeds[s], self._options[s])
            for w, s in zip(self.workers, self.slices, strict=True)
        ]
        parts = []
        for k, ref in enumerate(refs):
            try:
                obs, infos = ray.get(ref)
            except ray.exceptions.RayActorError as err:  # died during the reset: once more
                obs, infos = self._revive(k, err, self._seeds[self.slices[k]])
            parts.append(obs)
            self.reset_infos[self.slices[k]] = infos
        self._reset_seeds()
        self._reset_options()
        self._last_obs = np.concatenate(parts)
        return self._last_obs.copy()

    def step_async(self, actions: NDArray[Any]) -> None:
        self._pending = [
            w.step.remote(actions[s]) for w, s in zip(self.workers, self.slices, strict=True)
        ]

    def step_wait(self) -> VecEnvStepReturn:
        """Every worker's step, in env order; a dead worker's envs end their episodes."""
        ray = require_ray()
        try:
            results = ray.get(self._pending)  # one wait for all: the usual case
        except ray.exceptions.RayActorError:
            results = [self._step_result(k, ref) for k, ref in enumerate(self._pending)]
        self._pending = []
        obs, rewards, dones, infos = zip(*results, strict=True)
        self._last_obs = np.concatenate(obs)
        return (
            self._last_obs.copy(),
            np.concatenate(rewards),
            np.concatenate(dones),
            [info for part in infos for info in part],
        )

    def _step_result(self, k: int, ref: Any) -> VecEnvStepReturn:
        """Worker ``k``'s step, or (it died) its envs' episodes ended."""
        ray = require_ray()
        try:
            result: VecEnvStepReturn = ray.get(ref)
        except ray.exceptions.RayActorError as err:
            return self._lost(k, err)
        return result

    def _lost(self, k: int, err: Exception) -> VecEnvStepReturn:
        """Worker ``k`` died during a step: its episodes end truncated at their last
        observation, and new ones start once Ray has restarted it."""
        s = self.slices[k]
        assert self._last_obs is not None, "step before reset"
        terminal = self._last_obs[s]
        seeds = np.random.SeedSequence([self._base_seed, k, self.restarts + 1])
        new_seeds = [int(x) for x in seeds.generate_state(s.stop - s.start)]
        obs, reset_infos = self._revive(k, err, new_seeds)
        self.reset_infos[s] = reset_infos
        n = s.stop - s.start
        infos = [
            {"worker_restarted": True, "TimeLimit.truncated": True, "terminal_observation": t}
            for t in terminal
        ]
        return obs, np.zeros(n, dtype=np.float32), np.ones(n, dtype=bool), infos

    def _revive(
        self, k: int, err: Exception, seeds: Sequence[int | None]
    ) -> tuple[VecEnvObs, list[dict[str, Any]]]:
        """Count worker ``k``'s death and reset its envs (``seeds``) once Ray has
        restarted it; a worker past ``max_restarts`` ends the run with one line."""
        ray = require_ray()
        self.restarts += 1
        log.warning(
            "Ray worker %d died (%s); restarting it, its episodes end truncated "
            "(%d worker restarts in this run)",
            k,
            type(err).__name__,
            self.restarts,
        )
        s = self.slices[k]
        options: list[dict[str, Any]] = [{} for _ in range(s.stop - s.start)]
        for _ in range(RESTART_POLLS):
            try:
                result: tuple[VecEnvObs, list[dict[str, Any]]] = ray.get(
                    self.workers[k].reset.remote(seeds, options)
                )
                return result
            except ray.exceptions.ActorUnavailableError:  # restarting still
                time.sleep(1.0)
            except ray.exceptions.RayActorError as final:
                raise RuntimeError(
                    f"Ray worker {k} is lost for good (max_restarts={self.max_restarts}): "
                    f"{' '.join(str(final).split())[:200]}"
                ) from None
        raise RuntimeError(f"Ray worker {k} did not come back within {RESTART_POLLS} s")

    # ------------------------------------------------------------------ queries

    def _by_worker(self, indices: VecEnvIndices) -> list[tuple[int, list[int], list[int]]]:
        """(worker, local indices, positions in the answer) of the envs ``indices``."""
        wanted = list(self._get_indices(indices))
        out = []
        for k, s in enumerate(self.slices):
            mine = [(pos, i - s.start) for pos, i in enumerate(wanted) if s.start <= i < s.stop]
            if mine:
                out.append((k, [j for _, j in mine], [p for p, _ in mine]))
        return out

    def _query(self, method: str, indices: VecEnvIndices, *args: Any, **kwargs: Any) -> list[Any]:
        """``method`` of the envs ``indices``, answers in their order."""
        ray = require_ray()
        groups = self._by_worker(indices)
        refs = [
            self.workers[k].call.remote(method, *args, indices=local, **kwargs)
            for k, local, _ in groups
        ]
        answer: list[Any] = [None] * sum(len(p) for _, _, p in groups)
        for (_, _, positions), part in zip(groups, ray.get(refs), strict=True):
            for pos, value in zip(positions, part or [None] * len(positions), strict=True):
                answer[pos] = value
        return answer

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return self._query("get_attr", indices, attr_name)

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        self._query("set_attr", indices, attr_name, value)

    def env_method(
        self,
        method_name: str,
        *method_args: Any,
        indices: VecEnvIndices = None,
        **method_kwargs: Any,
    ) -> list[Any]:
        return self._query("env_method", indices, method_name, *method_args, **method_kwargs)

    def env_is_wrapped(
        self, wrapper_class: type[gym.Wrapper[Any, Any, Any, Any]], indices: VecEnvIndices = None
    ) -> list[bool]:
        return self._query("env_is_wrapped", indices, wrapper_class)

    def get_images(self) -> Sequence[NDArray[Any] | None]:
        ray = require_ray()
        parts = ray.get([w.call.remote("get_images") for w in self.workers])
        return [image for part in parts for image in part]

    def where(self) -> list[tuple[int, str]]:
        """(process id, Ray node id) of each worker."""
        ray = require_ray()
        return list(ray.get([w.where.remote() for w in self.workers]))

    def close(self) -> None:
        """Close every worker's envs and end the actors."""
        ray = require_ray()
        try:
            ray.get([w.close.remote() for w in self.workers], timeout=30)
        except (ray.exceptions.RayError, TimeoutError) as err:
            log.warning("closing the Ray workers: %s", type(err).__name__)
        for w in self.workers:
            ray.kill(w)
        self.workers = []
