"""How a scripted gait's progress falls when its commands carry noise (a developer tool).

    python scripts/gait_noise.py tensegrity_gym/SuperBallRoll-v0 [--gait steer]
        [--noise 0 0.03 0.135] [--episodes 8] [--seed 1000] [--estimator oracle]
        [--robot PRESET_OR_YAML]

The env is made with residual actions on the gait (``gym.make(id, residual_gait=0.5,
base_gait=GAIT)``) and driven by Gaussian corrections of standard deviation NOISE (the
policy's units, before the scale of 0.5; 0 is the gait itself), drawn from a generator
seeded by the episode's seed, for whole episodes from ``reset(seed)``, ``seed + 1``...
It prints, per noise, the true CoM's progress toward the goal of every episode and
their mean (m): a residual policy's exploration noise, or a real robot's motors, costs
the gait that much.
"""

from __future__ import annotations

import argparse
from typing import Any

import gymnasium as gym
import numpy as np

import tensegrity_gym  # noqa: F401  (registers the envs)
from agents.evaluation.evaluate import true_progress


def progress(env: gym.Env[Any, Any], noise: float, seed: int) -> float:
    """The true CoM's progress (m) over one episode from ``reset(seed)`` under corrections
    of standard deviation ``noise``."""
    rng = np.random.default_rng(seed)
    _, info = env.reset(seed=seed)
    heading = env.unwrapped.task.direction if "goal" not in info else None
    path, goals = [info["com_true"]], []
    done = False
    while not done:
        goals.append(info.get("goal"))
        action = (noise * rng.standard_normal(env.action_space.shape)).astype(np.float32)
        _, _, terminated, truncated, info = env.step(action)
        path.append(info["com_true"])
        done = terminated or truncated
    return true_progress(np.array(path), heading, None if heading is not None else np.array(goals))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("env")
    parser.add_argument("--gait", default="steer", help="the gait (a name of the robot's)")
    parser.add_argument("--noise", type=float, nargs="+", default=[0.0, 0.03, 0.135])
    parser.add_argument("--episodes", type=int, default=8)
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument("--estimator", default="oracle")
    parser.add_argument("--robot", default=None, help="a preset or YAML file (the env's own)")
    args = parser.parse_args()
    robot = {} if args.robot is None else {"robot": args.robot}
    env = gym.make(
        args.env, estimator=args.estimator, residual_gait=0.5, base_gait=args.gait, **robot
    )
    for noise in args.noise:
        runs = [progress(env, noise, args.seed + k) for k in range(args.episodes)]
        print(f"noise {noise:g}: mean {np.mean(runs):.3f} m; episodes {np.round(runs, 2).tolist()}")
    env.close()


if __name__ == "__main__":
    main()
