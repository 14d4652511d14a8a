"""The Gymnasium env: API checks, determinism, bad input, safety, pickling."""

from __future__ import annotations

import pickle
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env, env_render_passive_checker

from tensegrity_gym.envs.factory import make_roll_env
from tensegrity_gym.model.estimate import Estimate
from tensegrity_gym.model.kinematics import member_lengths
from tests.conftest import ENV_IDS


def test_contract_ids_are_registered() -> None:
    for env_id in ("tensegrity_gym/ThreeBarRoll-v0", "tensegrity_gym/SuperBallRoll-v0"):
        assert env_id in ENV_IDS
        assert gym.spec(env_id).max_episode_steps is not None


_SLOW_CHECKS = {
    "tensegrity_gym_hardware/SuperBallGoTo-v0",
    "tensegrity_gym_hardware/SuperBallRoll-v0",
}
"""Ids whose check runs with the slow tests (over 30 s each against the emulator): the
3-bar's hardware ids check the same link in the default run."""


@pytest.mark.parametrize(
    "env_id",
    [pytest.param(i, marks=pytest.mark.slow) if i in _SLOW_CHECKS else i for i in ENV_IDS],
)
def test_gymnasium_check_env(env_id: str, make_env) -> None:
    env = make_env(env_id)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        # Warnings are errors here, and "human" without a display warns that it shows no
        # window (check_env with its defaults passes headless: tests/envs/test_rough_edges.py);
        # rgb_array is checked below.
        check_env(env.unwrapped, skip_render_check=True)
    env.close()


_SB3_DEFAULT = ("tensegrity_gym/ThreeBarRoll-v0", "tensegrity_gym_hardware/ThreeBarRoll-v0")
"""The ids SB3's checker runs on by default (one a namespace); Gymnasium's runs on all."""


@pytest.mark.parametrize(
    "env_id",
    [i if i in _SB3_DEFAULT else pytest.param(i, marks=pytest.mark.slow) for i in ENV_IDS],
)
def test_sb3_check_env(env_id: str, make_env) -> None:
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = make_env(env_id)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sb3_check_env(env.unwrapped, warn=True)
    env.close()


