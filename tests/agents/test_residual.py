"""Residual actions (``gym.make(..., residual_gait=SCALE)``): a policy's action corrects
the robot's scripted gait; trained so, it is evaluated so."""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import tensegrity_gym  # noqa: F401  (registers the envs)
from agents.evaluation.evaluate import _condition_env, _release_env, condition, load_policy
from agents.training.train import train
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.model.protocols import ActionBase
from tensegrity_gym.tasks.gaits import FaceGait

if TYPE_CHECKING:
    from pathlib import Path

THREE_BAR = "tensegrity_gym/ThreeBarRoll-v0"


def _com_after(env: gym.Env, act, steps: int = 40) -> np.ndarray:  # type: ignore[no-untyped-def, type-arg]
    obs, info = env.reset(seed=4)
    for _ in range(steps):
        obs, _, _, _, info = env.step(act(obs))
    env.close()
    return np.asarray(info["com_true"])


def test_a_zero_correction_is_the_gait_bit_for_bit() -> None:
    residual = gym.make(THREE_BAR, estimator="oracle", residual_gait=0.5)
    zeros = np.zeros(residual.action_space.shape, dtype=np.float32)
    plain = gym.make(THREE_BAR, estimator="oracle")
    inner = plain.unwrapped
    gait = FaceGait(inner.backend.description, inner.task)  # type: ignore[attr-defined]
    on_its_own = _com_after(plain, gait)
    assert np.array_equal(_com_after(residual, lambda obs: zeros), on_its_own)
    # The gait rolled the robot; a correction changes where it goes.
    assert np.linalg.norm(on_its_own[:2]) > 0.1
    against = gym.make(THREE_BAR, estimator="oracle", residual_gait=1.0)
    full = np.ones(against.action_space.shape, dtype=np.float32)
    assert not np.allclose(_com_after(against, lambda obs: full), on_its_own)


def _rewards(env: gym.Env, act, steps: int = 30) -> np.ndarray:  # type: ignore[no-untyped-def, type-arg]
    obs, _ = env.reset(seed=4)
    rewards = []
    for _ in range(steps):
        obs, reward, _, _, _ = env.step(act(obs))
        rewards.append(reward)
    env.close()
    return np.array(rewards)


def test_the_control_cost_is_the_corrections_not_the_gaits() -> None:
    """The gait's own commands are free: a zero correction earns the gait's progress
    reward alone, and a correction pays ``ctrl_cost`` times its mean square."""
    plain = gym.make(THREE_BAR, estimator="oracle", ctrl_cost=0.0)
    inner = plain.unwrapped
    gait = FaceGait(inner.backend.description, inner.task)  # type: ignore[attr-defined]
    free = _rewards(plain, gait)
    residual = gym.make(THREE_BAR, estimator="oracle", residual_gait=0.5, ctrl_cost=0.05)
    zeros = np.zeros(residual.action_space.shape, dtype=np.float32)
    assert np.array_equal(_rewards(residual, lambda obs: zeros), free)
    assert np.abs(free).sum() > 0  # the gait's rolling earned (or lost) progress
    half = np.full(residual.action_space.shape, 0.5, dtype=np.float32)
    charged = gym.make(THREE_BAR, estimator="oracle", residual_gait=0.5, ctrl_cost=0.05)
    uncharged = gym.make(THREE_BAR, estimator="oracle", residual_gait=0.5, ctrl_cost=0.0)
    difference = _rewards(uncharged, lambda obs: half) - _rewards(charged, lambda obs: half)
    np.testing.assert_allclose(difference, 0.05 * 0.25, rtol=1e-6)


