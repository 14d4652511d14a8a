"""What the subcommands' parsers share: the argparse value types, the help formatter, the
shared options (``--ray``, ``--env``'s help) and a command's entry in the registry."""

from __future__ import annotations

import argparse
import ast
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from collections.abc import Callable

__all__ = [
    "Command",
    "HelpFormatter",
    "SubcommandParser",
    "add_ray",
    "calibration_seconds",
    "count",
    "env_help",
    "env_kwarg",
    "finite_float",
    "given",
    "hyperparam",
    "non_negative_float",
    "pairs",
    "port",
    "positive_float",
    "positive_int",
    "tempo",
]


@dataclass(frozen=True)
class Command:
    """A subcommand: its name and one-line help (``tensegrity-gym --help``), what adds its
    options to its parser, and what runs it (its exit status back)."""

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


def count(text: str) -> int:
    """An argparse type: a whole number >= 0."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must not be negative, got {value}")
    return value


def positive_int(text: str) -> int:
    """An argparse type: a whole number >= 1."""
    value = count(text)
    if value == 0:
        raise argparse.ArgumentTypeError("must be at least 1, got 0")
    return value


def port(text: str) -> int:
    """An argparse type: a TCP port, 0 (a free one) to 65535."""
    value = count(text)
    if value > 65535:
        raise argparse.ArgumentTypeError(f"must be a TCP port in [0, 65535], got {value}")
    return value


def finite_float(text: str) -> float:
    """``text`` as a finite float, or ArgumentTypeError."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
    return value


def positive_float(text: str) -> float:
    """An argparse type: a finite number > 0."""
    value = finite_float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def tempo(text: str) -> list[int]:
    """An argparse type: a gait period's ``HOLD/SETTLE`` control steps, whole numbers,
    the hold > 0 and the settle >= 0."""
    parts = text.split("/")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts) or int(parts[0]) < 1:
        raise argparse.ArgumentTypeError(
            f"must be HOLD/SETTLE control steps (whole numbers, HOLD > 0), got {text!r}"
        )
    return [int(parts[0]), int(parts[1])]


def non_negative_float(text: str) -> float:
    """An argparse type: a finite number >= 0."""
    value = finite_float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text}")
    return value


def calibration_seconds(text: str) -> float:
    """An argparse type: a calibration run's length (s), in the range
    :func:`tensegrity_gym.envs.calibration_run.check_seconds` takes (its message, after the
    flag)."""
    from tensegrity_gym.envs.calibration_run import check_seconds

    try:
        seconds = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number of seconds, got {text!r}") from None
    try:
        return check_seconds(seconds)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err).partition(": ")[2]) from None


def _key_value(text: str) -> tuple[str, str]:
    """``KEY:VALUE`` split at its first colon; ArgumentTypeError for another form."""
    key, sep, value = text.partition(":")
    if not sep or not key.isidentifier():
        raise argparse.ArgumentTypeError(f"expected KEY:VALUE, got {text!r}")
    return key, value


def env_kwarg(text: str) -> tuple[str, Any]:
    """An argparse type: ``KEY:VALUE``, a ``gym.make`` argument as rl-zoo3's
    ``--env-kwargs`` writes it (the value a Python literal: ``ctrl_cost:0.0``,
    ``goal_heading:None``, ``terrain:"'valley'"``)."""
    key, value = _key_value(text)
    try:
        return key, ast.literal_eval(value)
    except (ValueError, SyntaxError):
        raise argparse.ArgumentTypeError(
            f"{key}: {value!r} is not a Python literal (quote a string: {key}:\"'{value}'\")"
        ) from None


_TEXT_HYPERPARAMS = ("policy", "normalize", "policy_kwargs")
"""The hyperparameters whose value may be text as it stands (rl-zoo3 writes them so)."""


def hyperparam(text: str) -> tuple[str, Any]:
    """An argparse type: ``KEY:VALUE``, a hyperparameter as rl-zoo3's ``--hyperparams``
    writes it (``learning_rate:1e-4``, ``policy_kwargs:"dict(log_std_init=-2.0)"``): a
    Python literal, or for :data:`_TEXT_HYPERPARAMS` the text as it stands (a
    ``dict(...)`` the config reader parses)."""
    key, value = _key_value(text)
    try:
        return key, ast.literal_eval(value)
    except (ValueError, SyntaxError):
        if key in _TEXT_HYPERPARAMS:
            return key, value
        raise argparse.ArgumentTypeError(
            f"--hyperparams {key}: {value!r} is not a Python literal"
        ) from None


def pairs(given_pairs: list[tuple[str, Any]] | None, option: str) -> dict[str, Any]:
    """``KEY:VALUE`` options as a dict; ValueError for a key given twice."""
    out: dict[str, Any] = {}
    for key, value in given_pairs or ():
        if key in out:
            raise ValueError(f"{option} {key} is given twice")
        out[key] = value
    return out


def given(args: argparse.Namespace, *names: str) -> dict[str, Any]:
    """The options among ``names`` that the command line gave (not None), by name."""
    return {n: getattr(args, n) for n in names if getattr(args, n) is not None}


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Each option's default after its help, where it has one (not None, not a flag's
    False: those help texts say what their absence means)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        """``action``'s help, with ``(default: ...)`` where it has a default to show."""
        if action.default is None or action.default is False:
            return action.help
        return super()._get_help_string(action)


class SubcommandParser(argparse.ArgumentParser):
    """A subcommand's parser, whose ``--help`` shows defaults (and choices, as ever)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        """An ArgumentParser with :class:`HelpFormatter` unless told another."""
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)


def env_help(what: str = "env id") -> str:
    """Help for ``--env``: ``what``, and the ids registered now (the robot presets' and
    the labs' own), which any other id is refused with."""
    import tensegrity_gym  # registers the ids

    return f"{what}; registered: {', '.join(tensegrity_gym.env_ids(hardware=None))}"


def add_engine(parser: argparse.ArgumentParser) -> None:
    """``--engine``: the simulator's physics engine (None, its default: ``pybullet``)."""
    from tensegrity_gym.sim.engines import DEFAULT_ENGINE, ENGINES

    parser.add_argument(
        "--engine", default=None, choices=list(ENGINES.names()),
        help=f"the simulator's physics engine (default: {DEFAULT_ENGINE}; mujoco needs "
        "pip install tensegrity-gym[mujoco])",
    )  # fmt: skip


def add_randomization(parser: argparse.ArgumentParser, help_text: str) -> None:
    """``--randomization``: the simulated world drawn at each reset from these ranges."""
    from tensegrity_gym.model.randomization import RANDOMIZATIONS

    parser.add_argument(
        "--randomization", default=None, choices=sorted(RANDOMIZATIONS),
        help=f"{help_text} (default: none, the description exactly)",
    )  # fmt: skip


def add_lab_map(parser: argparse.ArgumentParser) -> None:
    """``--lab-map``: read the bag argument as a lab's own recording (imported first)."""
    parser.add_argument(
        "--lab-map", default=None,
        help="a lab map (YAML: its bag's topics or its files' kinds, columns, units): read "
        "the BAG argument as the lab's own ROS 1/ROS 2 bag or files, imported first",
    )  # fmt: skip


def add_ray(parser: argparse.ArgumentParser, what: str) -> None:
    """``--ray ADDRESS``: run ``what`` on a Ray cluster."""
    parser.add_argument(
        "--ray",
        default=None,
        metavar="ADDRESS",
        help=f"{what}, on the Ray cluster at ADDRESS (HOST:PORT of `ray start --head`, "
        "auto, or local: a Ray instance started here); needs pip install tensegrity-gym[ray]",
    )
