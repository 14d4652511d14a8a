"""Training that never writes a model with a non-finite number in it.

In stable-baselines3 a run whose loss or weights turn NaN or infinite (a learning rate
too large, a discount above 1) goes on until torch's distributions refuse the NaN (a
ValueError and a dump of tensors), and the model saved then is NaN throughout.
:class:`FiniteGuard` checks the losses, the weights, the optimisers' state and the
normalisation statistics after each update (at each rollout's start, and at the end),
stops the run with :class:`TrainingDivergedError` at the first non-finite number, and saves
the periodic checkpoints itself, of checked models only; :meth:`FiniteGuard.finish`
then writes the run's ``model.zip``: the model where it is finite, else the last good
checkpoint, else none. Every file is written under a temporary name and renamed, so
none is ever left half-written.
"""

from __future__ import annotations

import math
import os
import pickle
import shutil
from typing import TYPE_CHECKING, Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

if TYPE_CHECKING:
    from collections.abc import Callable, Iterator
    from pathlib import Path

    from stable_baselines3.common.base_class import BaseAlgorithm

__all__ = ["FiniteGuard", "TrainingDivergedError", "nonfinite", "replace_atomically", "save_model"]


class TrainingDivergedError(ValueError):
    """Training reached a non-finite loss, weight or statistic: ``what``, at
    ``timestep``; ``kept``: the checkpoint that ``model.zip`` now holds, or None (there
    is no model.zip). A ValueError, as a value out of range is: what to change is the
    user's (a smaller learning rate, a discount within [0, 1]), and the command line
    says it in one line."""

    def __init__(self, message: str, what: str, timestep: int, kept: Path | None) -> None:
        super().__init__(message)
        self.what, self.timestep, self.kept = what, timestep, kept


def replace_atomically(path: Path, write: Callable[[Path], object]) -> None:
    """``write`` a temporary file beside ``path``, then rename it ``path``: a reader, or
    a run killed in between, finds the old file or the new one whole. The temporary
    name ends as ``path`` does (SB3's save appends ``.zip`` to a name without it)."""
    partial = path.with_name(f".{path.stem}.{os.getpid()}.partial{path.suffix}")
    try:
        write(partial)
        with partial.open("rb") as f:
            os.fsync(f.fileno())  # on disk before the rename makes it the file
        os.replace(partial, path)
    finally:
        partial.unlink(missing_ok=True)


def save_model(model: BaseAlgorithm, path: Path, stats_path: Path) -> None:
    """``model`` at ``path`` and, where it normalises, its statistics at ``stats_path``
    (pickled whole, as ``VecNormalize.save`` pickles them)."""
    replace_atomically(path, model.save)
    norm = model.get_vec_normalize_env()
    if norm is not None:
        replace_atomically(stats_path, lambda p: p.write_bytes(pickle.dumps(norm)))


def nonfinite(model: BaseAlgorithm) -> str | None:
    """The name of the first tensor of ``model``'s save (weights, optimisers' state,
    SAC's entropy coefficient) or normalisation statistic holding a NaN or an infinity,
    as ``policy.mlp_extractor.value_net.0.weight``; None where all are finite."""
    import torch
    from stable_baselines3.common.save_util import recursive_getattr

    saved: dict[str, Any] = dict(model.get_parameters())
    saved |= {name: recursive_getattr(model, name) for name in model._get_torch_save_params()[1]}
    for key, value in _leaves(saved, ""):
        if isinstance(value, torch.Tensor) and value.is_floating_point():
            # A NaN or an infinity makes the sum non-finite: 5 times faster than isfinite
            # over each tensor (SAC's nets are checked every few steps); the exact look
            # only where the sum is not finite, as it is too where finite terms overflow.
            value = value.detach()  # SAC's entropy coefficient is a leaf that learns
            if not math.isfinite(float(value.sum())) and not bool(torch.isfinite(value).all()):
                return key
    norm = model.get_vec_normalize_env()
    if norm is not None:
        stats = {"obs_rms": norm.obs_rms, "ret_rms": norm.ret_rms}
        for key, value in _leaves(stats, ""):
            if hasattr(value, "mean") and hasattr(value, "var"):  # a RunningMeanStd
                if not (np.isfinite(value.mean).all() and np.isfinite(value.var).all()):
                    return f"VecNormalize {key}"
    return None


def _leaves(tree: Any, prefix: str) -> Iterator[tuple[str, Any]]:
    """The leaves of nested dicts, lists and tuples, each named by its dotted path."""
    if isinstance(tree, dict):
        for key, value in tree.items():
            yield from _leaves(value, f"{prefix}.{key}" if prefix else str(key))
    elif isinstance(tree, (list, tuple)):
        for i, value in enumerate(tree):
            yield from _leaves(value, f"{prefix}.{i}")
    else:
        yield prefix, tree