def test_a_deadband_leaves_small_corrections_out_and_shrinks_the_others() -> None:
    """``residual_deadband=d``: actions within d of 0 are the gait bit for bit; a larger
    one corrects it by its excess over d (soft thresholding)."""

    def banded() -> gym.Env:  # type: ignore[type-arg]
        return gym.make(THREE_BAR, estimator="oracle", residual_gait=0.5, residual_deadband=0.2)

    def plain() -> gym.Env:  # type: ignore[type-arg]
        return gym.make(THREE_BAR, estimator="oracle", residual_gait=0.5)

    m = plain().action_space.shape[0]
    rng = np.random.default_rng(1)
    small = iter(rng.uniform(-0.19, 0.19, (40, m)).astype(np.float32))
    zeros = np.zeros(m, dtype=np.float32)
    assert np.array_equal(
        _com_after(banded(), lambda obs: next(small)), _com_after(plain(), lambda obs: zeros)
    )
    large = rng.uniform(-1.0, 1.0, m).astype(np.float32)
    wide = large.astype(np.float64)
    excess = np.sign(wide) * np.maximum(np.abs(wide) - 0.2, 0.0)
    assert np.count_nonzero(excess) > 0
    env = banded()
    np.testing.assert_array_equal(env.unwrapped.correction(wide), excess)  # type: ignore[attr-defined]
    shrunk = _com_after(env, lambda obs: large)
    assert np.array_equal(shrunk, _com_after(plain(), lambda obs: excess))
    assert not np.allclose(shrunk, _com_after(plain(), lambda obs: large))


@pytest.mark.parametrize("observe_base", [False, True])
def test_the_residual_env_passes_gymnasiums_checks(observe_base: bool) -> None:
    env = gym.make(THREE_BAR, estimator="oracle", residual_gait=0.5, observe_base=observe_base)
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


