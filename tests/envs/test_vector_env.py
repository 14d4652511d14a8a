"""The native vector env (issue 41): ``gym.make_vec(ID, num_envs=N,
vectorization_mode="vector_entry_point")`` is a Gymnasium ``VectorEnv`` with autoreset
whose episodes are those of N single envs, bit for bit, and it trains with SB3 through
:class:`agents.training.vec_env.Sb3VecEnv` as ``DummyVecEnv`` over single envs would."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import tensegrity_gym
from tensegrity_gym.envs.vector import TensegrityVectorEnv

ROLL = "tensegrity_gym/ThreeBarRoll-v0"
LIMIT = 4  # steps per episode: every env resets within the test's steps


def _actions(n: int, steps: int, seed: int = 5) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1, 1, (steps, n, 6)).astype(np.float32)


def _singles(n: int, seed: int, actions: np.ndarray, **kwargs: Any) -> list[list[Any]]:
    """N single envs of ROLL stepped through ``actions``, reset as NEXT_STEP does."""
    runs = []
    for i in range(n):
        env = gym.make(ROLL, max_episode_steps=LIMIT, **kwargs)
        obs, _ = env.reset(seed=seed + i)
        run: list[Any] = [obs]
        done = False
        for a in actions[:, i]:
            if done:
                obs, _ = env.reset()
                reward, terminated, truncated = 0.0, False, False
            else:
                obs, reward, terminated, truncated, _ = env.step(a)
            done = terminated or truncated
            run += [obs, reward, terminated, truncated]
        env.close()
        runs.append(run)
    return runs


@pytest.mark.parametrize("engine", ["mujoco", "pybullet"])
def test_the_vector_env_is_n_single_envs_bit_for_bit(engine: str) -> None:
    n, steps = 3, 2 * LIMIT + 3
    actions = _actions(n, steps)
    vec = gym.make_vec(ROLL, num_envs=n, vectorization_mode="vector_entry_point",
                       max_episode_steps=LIMIT, engine=engine)  # fmt: skip
    assert isinstance(vec.unwrapped, TensegrityVectorEnv)
    assert vec.observation_space.shape == (n, 44) and vec.action_space.shape == (n, 6)
    obs, infos = vec.reset(seed=10)
    assert infos["com_true"].shape == (n, 3) and infos["_com_true"].all()
    got = [[obs[i]] for i in range(n)]
    for a in actions:
        obs, rewards, terminated, truncated, _ = vec.step(a)
        for i in range(n):
            got[i] += [obs[i], rewards[i], terminated[i], truncated[i]]
    vec.close()
    expected = _singles(n, 10, actions, engine=engine)
    for i in range(n):
        assert all(np.array_equal(x, y) for x, y in zip(got[i], expected[i], strict=True)), i
    assert sum(bool(x) for x in got[0][4::4]) >= 2  # the limit truncated episodes


def test_same_step_autoreset_hands_over_the_last_observation() -> None:
    vec = gym.make_vec(ROLL, num_envs=2, vectorization_mode="vector_entry_point",
                       max_episode_steps=2, engine="mujoco", autoreset_mode="SameStep")  # fmt: skip
    vec.reset(seed=0)
    zeros = np.zeros((2, 6), dtype=np.float32)
    _, _, _, truncated, infos = vec.step(zeros)
    assert not truncated.any() and "final_obs" not in infos
    obs, _, _, truncated, infos = vec.step(zeros)
    assert truncated.all() and infos["_final_obs"].all()
    assert infos["final_obs"][0].shape == (44,) and not np.array_equal(
        infos["final_obs"][0], obs[0]
    )
    vec.close()


def test_bad_vector_arguments_are_refused_in_one_line() -> None:
    with pytest.raises(ValueError, match=r"num_envs=0 must be an int >= 1"):
        TensegrityVectorEnv(0)
    with pytest.raises(ValueError, match=r"unknown engine 'x'"):
        gym.make_vec(ROLL, num_envs=2, vectorization_mode="vector_entry_point", engine="x")
    vec = TensegrityVectorEnv(2, engine="mujoco")
    with pytest.raises(ValueError, match="3 seeds given for 2 envs"):
        vec.reset(seed=[1, 2, 3])
    vec.close()


def test_every_simulated_id_has_the_vector_entry_point() -> None:
    for env_id in tensegrity_gym.env_ids():
        assert gym.spec(env_id).vector_entry_point == "tensegrity_gym.envs.vector:make_vector_env"
    for env_id in tensegrity_gym.env_ids(hardware=True):
        assert gym.spec(env_id).vector_entry_point is None


def test_sb3_trains_on_the_vector_env_as_on_single_envs() -> None:
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    from agents.training.vec_env import Sb3VecEnv

    def native() -> Sb3VecEnv:
        return Sb3VecEnv(gym.make_vec(ROLL, num_envs=2, vectorization_mode="vector_entry_point",
                                      max_episode_steps=3, engine="mujoco",
                                      autoreset_mode=AutoresetMode.SAME_STEP))  # fmt: skip

    dummy = DummyVecEnv(
        [lambda: gym.make(ROLL, max_episode_steps=3, engine="mujoco") for _ in range(2)]
    )
    ours = native()
    for venv in (dummy, ours):
        venv.seed(4)
    a, b = dummy.reset(), ours.reset()
    assert np.array_equal(a, b)
    for action in _actions(2, 5, seed=1):
        ra, rb = dummy.step(action), ours.step(action)
        for x, y in zip(ra[:3], rb[:3], strict=True):
            assert np.array_equal(x, y)
        for ia, ib in zip(ra[3], rb[3], strict=True):
            assert ia.keys() == ib.keys()  # the ended step's info, not the new episode's
            for key in ia:
                assert np.array_equal(ia[key], ib[key]), key
        for ia, ib in zip(dummy.reset_infos, ours.reset_infos, strict=True):
            assert ia.keys() == ib.keys()
            for key in ia:
                assert np.array_equal(ia[key], ib[key]), key
    dummy.close()
    model = PPO("MlpPolicy", ours, n_steps=16, batch_size=16, n_epochs=1, seed=0, device="cpu")
    model.learn(32)
    assert model.num_timesteps == 32
    ours.close()
