"""Named training settings: ``tensegrity-gym train --preset NAME``.

A preset fills in the options a command line leaves out (the hyperparameter config, the
step count, the residual scale and the env's arguments); any it gives wins. The runs
are checkpointed every 50,000 steps and go on after a stop with ``train --resume``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from agents.training.train import CONFIG_DIR

if TYPE_CHECKING:
    from pathlib import Path

__all__ = ["PRESETS", "Preset", "preset"]


@dataclass(frozen=True)
class Preset:
    """Training options under one name."""

    about: str
    config: Path
    """The hyperparameter config (rl-zoo3 layout)."""
    timesteps: int
    residual_gait: float | None = None
    """The scale of residual actions on the robot's gait; None: absolute actions."""
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    moves: str | None = None
    """A steering gait whose choices the policy makes (``train --moves``); None: the
    env's own actions."""
    move_tempos: tuple[tuple[int, int], ...] | None = None
    """With ``moves``: the tempos beside the gait's own (``--move-tempos``)."""
    move_ranks: int | None = None
    """With ``moves``: the gait's ranks a choice picks among (``--move-ranks``)."""


PRESETS: dict[str, Preset] = {
    "long": Preset(
        "the long run: PPO correcting the steering gait (residual actions at 0.5, "
        "agents/training/configs/steer.yml) for a million steps",
        CONFIG_DIR / "steer.yml",
        1_000_000,
        0.5,
        {"base_gait": "steer"},
    ),
    "tempo": Preset(
        "PPO choosing the steering gait's tempo (15/0, 15/5 or its own) each period, "
        "the move left to the gait, for 2,048 choices "
        "(agents/training/configs/tempo.yml; ahead of the steering gait on the 3-bar "
        "under the UKF, docs/results/training.md)",
        CONFIG_DIR / "tempo.yml",
        2048,
        moves="steer",
        move_tempos=((15, 0), (15, 5)),
        move_ranks=1,
    ),
}
"""Every preset ``train --preset`` takes, by name."""


def preset(name: str) -> Preset:
    """The preset ``name``; ValueError naming the valid ones."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; valid choices: {sorted(PRESETS)}")
    return PRESETS[name]