def test_an_observed_base_is_the_gaits_command_for_the_step_to_come() -> None:
    """``observe_base=True`` appends the gait's action for the next step to the
    observation (the gait's phase and choice, which the robot's state does not hold);
    the episode is the same as without it, bit for bit."""
    seen = gym.make(THREE_BAR, estimator="oracle", residual_gait=0.5, observe_base=True)
    blind = gym.make(THREE_BAR, estimator="oracle", residual_gait=0.5)
    m = seen.action_space.shape[0]
    assert seen.observation_space.shape[0] == blind.observation_space.shape[0] + m
    plain = gym.make(THREE_BAR, estimator="oracle")
    inner = plain.unwrapped
    gait = FaceGait(inner.backend.description, inner.task)  # type: ignore[attr-defined]
    corrections = np.random.default_rng(0).normal(0.0, 0.3, (40, m)).astype(np.float32)
    obs, _ = seen.reset(seed=4)
    blind_obs, _ = blind.reset(seed=4)
    plain_obs, _ = plain.reset(seed=4)
    commands = []
    for correction in corrections:
        np.testing.assert_array_equal(obs[:-m], blind_obs)
        command = gait(plain_obs)
        np.testing.assert_array_equal(obs[-m:], command)  # what it will command
        commands.append(command)
        obs, *_ = seen.step(correction)
        blind_obs, *_ = blind.step(correction)
        plain_obs, *_ = plain.step(np.clip(command + 0.5 * correction, -1.0, 1.0))
    # The gait contracted and released within those 40 steps: the part is not constant.
    assert np.ptp(np.array(commands), axis=0).max() > 0.5
    for env in (seen, blind, plain):
        env.close()


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"base_gait": "steer"}, r"^make: base_gait='steer' names .*give residual_gait"),
        ({"residual_gait": 0.5, "base_gait": 3}, r"^make: base_gait must be a gait's name"),
        ({"observe_base": True}, r"^make: observe_base=True shows .*give residual_gait"),
        ({"residual_gait": 0.5, "observe_base": 1}, r"^make: observe_base must be True or"),
        ({"residual_deadband": 0.1}, r"^make: residual_deadband leaves .*give residual_gait"),
    ],
)
def test_a_base_gait_without_residual_actions_is_refused(
    kwargs: dict[str, object], message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        gym.make(THREE_BAR, estimator="oracle", **kwargs)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"residual_gait": 0.0}, "residual_gait=0.0 must be a finite number and > 0"),
        ({"residual_gait": "big"}, "residual_gait='big' must be a finite number"),
        ({"residual_gait": 0.5, "residual_deadband": -0.1}, "residual_deadband=-0.1 must be a"),
        (
            {"residual_gait": 0.5, "residual_deadband": 1.0},
            "residual_deadband=1.0 must be a finite number in",
        ),
        ({"residual_gait": 0.5, "residual_deadband": "x"}, "residual_deadband='x' must be a"),
        ({"residual_gait": 0.5, "residual_deadband": float("nan")}, "residual_deadband=nan must"),
        (
            {
                "residual_gait": 0.5,
                "robot": replace(load_robot("three_bar"), gait=None, named_gaits=()),
            },
            "three_bar's gaits: none",
        ),
    ],
)
def test_bad_residual_arguments_are_refused(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        gym.make(THREE_BAR, estimator="oracle", **kwargs)


def test_a_policy_trained_on_residual_actions_is_evaluated_on_them(tmp_path: Path) -> None:
    out = tmp_path / "run"
    config = tmp_path / "ppo.yml"
    config.write_text(
        f"{THREE_BAR}:\n  n_envs: 1\n  n_steps: 32\n  batch_size: 32\n  n_epochs: 1\n"
        "  policy: MlpPolicy\n"
    )
    train(
        THREE_BAR,
        "ppo",
        "oracle",
        out,
        timesteps=32,
        seed=1,
        config_file=config,
        progress_bar=False,
        env_kwargs={
            "max_episode_steps": 16,
            "residual_gait": 0.25,
            "base_gait": "steer",
            "observe_base": True,
            "ctrl_cost": 0.0,
        },
    )
    policy = load_policy(out)
    # what its actions and observations mean goes with it; its reward and episode
    # length were its training's: every row of an evaluation runs on the env id's task
    assert policy.env_kwargs == {"residual_gait": 0.25, "base_gait": "steer", "observe_base": True}
    try:
        env = _condition_env(policy.env_id, condition("oracle"), policy.env_kwargs).unwrapped
        assert isinstance(env.action_base, FaceGait) and env.residual_scale == 0.25  # type: ignore[attr-defined]
        assert env.action_base.gait == "steer" and env.observe_base  # type: ignore[attr-defined]
        obs, _ = env.reset(seed=0)
        assert policy.act(obs).shape == env.action_space.shape
        assert isinstance(env.action_base, ActionBase)  # type: ignore[attr-defined]
        assert env.task.ctrl_cost == 0.05  # type: ignore[attr-defined]
        plain = _condition_env(policy.env_id, condition("oracle"), {}).unwrapped
        assert plain.action_base is None  # type: ignore[attr-defined]
    finally:
        _release_env()


class _Commanding:
    """A backend that reports the targets that drove each period, as the robot link's
    driver does: the ones asked for (``trim=None``), else these."""

    def __init__(self, inner: object, trim: np.ndarray | None = None) -> None:
        self._inner, self._trim = inner, trim

    def __getattr__(self, name: str) -> object:
        return getattr(self._inner, name)

    def step(self, targets: np.ndarray) -> object:
        driven = np.array(targets if self._trim is None else self._trim, dtype=np.float64)
        return replace(self._inner.step(driven), command=driven)  # type: ignore[attr-defined]


def test_a_backend_that_reports_its_command_is_charged_what_drove_it() -> None:
    """A robot that reports the command it was asked for (the link's driver) charges
    the correction as the simulation does; one that drove other targets (a limiter, a
    replayed log) charges the action those imply."""

    def run(trim: np.ndarray | None, ctrl_cost: float, **kwargs: object) -> np.ndarray:
        env = gym.make(THREE_BAR, estimator="oracle", ctrl_cost=ctrl_cost, **kwargs)
        env.unwrapped.backend = _Commanding(env.unwrapped.backend, trim)  # type: ignore[attr-defined]
        half = np.full(env.action_space.shape, 0.5, dtype=np.float32)
        return _rewards(env, lambda obs: half)

    echoed = run(None, 0.05, residual_gait=0.5)
    plain = gym.make(THREE_BAR, estimator="oracle", residual_gait=0.5, ctrl_cost=0.05)
    half = np.full(plain.action_space.shape, 0.5, dtype=np.float32)
    assert np.array_equal(echoed, _rewards(plain, lambda obs: half))
    # Absolute actions, the robot held at the middle of the motors' range (action 0):
    # asked for 0.5 everywhere, charged nothing.
    env = gym.make(THREE_BAR, estimator="oracle").unwrapped
    middle = env.action_to_targets(np.zeros(env.action_space.shape))  # type: ignore[attr-defined]
    env.close()
    np.testing.assert_array_equal(run(middle, 0.05), run(middle, 0.0))


def test_with_a_deadband_the_cost_charges_the_action_or_the_least_one_that_drove() -> None:
    """With ``residual_deadband``, a step charges the policy's action itself (the band
    included); where the backend drove other targets, the least action that implies
    them: the correction they make, moved out by the band."""
    env = gym.make(THREE_BAR, estimator="oracle", residual_gait=0.5, residual_deadband=0.2)
    inner = env.unwrapped
    m = env.action_space.shape[0]
    base = np.zeros(m)
    action = np.linspace(-0.9, 0.9, m)
    asked = inner.action_to_targets(base + 0.5 * inner.correction(action))  # type: ignore[attr-defined]
    charged = inner._charged(action, base, asked, asked)  # type: ignore[attr-defined]
    np.testing.assert_allclose(charged, action, atol=1e-7)
    correction = np.zeros(m)
    correction[0], correction[-1] = 0.3, -0.1  # the others: none
    driven = inner.action_to_targets(base + 0.5 * correction)  # type: ignore[attr-defined]
    expected = np.sign(correction) * (np.abs(correction) + 0.2 * (correction != 0))
    charged = inner._charged(action, base, asked, driven)  # type: ignore[attr-defined]
    np.testing.assert_allclose(charged, expected, atol=1e-6)
    env.close()


def test_a_base_set_mid_episode_asks_for_a_reset_and_decode_refuses_the_longer_observation() -> (
    None
):
    env = gym.make(THREE_BAR, estimator="oracle")
    inner = env.unwrapped
    obs, _ = env.reset(seed=0)
    env.step(np.zeros(env.action_space.shape, dtype=np.float32))
    gait = FaceGait(inner.backend.description, inner.task)  # type: ignore[attr-defined]
    inner.correct(gait, 0.5, observe=True)  # type: ignore[attr-defined]
    with pytest.raises(RuntimeError, match="call reset"):
        env.step(np.zeros(env.action_space.shape, dtype=np.float32))
    longer, _ = env.reset(seed=0)
    assert longer.shape == inner.observation_space.shape == (obs.size + gait.hold_action.size,)  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match=r"RollTask.decode: an observation of shape"):
        inner.task.decode(longer)  # type: ignore[attr-defined]
    env.close()