def test_rgb_array_render() -> None:
    env = gym.make("tensegrity_gym/ThreeBarRoll-v0", render_mode="rgb_array")
    env.reset(seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env_render_passive_checker(env.unwrapped)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.shape == (360, 480, 3)
    assert frame.reshape(-1, 3).std(axis=0).max() > 5.0  # a scene, not a blank image
    env.close()


def test_observations_are_finite_float32_within_bounds(three_bar_env) -> None:
    obs, _ = three_bar_env.reset(seed=3)
    space = three_bar_env.observation_space
    assert np.all(np.isfinite(space.low)) and np.all(np.isfinite(space.high))
    rng = np.random.default_rng(0)
    for _ in range(30):
        obs, reward, *_ = three_bar_env.step(rng.uniform(-1, 1, 6).astype(np.float32))
        assert obs.dtype == np.float32 and space.contains(obs)
        assert np.isfinite(reward)


def _rollout(seed: int, steps: int = 25, env_id: str = "tensegrity_gym/ThreeBarRoll-v0") -> list:
    env = gym.make(env_id)
    rng = np.random.default_rng(seed + 100)
    obs, info = env.reset(seed=seed)
    record = [obs, info["com_true"], info.get("goal")]
    for _ in range(steps):
        obs, reward, terminated, truncated, info = env.step(
            rng.uniform(-1, 1, 6).astype(np.float32)
        )
        record += [obs, reward, terminated, truncated, info["com_true"], info["com_estimate"]]
        record += [info.get("goal")]
    env.close()
    return record


def _equal(a: list, b: list) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


@pytest.mark.parametrize(
    "env_id", ["tensegrity_gym/ThreeBarRoll-v0", "tensegrity_gym/ThreeBarGoTo-v0"]
)
def test_same_seed_same_episode_bit_for_bit(env_id: str) -> None:
    assert _equal(_rollout(7, env_id=env_id), _rollout(7, env_id=env_id))
    assert not _equal(_rollout(7, env_id=env_id), _rollout(8, env_id=env_id))


def test_goto_goal_is_drawn_from_the_seed_and_reported() -> None:
    env = gym.make("tensegrity_gym/ThreeBarGoTo-v0", goal_range=(1.0, 1.5), success_radius=0.2)
    goals = [env.reset(seed=seed)[1]["goal"] for seed in (3, 3, 4)]
    np.testing.assert_array_equal(goals[0], goals[1])
    assert not np.array_equal(goals[0], goals[2])
    _, info = env.reset(seed=3)
    assert 1.0 <= info["distance_to_goal"] <= 1.5 and info["goals_reached"] == 0
    assert gym.spec("tensegrity_gym/ThreeBarGoTo-v0").max_episode_steps == 600
    env.close()


def test_reset_with_seed_repeats_the_episode(three_bar_env) -> None:
    a = np.full(6, -0.5, dtype=np.float32)
    runs = []
    for _ in range(2):
        obs, _ = three_bar_env.reset(seed=11)
        seq = [obs]
        for _ in range(10):
            seq.append(three_bar_env.step(a)[0])
        runs.append(seq)
    assert _equal(*runs)


def test_settled_robot_keeps_rod_lengths_and_taut_cables(three_bar_env) -> None:
    env = three_bar_env.unwrapped
    d = env.backend.description
    env.reset(seed=0)
    hold = env.targets_to_action(d.rest_lengths[d.actuated])
    for _ in range(20):
        env.step(hold)
    truth = env.backend.ground_truth()
    rods = member_lengths(truth.node_positions, d.rod_nodes)
    np.testing.assert_allclose(rods, [r.length for r in d.rods], atol=1e-6)
    cables = member_lengths(truth.node_positions, d.cable_nodes)
    assert np.all(cables > d.rest_lengths), "every cable is taut at rest"
    assert np.abs(truth.node_velocities).max() < 0.01


def test_nan_action_names_the_bad_entries(three_bar_env) -> None:
    three_bar_env.reset(seed=0)
    action = np.zeros(6, dtype=np.float32)
    action[[1, 4]] = [np.nan, np.inf]
    with pytest.raises(ValueError, match=r"entries \[1, 4\].*not finite"):
        three_bar_env.step(action)
    with pytest.raises(ValueError, match="shape"):
        three_bar_env.step(np.zeros(5, dtype=np.float32))


def test_out_of_range_actions_are_clipped_silently(three_bar_env) -> None:
    env = three_bar_env.unwrapped
    np.testing.assert_array_equal(
        env.action_to_targets(np.full(6, 5.0)), env.action_to_targets(np.ones(6))
    )
    lo, hi, _ = env.backend.description.motor_limits
    np.testing.assert_allclose(env.action_to_targets(-np.ones(6)), lo)
    np.testing.assert_allclose(env.action_to_targets(np.ones(6)), hi)
    env.reset(seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        obs, *_ = env.step(np.full(6, 3.0, dtype=np.float32))
    assert np.all(np.isfinite(obs))


def test_bad_names_fail_with_the_valid_choices() -> None:
    with pytest.raises(ValueError, match=r"unknown estimator 'kalman'.*oracle"):
        gym.make("tensegrity_gym/ThreeBarRoll-v0", estimator="kalman")
    with pytest.raises(ValueError, match="driver"):
        gym.make("tensegrity_gym/ThreeBarRoll-v0", driver="ros://robot")
    with pytest.raises(ValueError, match="render_mode"):
        make_roll_env("three_bar", render_mode="video")


def test_divergence_truncates_with_a_flag_and_finite_observation(three_bar_env) -> None:
    env = three_bar_env.unwrapped
    obs, _ = env.reset(seed=0)
    world = env.backend.world
    truth = env.backend.ground_truth()
    fast = np.zeros((3, 3))
    fast[0] = [1e4, 0.0, 0.0]  # an absurd speed, as a blown-up integration gives
    world.set_rod_states(truth.rod_positions, truth.rod_quaternions, fast)
    obs, reward, terminated, truncated, info = env.step(np.zeros(6, dtype=np.float32))
    assert truncated and not terminated
    assert info["sim_diverged"] is True
    assert np.all(np.isfinite(obs)) and reward == 0.0
    assert "com_true" not in info
    env.reset(seed=0)  # and the env recovers on reset
    assert env.step(np.zeros(6, dtype=np.float32))[4]["sim_diverged"] is False


class _NanEstimator:
    """An estimator gone bad: every estimate is NaN."""

    needs_camera = False

    def _nan(self) -> Estimate:
        return Estimate(
            t=0.0,
            node_positions=np.full((6, 3), np.nan),
            node_velocities=np.full((6, 3), np.inf),
            com=np.full(3, np.nan),
            rest_lengths=np.full(6, np.nan),
        )

    def reset(self, *args, **kwargs) -> Estimate:
        return self._nan()

    def update(self, samples, command) -> Estimate:
        return self._nan()


def test_no_nan_reaches_the_policy() -> None:
    env = make_roll_env("three_bar", estimator=_NanEstimator())
    obs, _ = env.reset(seed=0)
    assert np.all(np.isfinite(obs))
    obs, reward, *_ = env.step(np.zeros(6, dtype=np.float32))
    assert np.all(np.isfinite(obs)) and np.isfinite(reward)
    env.close()


def test_estimator_must_follow_the_protocol() -> None:
    with pytest.raises(TypeError, match="estimator must be one of"):
        make_roll_env("three_bar", estimator=42)  # type: ignore[arg-type]


def test_env_pickles_and_runs_after_unpickling(three_bar_env) -> None:
    three_bar_env.reset(seed=0)
    clone = pickle.loads(pickle.dumps(three_bar_env.unwrapped))
    obs_a, _ = clone.reset(seed=5)
    obs_b, _ = three_bar_env.unwrapped.reset(seed=5)
    np.testing.assert_array_equal(obs_a, obs_b)
    a = np.zeros(6, dtype=np.float32)
    np.testing.assert_array_equal(clone.step(a)[0], three_bar_env.unwrapped.step(a)[0])
    clone.close()


@pytest.mark.slow  # two worker processes importing the package: over 20 s
def test_subproc_vec_env_runs_one_client_per_worker() -> None:
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv

    # "module:id" makes each worker import the package, which registers the ids.
    vec = make_vec_env(
        "tensegrity_gym:tensegrity_gym/ThreeBarRoll-v0",
        n_envs=2,
        seed=0,
        vec_env_cls=SubprocVecEnv,
    )
    obs = vec.reset()
    for _ in range(5):
        obs, _rewards, _dones, _infos = vec.step(np.zeros((2, 6), dtype=np.float32))
    assert obs.shape == (2, 44) and np.all(np.isfinite(obs))
    assert not np.array_equal(obs[0], obs[1])  # seeds 0 and 1: different episodes
    vec.close()
