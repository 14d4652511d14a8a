"""The valid values of each hyperparameter a training config or ``--hyperparams`` gives,
checked before any env is made.

stable-baselines3 checks few of them, and those with ``assert`` (a traceback); most it
takes as they come, and a value out of range shows only once training has run: PPO with
``gamma`` 2.0 grows its returns as 1.9 ** n_steps, and its first update writes NaN into
every weight. :data:`VALID` names each key's valid values, one :class:`Valid` per key;
:func:`check_rollout` checks the few that bound each other (PPO's minibatches against its
rollout).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from collections.abc import Mapping

__all__ = ["VALID", "Valid", "check_hyperparams", "check_rollout"]


@dataclass(frozen=True)
class Valid:
    """The values one hyperparameter takes: numbers of ``number``'s kind (an int kind
    takes a whole float too, as YAML's ``!!float 1e5`` writes one) between ``low`` and
    ``high`` (bounds excluded where ``open_low`` / ``open_high``); besides, any of
    ``also`` exactly, values of ``types`` whole, text ``<prefix><x>`` with x > 0, and a
    pair ``[n, unit]`` with n such a number and ``unit`` among ``units``."""

    number: type[int] | type[float] | None = None
    low: float = -math.inf
    high: float = math.inf
    open_low: bool = False
    open_high: bool = False
    also: tuple[Any, ...] = ()
    types: tuple[type, ...] = ()
    prefix: str | None = None
    units: tuple[str, ...] = ()

    def describe(self) -> str:
        """The valid values in words: ``a number in [0, 1]``, ``a number > 0 or None``."""
        parts = [self._describe_number()] if self.number is not None else []
        parts += [word for t in self.types for word in _TYPE_WORDS.get(t, (t.__name__,))]
        parts += [repr(value) for value in self.also]
        if self.prefix is not None:
            parts.append(f"'{self.prefix}<x>' with x > 0")
        if self.units:
            parts.append(f"[n, {' or '.join(map(repr, self.units))}] with n as above")
        return ", ".join(parts[:-1]) + " or " + parts[-1] if len(parts) > 1 else parts[0]

    def _describe_number(self) -> str:
        noun = "a whole number" if self.number is int else "a number"
        low, high = f"{self.low:g}", f"{self.high:g}"
        if math.isfinite(self.low) and math.isfinite(self.high):
            left, right = "(" if self.open_low else "[", ")" if self.open_high else "]"
            return f"{noun} in {left}{low}, {high}{right}"
        if math.isfinite(self.low):
            return f"{noun} {'>' if self.open_low else '>='} {low}"
        if math.isfinite(self.high):
            return f"{noun} {'<' if self.open_high else '<='} {high}"
        return f"a finite {noun.removeprefix('a ')}"

    def accept(self, value: Any) -> Any:
        """``value`` as the algorithm takes it (a whole float as an int, a pair as a
        list), or :data:`_REFUSED`."""
        if any(value == a and type(value) is type(a) for a in self.also):
            return value
        number = self._number(value)
        if number is not _REFUSED:
            return number
        if self.types and isinstance(value, self.types):
            return value
        if self.prefix is not None and isinstance(value, str) and value.startswith(self.prefix):
            return value if _positive(value.removeprefix(self.prefix)) else _REFUSED
        if self.units and isinstance(value, (list, tuple)) and len(value) == 2:
            count = self._number(value[0])
            if count is not _REFUSED and value[1] in self.units:
                return [count, value[1]]  # a list: config.yaml is YAML
        return _REFUSED

    def _number(self, value: Any) -> Any:
        # bool is an int to Python, never a number to a user: gamma:True is a mistake
        if self.number is None or isinstance(value, bool):
            return _REFUSED
        if not isinstance(value, (int, float)) or not math.isfinite(value):
            return _REFUSED
        if self.number is int:
            if isinstance(value, float) and not value.is_integer():
                return _REFUSED
            value = int(value)
        above = value > self.low if self.open_low else value >= self.low
        below = value < self.high if self.open_high else value <= self.high
        return value if above and below else _REFUSED


_REFUSED = object()
"""What :meth:`Valid.accept` returns for a value it does not take (None is a value)."""

_TYPE_WORDS = {bool: ("True", "False"), dict: ("a dict(...)",)}


def _positive(text: str) -> bool:
    try:
        return 0 < float(text) < math.inf
    except ValueError:
        return False


_WHOLE = Valid(int, low=1)
_FLAG = Valid(types=(bool,))
_FRACTION = Valid(float, low=0, high=1)
_POSITIVE = Valid(float, low=0, open_low=True)

# Keys that both algorithms (and the trainer, for the run keys) take.
_COMMON: dict[str, Valid] = {
    "n_envs": _WHOLE,
    "n_timesteps": _WHOLE,
    "policy": Valid(also=("MlpPolicy", "CnnPolicy", "MultiInputPolicy")),
    "normalize": Valid(types=(bool, dict)),
    "policy_kwargs": Valid(types=(dict,), also=(None,)),
    "learning_rate": _POSITIVE,
    "gamma": _FRACTION,
    "batch_size": _WHOLE,
    "n_steps": _WHOLE,  # PPO's rollout per env; SAC's n-step returns
    "use_sde": _FLAG,
    # -1: gSDE's noise is drawn once a rollout; 0 is the same, n > 0 every n steps
    "sde_sample_freq": Valid(int, low=-1),
    "stats_window_size": _WHOLE,
}

VALID: dict[str, dict[str, Valid]] = {
    "ppo": _COMMON
    | {
        "n_epochs": _WHOLE,
        "gae_lambda": _FRACTION,
        "clip_range": _POSITIVE,
        "clip_range_vf": Valid(float, low=0, open_low=True, also=(None,)),
        "normalize_advantage": _FLAG,
        "ent_coef": Valid(float, low=0),
        "vf_coef": Valid(float, low=0),
        # 0 would zero every gradient, a negative norm turn them around
        "max_grad_norm": _POSITIVE,
        "target_kl": Valid(float, low=0, open_low=True, also=(None,)),
    },
    "sac": _COMMON
    | {
        "buffer_size": _WHOLE,
        "learning_starts": Valid(int, low=0),
        "tau": Valid(float, low=0, high=1, open_low=True),
        "train_freq": Valid(int, low=1, units=("step", "episode")),
        "gradient_steps": Valid(int, low=1, also=(-1,)),  # -1: as many as steps taken
        "optimize_memory_usage": _FLAG,
        "ent_coef": Valid(float, low=0, also=("auto",), prefix="auto_"),
        "target_update_interval": _WHOLE,
        "target_entropy": Valid(float, also=("auto",)),
        "use_sde_at_warmup": _FLAG,
    },
}
"""Each algorithm's keys and their valid values; a key not named here (a class, say
``replay_buffer_class``) is left to stable-baselines3."""


def check_hyperparams(
    algo: str, params: Mapping[str, Any], where: Mapping[str, str]
) -> dict[str, Any]:
    """``params`` as the algorithm takes them (see :meth:`Valid.accept`); ValueError,
    one line, for the first value that is not valid: ``{where[key]} {key}: {value!r}
    is not {the valid values}``."""
    rules = VALID[algo]
    checked = dict(params)
    for key, value in params.items():
        if key not in rules:
            continue
        checked[key] = rules[key].accept(value)
        if checked[key] is _REFUSED:
            raise ValueError(f"{where[key]} {key}: {value!r} is not {rules[key].describe()}")
    return checked


def check_rollout(n_steps: int, n_envs: int, batch_size: int, normalize_advantage: bool) -> None:
    """ValueError unless PPO's minibatches fit its rollout of ``n_steps * n_envs`` steps
    (SB3 asserts some of this; a batch larger than the rollout is the whole rollout).
    Normalising the advantages takes 2 of them at least: the std of one is 0."""
    rollout = n_steps * n_envs
    least = 2 if normalize_advantage else 1
    if rollout < least:
        raise ValueError(
            f"n_steps * n_envs = {n_steps} * {n_envs} = {rollout}: a PPO rollout that "
            "normalises its advantages (normalize_advantage) must hold 2 steps at least"
        )
    if not least <= batch_size <= rollout:
        raise ValueError(
            f"batch_size: {batch_size} is not a whole number in [{least}, {rollout}] "
            f"(a minibatch of a rollout of n_steps * n_envs = {n_steps} * {n_envs} steps"
            + (", of 2 steps at least to normalise the advantages)" if least == 2 else ")")
        )