def test_record_and_view_make_a_runs_env_with_what_its_actions_mean(tmp_path: Path) -> None:
    from agents.recordings.offline import policy_env_kwargs

    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text(
        "env_id: tensegrity_gym/ThreeBarRoll-v0\nenv_kwargs:\n  residual_gait: 0.5\n"
        "  base_gait: steer\n  observe_base: true\n  ctrl_cost: 0.0\n"
    )
    (run / "model.zip").write_bytes(b"")
    expected = {"residual_gait": 0.5, "base_gait": "steer", "observe_base": True}
    assert policy_env_kwargs(str(run)) == expected
    assert policy_env_kwargs(str(run / "model.zip")) == expected
    assert policy_env_kwargs("scripted") == policy_env_kwargs(str(tmp_path / "none")) == {}


def test_residual_corrections_counts_the_actions_that_leave_the_deadband() -> None:
    """``scripts/residual_corrections.py``: a policy whose actions stay within the band
    corrects nothing; one whose entries leave it corrects those, by their excess."""
    import importlib.util
    from pathlib import Path

    from agents.evaluation.evaluate import LoadedPolicy

    path = Path(__file__).resolve().parents[2] / "scripts" / "residual_corrections.py"
    spec = importlib.util.spec_from_file_location("residual_corrections", path)
    assert spec is not None and spec.loader is not None
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    kwargs = {"residual_gait": 0.5, "residual_deadband": 0.2}
    env = gym.make(THREE_BAR, estimator="oracle", **kwargs)
    m = env.action_space.shape[0]
    inside = np.full(m, 0.15, dtype=np.float32)
    quiet = LoadedPolicy("quiet", THREE_BAR, "-", lambda obs: inside, env_kwargs=kwargs)
    f = script.measure(quiet, env, episodes=2, seed=1000, steps=5)
    assert f["steps"] == 10 and f["entries_corrected"] == f["correction_rms"] == 0.0
    assert f["largest_entry"] == pytest.approx(0.15)
    half_out = np.where(np.arange(m) % 2 == 0, 0.5, 0.1).astype(np.float32)
    loud = LoadedPolicy("loud", THREE_BAR, "-", lambda obs: half_out, env_kwargs=kwargs)
    f = script.measure(loud, env, episodes=1, seed=1000, steps=5)
    assert f["steps_corrected"] == 1.0
    assert f["entries_corrected"] == pytest.approx(np.mean(np.arange(m) % 2 == 0))
    env.close()
