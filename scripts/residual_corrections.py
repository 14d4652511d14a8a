"""How often a trained residual policy corrects its gait at all (a developer tool).

    python scripts/residual_corrections.py RUN [--episodes 2] [--seed 1000]
        [--estimator ukf]

Runs the training run's policy (deterministic, as ``evaluate`` runs it) on its own env
(its ``residual_gait``, ``base_gait`` and ``residual_deadband``) for whole episodes
from ``reset(seed)``, ``seed + 1``... and prints the RMS and the largest entry of its
actions, the share of action entries and of steps whose correction is not zero (with
a deadband, those that left the band) and the RMS of the corrections, before the
residual scale. A policy that never corrects runs its gait exactly.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np

from agents.evaluation.evaluate import load_policy

if TYPE_CHECKING:
    from agents.evaluation.evaluate import LoadedPolicy


def measure(
    policy: LoadedPolicy, env: gym.Env[Any, Any], episodes: int, seed: int, steps: int | None = None
) -> dict[str, float]:
    """The figures the module docstring names, over ``episodes`` episodes of ``env``
    (made with the policy's residual actions) from ``reset(seed)``, ``seed + 1``...,
    each cut at ``steps`` steps (None: whole)."""
    correct = env.unwrapped.correction  # type: ignore[attr-defined]
    actions, corrections = [], []
    for k in range(episodes):
        observation, _ = env.reset(seed=seed + k)
        done, taken = False, 0
        while not done and (steps is None or taken < steps):
            action = policy.act(observation)
            actions.append(action.astype(np.float64))
            corrections.append(correct(actions[-1]))
            observation, _, terminated, truncated, _ = env.step(action)
            done, taken = terminated or truncated, taken + 1
    a, c = np.array(actions), np.array(corrections)
    return {
        "steps": len(a),
        "action_rms": float(np.sqrt(np.mean(a**2))),
        "largest_entry": float(np.abs(a).max()),
        "entries_corrected": float(np.mean(c != 0)),
        "steps_corrected": float(np.mean((c != 0).any(axis=1))),
        "correction_rms": float(np.sqrt(np.mean(c**2))),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run", type=Path, help="a training run trained with residual actions")
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--seed", type=int, default=1000, help="the first episode's seed")
    parser.add_argument("--estimator", default="ukf")
    args = parser.parse_args()
    policy = load_policy(args.run)
    if not policy.env_kwargs.get("residual_gait"):
        parser.error(f"{args.run}: its policy commands rest lengths itself (no residual_gait)")
    env = gym.make(policy.env_id, estimator=args.estimator, **policy.env_kwargs)
    f = measure(policy, env, args.episodes, args.seed)
    env.close()
    print(
        f"{args.run}: {f['steps']} steps; action RMS {f['action_rms']:.4f}, largest |entry| "
        f"{f['largest_entry']:.3f}; entries corrected {f['entries_corrected']:.2%}, steps "
        f"with a correction {f['steps_corrected']:.2%}; correction RMS "
        f"{f['correction_rms']:.5f}"
    )


if __name__ == "__main__":
    main()
