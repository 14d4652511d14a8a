"""``bench --ray``: the Ray vec env against ``SubprocVecEnv``, and the per-step costs a
cluster is sized with.

Every vec env is made first, then they step in turns (``rounds`` turns each), so that
the ratios compare like with like on a shared, noisy machine. Figures:

- the overhead per env step of :class:`agents.training.cluster.vec_env.RayVecEnv` against
  ``SubprocVecEnv``, both with the same number of workers (one env each, and two
  envs on each Ray worker);
- env steps per second with 1 and 2 Ray workers;
- the costs of the sizing model (docs/training.md, "On a cluster"): an env step in a process of
  its own (``t_env``), a worker's round trip through Ray without env work
  (``t_call``) and the driver's own share of it (``t_driver``), the bytes a step sends
  and receives per env, and the learner's update time per collected env step
  (``t_learn``, PPO with the env's configuration).
"""

from __future__ import annotations

import pickle
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from agents.training.cluster import require_ray

if TYPE_CHECKING:
    from stable_baselines3.common.vec_env import VecEnv

__all__ = ["bench_ray"]

ENV_ID = "tensegrity_gym/ThreeBarRoll-v0"


def _seconds_per_step(venv: VecEnv, steps: int, rng: np.random.Generator) -> float:
    """Wall time of ``steps`` vec steps under uniform random actions (s)."""
    shape = (venv.num_envs, *(venv.action_space.shape or ()))
    actions = rng.uniform(-1.0, 1.0, (steps, *shape)).astype(np.float32)
    t = time.perf_counter()
    for a in actions:
        venv.step(a)
    return time.perf_counter() - t


