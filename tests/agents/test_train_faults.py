"""Training's faults: a hyperparameter out of its range is refused in one line before any
env is made, and a run whose numbers turn non-finite stops with a named error, keeping
the last good checkpoint and never writing a model with a NaN in it."""

from __future__ import annotations

import logging
import math
import re
from typing import TYPE_CHECKING, Any

import pytest
import yaml
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback

import agents.training.train
from agents.training.guards import TrainingDivergedError, nonfinite, replace_atomically
from agents.training.hyperparams import VALID
from agents.training.train import load_hyperparams, train
from tests.agents.test_train import THREE_BAR, _tiny_config

if TYPE_CHECKING:
    from pathlib import Path


@pytest.fixture
def no_env(monkeypatch: pytest.MonkeyPatch) -> None:
    """Making an env fails the test: a refusal must come before the first."""

    def made(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("an env was made before the hyperparameters were checked")

    monkeypatch.setattr(agents.training.train, "make_training_env", made)


# ---------------------------------------------------------------------- ranges

REFUSED = [
    ({"gamma": 2.0}, "--hyperparams gamma: 2.0 is not a number in [0, 1]"),
    ({"gamma": -0.1}, "--hyperparams gamma: -0.1 is not a number in [0, 1]"),
    ({"gamma": "abc"}, "--hyperparams gamma: 'abc' is not a number in [0, 1]"),
    ({"gae_lambda": 1.5}, "--hyperparams gae_lambda: 1.5 is not a number in [0, 1]"),
    ({"learning_rate": 0}, "--hyperparams learning_rate: 0 is not a number > 0"),
    ({"learning_rate": True}, "--hyperparams learning_rate: True is not a number > 0"),
    ({"learning_rate": "lin_3e-4"}, "learning_rate: 'lin_3e-4' is not a number > 0"),
    ({"n_steps": -5}, "--hyperparams n_steps: -5 is not a whole number >= 1"),
    ({"n_steps": 2.5}, "--hyperparams n_steps: 2.5 is not a whole number >= 1"),
    ({"batch_size": 0}, "--hyperparams batch_size: 0 is not a whole number >= 1"),
    ({"n_epochs": 0}, "--hyperparams n_epochs: 0 is not a whole number >= 1"),
    ({"clip_range": 0.0}, "--hyperparams clip_range: 0.0 is not a number > 0"),
    ({"clip_range_vf": -1}, "clip_range_vf: -1 is not a number > 0 or None"),
    ({"ent_coef": -0.01}, "--hyperparams ent_coef: -0.01 is not a number >= 0"),
    ({"vf_coef": -1.0}, "--hyperparams vf_coef: -1.0 is not a number >= 0"),
    ({"max_grad_norm": 0}, "--hyperparams max_grad_norm: 0 is not a number > 0"),
    ({"target_kl": 0}, "--hyperparams target_kl: 0 is not a number > 0 or None"),
    ({"use_sde": "yes"}, "--hyperparams use_sde: 'yes' is not True or False"),
    ({"normalize_advantage": 1}, "normalize_advantage: 1 is not True or False"),
    ({"sde_sample_freq": -2}, "sde_sample_freq: -2 is not a whole number >= -1"),
    ({"n_envs": 0}, "--hyperparams n_envs: 0 is not a whole number >= 1"),
    ({"n_timesteps": -1}, "--hyperparams n_timesteps: -1 is not a whole number >= 1"),
    ({"policy": "MLP"}, "policy: 'MLP' is not 'MlpPolicy', 'CnnPolicy' or 'MultiInputPolicy'"),
    # the keys that bound each other: PPO's minibatches against its rollout
    ({"batch_size": 128}, "batch_size: 128 is not a whole number in [2, 64] (a minibatch"),
    ({"batch_size": 1}, "batch_size: 1 is not a whole number in [2, 64]"),
    ({"n_steps": 1, "batch_size": 2}, "n_steps * n_envs = 1 * 1 = 1: a PPO rollout"),
]


@pytest.mark.parametrize(("given", "message"), REFUSED)
def test_a_hyperparameter_out_of_range_is_refused_before_any_env(
    given: dict[str, Any], message: str, tmp_path: Path, no_env: None
) -> None:
    out = tmp_path / "run"
    with pytest.raises(ValueError, match=re.escape(message)) as refused:
        train(
            THREE_BAR,
            "ppo",
            "oracle",
            out,
            timesteps=64,
            config_file=_tiny_config(tmp_path),
            hyperparams=given,
            progress_bar=False,
        )
    assert "\n" not in str(refused.value)
    assert not out.exists()


@pytest.mark.parametrize(
    ("given", "message"),
    [
        ({"tau": 0}, "--hyperparams tau: 0 is not a number in (0, 1]"),
        ({"ent_coef": "auto_0"}, "ent_coef: 'auto_0' is not a number >= 0, 'auto' or 'auto_<x>'"),
        ({"ent_coef": -1}, "--hyperparams ent_coef: -1 is not a number >= 0, 'auto'"),
        ({"train_freq": [1, "epoch"]}, "train_freq: [1, 'epoch'] is not a whole number >= 1 or"),
        ({"gradient_steps": 0}, "gradient_steps: 0 is not a whole number >= 1 or -1"),
        ({"learning_starts": -1}, "learning_starts: -1 is not a whole number >= 0"),
        ({"buffer_size": 0.5}, "--hyperparams buffer_size: 0.5 is not a whole number >= 1"),
        ({"target_entropy": "low"}, "target_entropy: 'low' is not a finite number or 'auto'"),
    ],
)
def test_sacs_own_keys_are_checked_too(given: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError, match=re.escape(message)):
        load_hyperparams("sac", THREE_BAR, overrides=given)


def test_valid_values_pass_as_the_algorithm_takes_them() -> None:
    """A whole float (YAML's ``!!float 1e5``) is an int to SB3's arrays; a train_freq
    pair stays a list for config.yaml (the trainer makes it a tuple for SB3)."""
    sac = load_hyperparams(
        "sac",
        THREE_BAR,
        overrides={"ent_coef": "auto_0.1", "train_freq": [4, "episode"], "gradient_steps": -1},
    )
    assert sac["ent_coef"] == "auto_0.1" and sac["train_freq"] == [4, "episode"]
    assert sac["gradient_steps"] == -1
    ppo = load_hyperparams("ppo", THREE_BAR, overrides={"n_steps": 512.0, "target_kl": None})
    assert ppo["n_steps"] == 512 and isinstance(ppo["n_steps"], int)
    assert isinstance(ppo["n_timesteps"], int)  # !!float 1.2e5 in ppo.yml
    assert ppo["target_kl"] is None


def test_the_table_names_only_keys_the_algorithms_take() -> None:
    import inspect

    for algo, rules in VALID.items():
        own = set(
            inspect.signature(agents.training.train._algorithm_class(algo).__init__).parameters
        )
        assert set(rules) - own <= agents.training.train._RUN_KEYS, algo


def test_a_config_files_bad_value_names_the_file_and_its_entry(tmp_path: Path) -> None:
    config = _tiny_config(tmp_path, n_epochs=0)
    with pytest.raises(ValueError, match=rf"^{re.escape(str(config))}: {THREE_BAR} n_epochs: 0"):
        load_hyperparams("ppo", THREE_BAR, config)
    # another task's id takes its robot's rolling entry: the error names that entry
    with pytest.raises(ValueError, match=rf": {THREE_BAR} n_epochs: 0 is not a whole number"):
        load_hyperparams("ppo", "tensegrity_gym/ThreeBarGoTo-v0", config)
    # a value --hyperparams replaces is never used, and not refused
    assert load_hyperparams("ppo", THREE_BAR, config, {"n_epochs": 3})["n_epochs"] == 3


@pytest.mark.parametrize(
    ("given", "message"),
    [
        ("gamma:2.0", "--hyperparams gamma: 2.0 is not a number in [0, 1]"),
        ("n_steps:-5", "--hyperparams n_steps: -5 is not a whole number >= 1"),
        ("batch_size:0", "--hyperparams batch_size: 0 is not a whole number >= 1"),
        ("n_steps:2.5", "--hyperparams n_steps: 2.5 is not a whole number >= 1"),
        ("gamma:'abc'", "--hyperparams gamma: 'abc' is not a number in [0, 1]"),
    ],
)
def test_the_command_line_says_a_bad_hyperparameter_in_one_line_and_exits_2(
    given: str, message: str, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from agents.cli import main

    out = tmp_path / "t"
    argv = ["train", "--out", str(out), "--config", str(_tiny_config(tmp_path))]
    with caplog.at_level(logging.ERROR):
        code = main([*argv, "--timesteps", "64", "--no-progress", "--hyperparams", given])
    assert code == 2
    [error] = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert error == message
    assert not out.exists()


# ---------------------------------------------------------------------- divergence


class _Poison(BaseCallback):
    """Puts a NaN into the value net at the end of the rollout that reaches ``at``
    steps: the update that follows makes every weight NaN (its gradients are)."""

    def __init__(self, at: int) -> None:
        super().__init__()
        self.at = at

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        if self.num_timesteps == self.at:
            self.model.policy.value_net.weight.data[0, 0] = math.nan


def _diverge(tmp_path: Path, at: int, **config: Any) -> tuple[Path, TrainingDivergedError]:
    """256 steps of the tiny PPO (rollouts of 64), poisoned at ``at``; a stale
    ``model.zip`` of another run lies in the folder first."""
    out = tmp_path / "run"
    out.mkdir()
    (out / "model.zip").write_bytes(b"an earlier run's model")
    with pytest.raises(TrainingDivergedError) as diverged:
        train(
            THREE_BAR,
            "ppo",
            "oracle",
            out,
            timesteps=256,
            seed=1,
            config_file=_tiny_config(tmp_path, **config),
            progress_bar=False,
            checkpoint_every=64,
            callbacks=[_Poison(at)],
        )
    return out, diverged.value


def _assert_finite_and_whole(out: Path) -> None:
    for path in (out / "checkpoints").glob("model_*_steps.zip"):
        assert nonfinite(PPO.load(path, device="cpu")) is None, path
    assert not list(out.rglob(".*partial*"))  # no temporary file left behind


@pytest.mark.parametrize(("at", "kept"), [(192, 128), (256, 192)])
def test_a_nan_update_stops_the_run_and_keeps_the_last_good_checkpoint(
    at: int, kept: int, tmp_path: Path
) -> None:
    """One minibatch an update: the update ends, and the guard finds its NaN loss when
    the next rollout starts (at 256, the last: when training ends)."""
    out, err = _diverge(tmp_path, at, batch_size=64, n_epochs=1)
    checkpoint = out / "checkpoints" / f"model_{kept}_steps.zip"
    assert str(err) == (
        f"training diverged: non-finite train/value_loss (nan) at timestep {at}; kept the "
        f"last good checkpoint {checkpoint} (timestep {kept}) as {out / 'model.zip'}"
    )
    assert err.kept == checkpoint and err.timestep == at
    assert (out / "model.zip").read_bytes() == checkpoint.read_bytes()
    stats = out / "checkpoints" / f"model_vecnormalize_{kept}_steps.pkl"
    assert (out / "vecnormalize.pkl").read_bytes() == stats.read_bytes()
    assert nonfinite(PPO.load(out / "model.zip", device="cpu")) is None
    assert sorted(p.name for p in (out / "checkpoints").glob("*.zip")) == sorted(
        f"model_{n}_steps.zip" for n in range(64, at, 64)
    )  # none of a NaN model
    _assert_finite_and_whole(out)
    record = yaml.safe_load((out / "config.yaml").read_text())
    assert record["diverged"] == str(err) and record["completed_timesteps"] == at


def test_torch_refusing_a_nan_mid_update_is_a_divergence_too(tmp_path: Path) -> None:
    """Two minibatches an update: the first makes the weights NaN, and the policy's
    Normal refuses its NaN mean in the second (SB3's ValueError and tensor dump)."""
    out, err = _diverge(tmp_path, 192)
    assert re.fullmatch(
        r"training diverged: non-finite policy\.\S+ at timestep 192; kept the last good "
        r"checkpoint \S+model_128_steps\.zip \(timestep 128\) as \S+model\.zip",
        str(err),
    ), err
    assert isinstance(err.__cause__, ValueError)  # torch's, for --verbose
    assert err.kept is not None and (out / "model.zip").read_bytes() == err.kept.read_bytes()
    _assert_finite_and_whole(out)


def test_a_divergence_before_any_good_checkpoint_leaves_no_model(tmp_path: Path) -> None:
    out, err = _diverge(tmp_path, 64)
    assert str(err).endswith(
        "at timestep 64; no good checkpoint yet (one is kept every 64 steps), "
        "so no model.zip was written"
    )
    assert err.kept is None
    assert not (out / "model.zip").exists() and not (out / "vecnormalize.pkl").exists()
    assert not list(out.glob("checkpoints/*"))
    assert yaml.safe_load((out / "config.yaml").read_text())["diverged"] == str(err)


def test_a_huge_learning_rate_diverges_with_the_named_error(tmp_path: Path) -> None:
    """No poison: the first update with a learning rate of 1e30 blows the policy's
    outputs up, and torch refuses them."""
    out = tmp_path / "run"
    with pytest.raises(TrainingDivergedError, match="at timestep 64; no good checkpoint yet"):
        train(
            THREE_BAR,
            "ppo",
            "oracle",
            out,
            timesteps=128,
            config_file=_tiny_config(tmp_path),
            hyperparams={"learning_rate": 1e30},
            progress_bar=False,
            checkpoint_every=64,
        )
    assert not (out / "model.zip").exists()


def test_the_command_line_says_a_divergence_in_one_line_and_exits_2(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from agents.cli import main

    out = tmp_path / "t"
    argv = ["train", "--out", str(out), "--config", str(_tiny_config(tmp_path))]
    argv += ["--timesteps", "64", "--no-progress", "--hyperparams", "learning_rate:1e30"]
    with caplog.at_level(logging.ERROR):
        assert main(argv) == 2
    [error] = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert error.getMessage().startswith("training diverged: non-finite ")
    assert "\n" not in error.getMessage() and error.exc_info is None


def test_a_file_is_replaced_whole_or_not_at_all(tmp_path: Path) -> None:
    path = tmp_path / "model.zip"
    path.write_bytes(b"the good one")

    def fails_halfway(partial: Path) -> None:
        partial.write_bytes(b"half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        replace_atomically(path, fails_halfway)
    assert path.read_bytes() == b"the good one"
    assert [p.name for p in tmp_path.iterdir()] == ["model.zip"]
    replace_atomically(path, lambda p: p.write_bytes(b"new"))
    assert path.read_bytes() == b"new" and [p.name for p in tmp_path.iterdir()] == ["model.zip"]
