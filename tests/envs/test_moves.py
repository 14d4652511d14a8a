"""MoveChoice: a policy picks the steering gait's entries, a gait period a step."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import tensegrity_gym  # noqa: F401  (registers the ids)
from tensegrity_gym.envs.moves import (
    MOVE_FEATURES,
    MoveChoice,
    MovePolicy,
    check_ranks,
    check_tempos,
)
from tensegrity_gym.tasks.gaits import FaceGait

GOTO = "tensegrity_gym/ThreeBarGoTo-v0"


def _own_choice(observation: np.ndarray, most: int) -> int:
    """The rank of the entry the gait itself would take: the first, as the
    observation's last features (the own-choice flags) say."""
    assert observation[-most] == 1.0
    return 0


def test_taking_the_gaits_own_choice_is_the_gait() -> None:
    """Choosing what the observation says the gait would choose gives the steering
    gait's episode step for step: same true path, same summed reward."""
    moved = MoveChoice(gym.make(GOTO, estimator="oracle", max_episode_steps=140))
    obs, _ = moved.reset(seed=3)
    assert moved.action_space.n == moved.most >= 2
    assert obs.shape == moved.observation_space.shape
    rewards, periods = 0.0, 0
    done = False
    while not done:
        obs, reward, terminated, truncated, info = moved.step(_own_choice(obs, moved.most))
        rewards += float(reward)
        periods += 1
        done = terminated or truncated
    moved_com = info["com_true"]
    assert periods == 4 and info["period_steps"] == 140 - 3 * moved.gait.period_steps

    env = gym.make(GOTO, estimator="oracle", max_episode_steps=140)
    inner = env.unwrapped
    gait = FaceGait(inner.backend.description, inner.task, gait="steer")
    obs, _ = env.reset(seed=3)
    total, done = 0.0, False
    while not done:
        obs, reward, terminated, truncated, info = env.step(gait(obs))
        total += float(reward)
        done = terminated or truncated
    np.testing.assert_array_equal(info["com_true"], moved_com)
    assert total == pytest.approx(rewards, abs=1e-9)


def test_move_features_describe_the_support_faces_entries() -> None:
    moved = MoveChoice(gym.make(GOTO, estimator="oracle"))
    obs, _ = moved.reset(seed=0)
    k = moved.most
    features = obs[-MOVE_FEATURES * k :].reshape(MOVE_FEATURES, k)
    present = features[1]
    assert present[0] == 1.0 and set(np.unique(present)) <= {0.0, 1.0}
    assert features[3].sum() == 1.0 and features[3][0] == 1.0  # the gait's own first
    assert np.all(features[0][present == 0] == 0.0) and np.all(features[2] == 0.0)
    # Nothing stalled yet: the gait's own is the most progress, the rest in its order.
    assert np.all(np.diff(features[0][present > 0]) <= 0.0)


def test_check_env_and_bad_wrapping() -> None:
    check_env(
        MoveChoice(gym.make(GOTO, estimator="oracle", max_episode_steps=70)), skip_render_check=True
    )
    with pytest.raises(ValueError, match="residual actions"):
        MoveChoice(gym.make(GOTO, estimator="oracle", residual_gait=0.5, base_gait="steer"))
    with pytest.raises(ValueError, match="one entry a face"):
        MoveChoice(gym.make(GOTO, estimator="oracle"), gait="forward")


SHORT = (15, 0)
"""A tempo beside the gait's own (25, 10): hold 15 control steps, no settle."""


def test_a_tempo_sets_the_periods_length_and_bad_tempos_are_refused() -> None:
    """With ``tempos``, action ``most * t + r`` runs rank r for tempo t's hold and
    settle (t = 0: the gait's own); a tempo the gait cannot run is refused in one line."""
    moved = MoveChoice(gym.make(GOTO, estimator="oracle"), tempos=[SHORT])
    assert moved.action_space.n == 2 * moved.most
    moved.reset(seed=2)
    assert moved.step(moved.most)[4]["period_steps"] == sum(SHORT)
    assert moved.step(0)[4]["period_steps"] == moved.gait.period_steps == 35
    tempo_only = MoveChoice(gym.make(GOTO, estimator="oracle"), tempos=[SHORT], ranks=1)
    assert tempo_only.action_space.n == 2  # the gait's move, at its tempo or the short one
    tempo_only.reset(seed=2)
    assert tempo_only.step(1)[4]["period_steps"] == sum(SHORT)
    for ranks in (0, moved.most + 1, 1.5):
        with pytest.raises(ValueError, match="ranks must be a whole number from 1 to"):
            check_ranks(moved.gait, ranks)  # type: ignore[arg-type]
    for tempo in [(5, 0), (15, -1), (15,), (15.0, 2)]:  # the ramp is 11 steps
        with pytest.raises(ValueError, match=r"tempo .*\(hold, settle\) control steps"):
            check_tempos(moved.gait, [tempo])  # what MoveChoice and MovePolicy call


def _second_if_open(observation: np.ndarray, most: int, period: int) -> int:
    """A choice that is not the gait's on even periods: rank 1 at the short tempo where
    the face offers it, as the observation's presence flags say; else the gait's own
    choice at its own tempo."""
    present = observation[-MOVE_FEATURES * most :].reshape(MOVE_FEATURES, most)[1]
    return most + 1 if present[1] == 1.0 and period % 2 == 0 else 0


def test_a_move_policy_drives_the_env_step_by_step_as_the_wrapper() -> None:
    """The same rule of MoveChoice's observation (ranks and tempos), acting through the
    wrapper (a step a period) and through MovePolicy on the env beneath (a step a
    control step, as evaluate runs it): the same true path, bit for bit, and the same
    choices."""
    moved = MoveChoice(gym.make(GOTO, estimator="oracle", max_episode_steps=140), tempos=[SHORT])
    obs, _ = moved.reset(seed=5)
    wrapped_path, ranks, lengths, done = [], [], [], False
    while not done:
        ranks.append(_second_if_open(obs, moved.most, len(ranks)))
        obs, _, terminated, truncated, info = moved.step(ranks[-1])
        wrapped_path.append(info["com_true"])
        lengths.append(info["period_steps"])
        done = terminated or truncated
    assert {0, moved.most + 1} <= set(ranks)  # both tempos, the gait's choice left

    env = gym.make(GOTO, estimator="oracle", max_episode_steps=140)
    inner = env.unwrapped
    gait = FaceGait(inner.backend.description, inner.task, gait="steer")
    picked: list[int] = []

    def pick(seen: np.ndarray) -> int:
        picked.append(_second_if_open(seen, gait.most_moves, len(picked)))
        return picked[-1]

    policy = MovePolicy(gait, pick, tempos=[SHORT])
    policy.reset()
    obs, _ = env.reset(seed=5)
    path, done = [], False
    while not done:
        obs, _, terminated, truncated, info = env.step(policy(obs))
        path.append(info["com_true"])
        done = terminated or truncated
    assert picked == ranks
    assert sum(lengths) == len(path) == 140
    ends = np.cumsum(lengths) - 1
    np.testing.assert_array_equal(np.array(wrapped_path), np.array(path)[ends])