def _raised_in(module: str, err: BaseException) -> bool:
    """Whether ``err`` was raised in ``module`` or one below it."""
    tb = err.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    name = tb.tb_frame.f_globals.get("__name__", "") if tb is not None else ""
    return bool(name == module or name.startswith(f"{module}."))


class FiniteGuard(BaseCallback):
    """Checks ``model`` after each update and saves a checkpoint of it every ``every``
    steps where all is finite (``out/checkpoints/model_<N>_steps.zip``, with
    ``model_vecnormalize_<N>_steps.pkl``: the names of SB3's CheckpointCallback, which
    saved on a step count whatever the weights held). An update comes between one
    rollout and the next: a rollout's start sees it before the policy acts on it."""

    def __init__(
        self, out: Path, every: int, kept: tuple[int, Path, Path | None] | None = None
    ) -> None:
        """``kept``: the checkpoint a resumed run goes on from (the next is saved past
        the next multiple of ``every``; a divergence before it falls back to this one)."""
        super().__init__()
        self.out, self.every = out, max(every, 1)
        self.kept = kept
        """The last good checkpoint: its step, model and statistics."""
        self._saved_at = 0 if kept is None else kept[0]

    def _on_step(self) -> bool:
        return True

    def _on_rollout_start(self) -> None:
        self._check()

    def _on_training_end(self) -> None:
        self._check()

    def _check(self) -> None:
        what = self._loss() or nonfinite(self.model)
        if what is not None:
            raise self.diverged(what, self.num_timesteps)
        if self.num_timesteps // self.every > self._saved_at // self.every:
            self._save_checkpoint(self.num_timesteps)

    def _loss(self) -> str | None:
        """The first non-finite loss of the last update that SB3 logged (``train/*_loss``;
        other figures, such as the explained variance, may be NaN in a good run)."""
        logged = self.model.logger.name_to_value
        for key, value in logged.items():
            if key.startswith("train/") and key.endswith("loss"):
                if not math.isfinite(float(value)):
                    return f"{key} ({value})"
        return None

    def _save_checkpoint(self, steps: int) -> None:
        folder = self.out / "checkpoints"
        folder.mkdir(parents=True, exist_ok=True)
        model_file = folder / f"model_{steps}_steps.zip"
        stats_file = folder / f"model_vecnormalize_{steps}_steps.pkl"
        save_model(self.model, model_file, stats_file)
        has_stats = self.model.get_vec_normalize_env() is not None
        self.kept = (steps, model_file, stats_file if has_stats else None)
        self._saved_at = steps

    def diverged(self, what: str, timestep: int) -> TrainingDivergedError:
        """The error for ``what`` turning non-finite at ``timestep``, which says what
        :meth:`finish` keeps."""
        if self.kept is None:
            kept = (
                f"no good checkpoint yet (one is kept every {self.every} steps), "
                "so no model.zip was written"
            )
            checkpoint = None
        else:
            steps, checkpoint, _ = self.kept
            kept = (
                f"kept the last good checkpoint {checkpoint} (timestep {steps}) "
                f"as {self.out / 'model.zip'}"
            )
        message = f"training diverged: non-finite {what} at timestep {timestep}; {kept}"
        return TrainingDivergedError(message, what, timestep, checkpoint)

    def divergence(self, model: BaseAlgorithm, err: ValueError) -> TrainingDivergedError | None:
        """``err``, raised by training, as a divergence; None where it is none. torch's
        distributions refuse a NaN mean with a ValueError (in an update, when its first
        minibatch made the weights NaN): the weights then say what went wrong."""
        if isinstance(err, TrainingDivergedError):
            return err
        what = nonfinite(model)
        if what is None and _raised_in("torch.distributions", err):
            what = "policy outputs (torch.distributions refused them)"
        if what is None:
            return None
        diverged = self.diverged(what, model.num_timesteps)
        diverged.__cause__ = err
        return diverged

    def finish(
        self, model: BaseAlgorithm, failure: TrainingDivergedError | None
    ) -> TrainingDivergedError | None:
        """Write ``out/model.zip`` (and ``vecnormalize.pkl``): ``model`` where it is
        finite and training did not diverge, else the last good checkpoint, else none (a
        stale one of an earlier run in ``out`` goes: this run's config.yaml is not its).
        Returns the divergence, ``failure`` or one found in ``model`` now."""
        model_file, stats_file = self.out / "model.zip", self.out / "vecnormalize.pkl"
        if failure is None:
            what = nonfinite(model)
            if what is None:
                save_model(model, model_file, stats_file)
                return None
            failure = self.diverged(what, model.num_timesteps)
        if self.kept is None:
            model_file.unlink(missing_ok=True)
            stats_file.unlink(missing_ok=True)
            return failure
        _, checkpoint, stats = self.kept
        replace_atomically(model_file, lambda p: shutil.copyfile(checkpoint, p))
        if stats is not None:
            replace_atomically(stats_file, lambda p: shutil.copyfile(stats, p))
        else:
            stats_file.unlink(missing_ok=True)
        return failure
