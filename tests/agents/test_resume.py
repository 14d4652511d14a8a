"""Training runs that go on after a stop (``train --resume``) and named settings
(``train --preset``)."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np
import pytest
import yaml

from agents.cli import build_parser, main
from agents.cli.training import _with_preset
from agents.training.presets import PRESETS
from agents.training.resume import last_checkpoint, read_record, resume
from agents.training.train import train
from tests.agents.test_train import THREE_BAR, _tiny_config

if TYPE_CHECKING:
    from pathlib import Path


def _run(out: Path, tmp: Path, timesteps: int) -> None:
    train(THREE_BAR, "ppo", "oracle", out, timesteps=timesteps, seed=4,
          config_file=_tiny_config(tmp), progress_bar=False, checkpoint_every=128,
          env_kwargs={"max_episode_steps": 40})  # fmt: skip


def _weights(path: Path) -> dict[str, np.ndarray]:
    from stable_baselines3 import PPO

    return {k: v.numpy() for k, v in PPO.load(path).policy.state_dict().items()}


def test_a_run_goes_on_from_its_newest_checkpoint(tmp_path: Path) -> None:
    """256 steps, then on to 448 from the checkpoint at 256: the steps, the Monitor logs
    of both parts and the record; two resumptions from one checkpoint agree."""
    out = tmp_path / "run"
    _run(out, tmp_path, 256)
    before = read_record(out)
    assert before["finished"] and before["completed_timesteps"] == 256
    assert last_checkpoint(out, before).steps == 256
    copy = tmp_path / "copy"
    import shutil

    shutil.copytree(out, copy)
    for folder in (out, copy):
        resume(folder, timesteps=448, checkpoint_every=128, progress_bar=False)
    record = read_record(out)
    assert record["completed_timesteps"] == 448 and record["finished"]
    assert record["resumed_from"].endswith("model_256_steps.zip")
    assert record["timesteps"] == 448 and record["env_id"] == THREE_BAR
    assert last_checkpoint(out, record).steps == 384  # the last multiple of 128 passed
    logs = sorted(p.name for p in (out / "monitor").glob("*.monitor.csv"))
    assert logs == ["0.before_256.monitor.csv", "0.monitor.csv"]
    first, again = _weights(out / "model.zip"), _weights(copy / "model.zip")
    assert all(np.array_equal(first[k], again[k]) for k in first)
    changed = _weights(out / "checkpoints" / "model_256_steps.zip")
    assert any(not np.array_equal(first[k], changed[k]) for k in first)  # it learned on


def test_resume_mistakes_are_one_line(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    out = tmp_path / "run"
    _run(out, tmp_path, 128)
    args = ["train", "--resume", "--no-progress", "--out"]
    with caplog.at_level(logging.ERROR):
        assert main([*args, str(tmp_path / "nothing")]) == 2
        assert main([*args, str(out)]) == 2  # its 128 steps done
        assert main([*args, str(out), "--config", "x.yml", "--timesteps", "256"]) == 2
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 3 and all("\n" not in e for e in errors)
    assert "no training run here (no config.yaml)" in errors[0]
    assert "has 128 steps already, its total is 128" in errors[1]
    assert "leave out ['--config']" in errors[2]
    (tmp_path / "bare").mkdir()
    (tmp_path / "bare" / "config.yaml").write_text(yaml.safe_dump(read_record(out)))
    with pytest.raises(ValueError, match="no checkpoint to resume from"):
        resume(tmp_path / "bare", timesteps=512)


def test_the_long_preset_fills_what_the_command_line_leaves_out() -> None:
    parser = build_parser()
    args = _with_preset(parser.parse_args(["train", "--preset", "long", "--out", "x"]))
    long = PRESETS["long"]
    assert args.config == str(long.config) and args.timesteps == 1_000_000
    assert args.residual_gait == 0.5 and dict(args.env_kwargs) == {"base_gait": "steer"}
    mine = parser.parse_args(["train", "--preset", "long", "--out", "x", "--timesteps", "100",
                              "--env-kwargs", "base_gait:'forward'"])  # fmt: skip
    args = _with_preset(mine)
    assert args.timesteps == 100 and dict(args.env_kwargs) == {"base_gait": "forward"}
    assert long.config.is_file()


def test_the_tempo_preset_gives_the_tempo_choice_and_its_settings() -> None:
    """``--preset tempo``: the steering gait's choice with the tempos and ranks of the
    runs in docs/results/training.md, and their hyperparameters (the config's)."""
    from pathlib import Path

    from agents.training.train import load_hyperparams

    parser = build_parser()
    args = _with_preset(parser.parse_args(["train", "--preset", "tempo", "--out", "x"]))
    assert (args.moves, args.move_tempos, args.move_ranks) == ("steer", [[15, 0], [15, 5]], 1)
    assert args.timesteps == 2048 and args.residual_gait is None
    params = load_hyperparams("ppo", "tensegrity_gym/ThreeBarRoll-v0", Path(args.config), {})
    assert (params["n_steps"], params["gamma"], params["ent_coef"]) == (64, 0.9, 0.01)
    mine = parser.parse_args(["train", "--preset", "tempo", "--out", "x", "--move-ranks", "2"])
    assert _with_preset(mine).move_ranks == 2  # the command line wins