def _in_turns(venvs: dict[str, VecEnv], steps: int, rounds: int) -> dict[str, float]:
    """Env steps per second of each vec env, stepped ``steps`` vec steps in all, in
    ``rounds`` turns taken one after the other."""
    rng = np.random.default_rng(0)
    for venv in venvs.values():
        venv.seed(0)
        venv.reset()
        _seconds_per_step(venv, 10, rng)  # warm-up: caches, first allocations
    spent = dict.fromkeys(venvs, 0.0)
    per_turn = max(steps // rounds, 1)
    for _ in range(rounds):
        for name, venv in venvs.items():
            spent[name] += _seconds_per_step(venv, per_turn, rng)
    return {n: per_turn * rounds * venvs[n].num_envs / spent[n] for n in venvs}


def _call_ms(venv: Any, calls: int = 200) -> tuple[float, float]:
    """Milliseconds of a Ray worker call that does no env work: one round trip at a
    time (latency), and the driver's share when ``calls`` are in flight to every
    worker at once (what the driver spends per worker and step, serially)."""
    ray = require_ray()
    venv.get_attr("render_mode", indices=[0])
    t = time.perf_counter()
    for _ in range(calls):
        venv.get_attr("render_mode", indices=[0])
    latency = (time.perf_counter() - t) / calls
    t = time.perf_counter()
    ray.get(
        [w.call.remote("get_attr", "render_mode", indices=[0])
         for _ in range(calls) for w in venv.workers]
    )  # fmt: skip
    driver = (time.perf_counter() - t) / (calls * len(venv.workers))
    return 1e3 * latency, 1e3 * driver


def _bytes_per_env_step(env_id: str, kwargs: dict[str, Any]) -> dict[str, int]:
    """What one env's step sends (the action) and receives (observation, reward, done,
    info), pickled as Ray ships them (bytes)."""
    from stable_baselines3.common.env_util import make_vec_env

    venv = make_vec_env(env_id, n_envs=1, seed=0, env_kwargs=kwargs)
    venv.reset()
    action = np.zeros((1, *(venv.action_space.shape or ())), dtype=np.float32)
    result = venv.step(action)
    venv.close()
    return {"sent": len(pickle.dumps(action)), "received": len(pickle.dumps(result))}


def _learner_ms_per_step(env_id: str, n_steps: int = 256) -> float:
    """Milliseconds of PPO's update per collected env step: the env's configured
    network, batch and epochs, on a rollout of ``n_steps`` per env."""
    from stable_baselines3.common.callbacks import BaseCallback

    from agents.training.train import load_hyperparams, make_training_env

    params = load_hyperparams("ppo", env_id)
    n_envs = int(params.pop("n_envs", 1))
    for key in ("n_timesteps", "normalize", "policy"):
        params.pop(key, None)
    params["n_steps"] = n_steps
    venv = make_training_env(env_id, n_envs, 0, {"estimator": "oracle"}, None)

    class Clock(BaseCallback):
        rollout_end = 0.0

        def _on_rollout_end(self) -> None:
            self.rollout_end = time.perf_counter()

        def _on_step(self) -> bool:
            return True

    import torch
    from stable_baselines3 import PPO

    torch.set_num_threads(1)  # as train has it
    clock = Clock()
    model = PPO("MlpPolicy", venv, seed=0, device="cpu", **params)
    model.learn(n_steps * n_envs, callback=clock)
    update = time.perf_counter() - clock.rollout_end
    venv.close()
    return 1e3 * update / (n_steps * n_envs)


def _sizing(t_env: float, t_call: float, t_driver: float, t_learn: float) -> dict[str, Any]:
    """The sizing model with the measured costs (ms), and what it predicts (env steps
    per second, collection alone and with PPO's updates taken in turn)."""

    def collect(workers: int, envs_per_worker: int) -> float:
        vec_step_ms = max(envs_per_worker * t_env + t_call, workers * t_driver)
        return 1e3 * workers * envs_per_worker / vec_step_ms

    def with_learner(workers: int, envs_per_worker: int) -> float:
        return 1.0 / (1.0 / collect(workers, envs_per_worker) + 1e-3 * t_learn)

    shapes = ((1, 1), (2, 1), (8, 4), (32, 4), (128, 4), (512, 4))
    return {
        "formula": "vec step = max(k t_env + t_call, W t_driver); collect = W k / vec step; "
        "rate = 1 / (1 / collect + t_learn); W workers of k envs, at most one per core",
        "t_env_ms": round(t_env, 3),
        "t_call_ms": round(t_call, 3),
        "t_driver_ms": round(t_driver, 3),
        "t_learn_ms_per_env_step": round(t_learn, 3),
        "predicted_collect_env_steps_per_s": {
            f"{w}x{k}": round(collect(w, k), 1) for w, k in shapes
        },
        "predicted_training_env_steps_per_s": {
            f"{w}x{k}": round(with_learner(w, k), 1) for w, k in shapes
        },
    }


def bench_ray(
    env_id: str = ENV_ID, estimator: str = "ukf", steps: int = 400, turn: int = 20
) -> dict[str, Any]:
    """The Ray vec env's figures (module docstring), on the Ray cluster this process is
    connected to; ``steps`` vec steps per vec env, in turns of ``turn`` steps (short
    turns: a change in the machine's load falls on every vec env alike)."""
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    from agents.training.cluster.vec_env import RayVecEnv
    from agents.training.train import qualified_id

    ray = require_ray()
    kwargs = {"estimator": estimator}
    qualified = qualified_id(env_id)

    def ray_venv(workers: int, envs: int) -> RayVecEnv:  # 5 workers on 2 cores: 0.4 CPU each
        return RayVecEnv(qualified, envs, 0, kwargs, workers=workers, num_cpus=0.4)

    venvs: dict[str, VecEnv] = {
        "in_process_1_env": make_vec_env(qualified, 1, 0, env_kwargs=kwargs,
                                         vec_env_cls=DummyVecEnv),
        "subproc_2_workers": make_vec_env(qualified, 2, 0, env_kwargs=kwargs,
                                          vec_env_cls=SubprocVecEnv),
        "ray_1_worker": ray_venv(1, 1),
        "ray_2_workers": ray_venv(2, 2),
        "ray_2_workers_of_2_envs": ray_venv(2, 4),
    }  # fmt: skip
    try:
        rates = _in_turns(venvs, steps, max(steps // turn, 1))
        call_ms, driver_ms = _call_ms(venvs["ray_2_workers"])
    finally:
        for venv in venvs.values():
            venv.close()
    t_learn = _learner_ms_per_step(env_id)
    return {
        "env": env_id,
        "estimator": estimator,
        "vec_steps": steps,
        "cluster_cpus": ray.cluster_resources().get("CPU"),
        "env_steps_per_s": {name: round(r, 1) for name, r in rates.items()},
        "ray_over_subproc_time_per_env_step": round(
            rates["subproc_2_workers"] / rates["ray_2_workers"], 3
        ),
        "ray_2_envs_per_worker_over_subproc_time_per_env_step": round(
            rates["subproc_2_workers"] / rates["ray_2_workers_of_2_envs"], 3
        ),
        "ray_2_over_1_worker_speedup": round(rates["ray_2_workers"] / rates["ray_1_worker"], 3),
        "bytes_per_env_step": _bytes_per_env_step(qualified, kwargs),
        "sizing": _sizing(1e3 / rates["in_process_1_env"], call_ms, driver_ms, t_learn),
        "targets": {"ray_over_subproc_time_per_env_step": 1.15},
    }
