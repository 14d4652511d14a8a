"""Going on with a training run that stopped: killed, interrupted, or given more steps.

A run writes its ``config.yaml`` when it starts and again when it ends, and a checkpoint
of the model (with its normalisation statistics) every ``checkpoint_every`` steps
(:class:`agents.training.guards.FiniteGuard`). :func:`resume` goes on from the newest
of them (or from the model an interrupted run saved at its end, where that came later)
with the run's own settings, to its total of steps or a new one. The Monitor logs of
the steps before are kept beside the new ones (``<name>.before_<N>.monitor.csv``), so
the training curve spans the whole run. What is not kept: SAC's replay buffer (it
refills from the step resumed at) and the random state of the envs (each is reset
anew), so a resumed run is the same every time it is resumed from one checkpoint, not
the same as a run never stopped.
"""

from __future__ import annotations

import re
from dataclasses import MISSING, fields, replace
from typing import TYPE_CHECKING, Any

import yaml

from agents.training.train import Checkpoint, RunOptions, TrainConfig, run_training

if TYPE_CHECKING:
    from collections.abc import Sequence
    from pathlib import Path

    from stable_baselines3.common.callbacks import BaseCallback

__all__ = ["last_checkpoint", "read_record", "resume"]

_REQUIRED = [f.name for f in fields(TrainConfig) if f.default is MISSING
             and f.default_factory is MISSING]  # fmt: skip
"""The fields every run's ``config.yaml`` has."""

_CHECKPOINT = re.compile(r"model_(\d+)_steps\.zip")


def read_record(out: Path) -> dict[str, Any]:
    """The run's ``config.yaml``; ValueError in one line where there is none or it is
    not a run's."""
    path = out / "config.yaml"
    try:
        record = yaml.safe_load(path.read_text())
    except OSError:
        raise ValueError(f"{out}: no training run here (no config.yaml)") from None
    except yaml.YAMLError as err:
        raise ValueError(f"{path}: not YAML ({' '.join(str(err).split())})") from None
    missing = [f for f in _REQUIRED if f not in (record or {})]
    if not isinstance(record, dict) or missing:
        raise ValueError(f"{path}: not a training run's config (missing {missing})")
    return record


def last_checkpoint(out: Path, record: dict[str, Any]) -> Checkpoint:
    """The newest model the run in ``out`` saved: a checkpoint, or the interrupted run's
    ``model.zip`` where that came later; ValueError where there is none."""
    found = []
    folder = out / "checkpoints"
    for path in folder.glob("model_*_steps.zip"):
        match = _CHECKPOINT.fullmatch(path.name)
        if match:
            steps = int(match[1])
            stats = folder / f"model_vecnormalize_{steps}_steps.pkl"
            found.append(Checkpoint(steps, path, stats if stats.is_file() else None))
    completed = int(record.get("completed_timesteps", 0))
    model, stats = out / "model.zip", out / "vecnormalize.pkl"
    if record.get("interrupted") and not record.get("diverged") and model.is_file():
        found.append(Checkpoint(completed, model, stats if stats.is_file() else None))
    if not found:
        raise ValueError(
            f"{out}: no checkpoint to resume from (checkpoints/model_<N>_steps.zip); a run "
            "saves one every --checkpoint-every steps"
        )
    return max(found, key=lambda c: c.steps)


def _keep_monitor_logs(out: Path, steps: int) -> None:
    """Rename the run's Monitor logs so that the resumed run's do not overwrite them."""
    for path in (out / "monitor").glob("*.monitor.csv"):
        if ".before_" not in path.name:
            stem = path.name.removesuffix(".monitor.csv")
            path.rename(path.with_name(f"{stem}.before_{steps}.monitor.csv"))


def resume(
    out: Path,
    *,
    timesteps: int | None = None,
    checkpoint_every: int = 50_000,
    progress_bar: bool = True,
    callbacks: Sequence[BaseCallback] = (),
    ray_address: str | None = None,
    workers: int | None = None,
) -> Path:
    """Go on with the run in ``out`` from its newest checkpoint, to ``timesteps`` steps in
    all (default: the run's own total); the path of the saved model."""
    record = read_record(out)
    # A run of an earlier version lacks the fields added since, which have defaults.
    config = TrainConfig(**{k: record[k] for k in TrainConfig.__dataclass_fields__ if k in record})
    if timesteps is not None:
        config = replace(config, timesteps=int(timesteps))
    start = last_checkpoint(out, record)
    if start.steps >= config.timesteps:
        raise ValueError(
            f"{out}: the run has {start.steps} steps already, its total is "
            f"{config.timesteps}; give more timesteps to go on"
        )
    _keep_monitor_logs(out, start.steps)
    options = RunOptions(checkpoint_every, progress_bar, callbacks, start)
    return run_training(config, out, options, ray_address, workers)
