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


PRESETS: dict[str, Preset] = {
    "long": Preset(
        "the long run: PPO correcting the steering gait (residual actions at 0.5, "
        "agents/training/configs/steer.yml) for a million steps",
        CONFIG_DIR / "steer.yml",
        1_000_000,
        0.5,
        {"base_gait": "steer"},
    ),
}
"""Every preset ``train --preset`` takes, by name."""


def preset(name: str) -> Preset:
    """The preset ``name``; ValueError naming the valid ones."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; valid choices: {sorted(PRESETS)}")
    return PRESETS[name]
