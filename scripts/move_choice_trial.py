"""A trial of the move-choice formulation: PPO choosing the steering gait's entries
(:class:`tensegrity_gym.envs.moves.MoveChoice`) against the gait's own choice, on the same
seeded episodes. Prints one JSON line: the progress toward the goal (m) of each.

    python scripts/move_choice_trial.py --env tensegrity_gym/ThreeBarGoTo-v0 \\
        --estimator oracle --decisions 2048 --seed 0 --episodes 8 --bias 3.0

``--bias``: added to rank 0's logit (the gait's own choice) before training: 0 starts
from a uniform choice, 3 from the gait nine times in ten.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

import gymnasium as gym
import numpy as np


def _train(args: argparse.Namespace) -> tuple[Any, Any, float]:
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv, VecNormalize

    from tensegrity_gym.envs.moves import MoveChoice

    clock = time.perf_counter()
    venv = make_vec_env(args.env, n_envs=2, seed=args.seed,
                        env_kwargs={"estimator": args.estimator}, wrapper_class=MoveChoice,
                        vec_env_cls=SubprocVecEnv)  # fmt: skip
    venv = VecNormalize(venv, norm_obs=True, norm_reward=True, gamma=0.9)
    model = PPO("MlpPolicy", venv, n_steps=128, batch_size=64, n_epochs=10,
                learning_rate=3e-4, gamma=0.9, gae_lambda=0.95, ent_coef=0.01,
                seed=args.seed, device="cpu",
                policy_kwargs={"net_arch": {"pi": [64, 64], "vf": [64, 64]}})  # fmt: skip
    with torch.no_grad():
        model.policy.action_net.bias[0] += args.bias
    model.learn(args.decisions)
    venv.training = False
    return model, venv, time.perf_counter() - clock


def _progress(args: argparse.Namespace, act: Any) -> list[float]:
    from agents.evaluation.evaluate import run_episode
    from tensegrity_gym.envs.moves import MoveChoice

    env = MoveChoice(gym.make(args.env, estimator=args.estimator))
    try:
        return [round(run_episode(env, act, 1000 + k).progress, 3) for k in range(args.episodes)]
    finally:
        env.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="tensegrity_gym/ThreeBarGoTo-v0")
    parser.add_argument("--estimator", default="oracle")
    parser.add_argument("--decisions", type=int, default=2048, help="training steps (periods)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--episodes", type=int, default=8)
    parser.add_argument("--bias", type=float, default=3.0)
    args = parser.parse_args()
    model, venv, seconds = _train(args)

    def policy(observation: np.ndarray) -> int:
        action, _ = model.predict(venv.normalize_obs(observation[None]), deterministic=True)
        return int(action[0])

    out: dict[str, Any] = vars(args) | {"train_s": round(seconds)}
    for name, act in (("policy", policy), ("gait", lambda _obs: 0)):
        each = _progress(args, act)
        out[name] = {"mean": round(float(np.mean(each)), 3),
                     "std": round(float(np.std(each)), 3), "each": each}  # fmt: skip
    sys.stdout.write(json.dumps(out) + "\n")


if __name__ == "__main__":
    main()
