"""Gymnasium environments for tensegrity robots whose policies see estimated states.

Importing the package only registers the env ids; nothing heavy is imported.

The ids come from a loop over the robot presets and the tasks: for each preset YAML in
``tensegrity_gym/model/assets`` (its ``display_name``, say ``ThreeBar``) and each task
(``Roll``, ``GoTo``), ``tensegrity_gym/ThreeBarRoll-v0``; and where the preset says
``hardware: true``, ``tensegrity_gym_hardware/ThreeBarRoll-v0`` through the robot link.
Adding a robot is adding its YAML file.
"""

from __future__ import annotations

from importlib import resources
from typing import Any

import yaml
from gymnasium.envs.registration import WrapperSpec, register

__version__ = "0.1.0"

NAMESPACE = "tensegrity_gym"
"""The simulated envs' Gymnasium namespace: ``tensegrity_gym/ThreeBarRoll-v0``."""
HARDWARE_NAMESPACE = "tensegrity_gym_hardware"
"""The namespace of the envs that drive a robot over the link (or the emulator)."""

_ENTRY = "tensegrity_gym.envs.factory:make_env"
_VECTOR_ENTRY = "tensegrity_gym.envs.vector:make_vector_env"
# Outermost: whatever fails in the stack gym.make builds, the motors stop.
_SAFETY = (WrapperSpec("StopOnError", "tensegrity_gym.envs.safety:StopOnError", {}),)
# The robot (or the emulator, ``tensegrity-gym emulate``) on the network; pass
# driver="zenoh/tcp/HOST:PORT" to reach another.
_HARDWARE_DRIVER = "zenoh/tcp/127.0.0.1:7447"

TASK_IDS: dict[str, tuple[str, int]] = {"roll": ("Roll", 300), "goto": ("GoTo", 600)}
"""Registered task name (``tensegrity_gym.model.registry.TASKS``) -> (its word in the
env ids, episode steps). A GoTo episode is 60 s: a goal is drawn 2-4 rod lengths away,
and at the scripted gait's pace (about 0.01 rod lengths a step on the 3-bar robot) the
mean distance takes 300 steps in a straight line, before any turning."""

_HEADER = frozenset({"name", "display_name", "hardware"})


def _header(text: str) -> dict[str, Any]:
    """The top-level scalars ``name``, ``display_name`` and ``hardware`` of a preset's
    YAML. YAML events are read only until all three are seen (the generated files
    start with them), so that importing the package does not parse the robots."""
    found: dict[str, Any] = {}
    depth, key = 0, None
    for event in yaml.parse(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader)):
        if isinstance(event, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
            depth, key = depth + 1, None
        elif isinstance(event, (yaml.MappingEndEvent, yaml.SequenceEndEvent)):
            depth -= 1
        elif depth == 1 and isinstance(event, yaml.ScalarEvent):
            if key is None:
                key = event.value
                continue
            if key in _HEADER:
                plain = event.implicit[0]
                found[key] = yaml.safe_load(event.value) if plain else event.value
                if found.keys() >= _HEADER:
                    break
            key = None
    return found


def preset_ids() -> dict[str, dict[str, Any]]:
    """Every registered id -> its ``gym.make`` kwargs (``robot``, ``task`` and, for a
    robot on the link, ``driver``), from the preset files and :data:`TASK_IDS`."""
    ids: dict[str, dict[str, Any]] = {}
    for asset in sorted((resources.files(__name__) / "model" / "assets").iterdir(),
                        key=lambda f: f.name):  # fmt: skip
        if not asset.name.endswith(".yaml"):
            continue
        head = _header(asset.read_text(encoding="utf-8"))
        robot = asset.name[: -len(".yaml")]
        display = head.get("display_name") or "".join(p.capitalize() for p in robot.split("_"))
        for task, (word, _) in TASK_IDS.items():
            ids[f"{NAMESPACE}/{display}{word}-v0"] = {"robot": robot, "task": task}
            if head.get("hardware") is True:
                ids[f"{HARDWARE_NAMESPACE}/{display}{word}-v0"] = {
                    "robot": robot,
                    "task": task,
                    "driver": _HARDWARE_DRIVER,
                }
    return ids


def env_ids(*, hardware: bool | None = False) -> list[str]:
    """The registered ids of this package's namespaces, sorted: the simulated ones
    (``hardware=False``), the robot's (``True``) or both (``None``); a lab's own ids
    registered in these namespaces included."""
    from gymnasium.envs.registration import registry

    if hardware is None:
        spaces: tuple[str, ...] = (NAMESPACE, HARDWARE_NAMESPACE)
    else:
        spaces = (HARDWARE_NAMESPACE,) if hardware else (NAMESPACE,)
    return sorted(i for i in registry if i.partition("/")[0] in spaces)


for _id, _kwargs in preset_ids().items():
    _robot = "driver" in _kwargs
    register(
        id=_id,
        entry_point=_ENTRY,
        max_episode_steps=TASK_IDS[_kwargs["task"]][1],
        # A robot's motors stop whatever fails in the wrapper stack. A simulated id has no
        # motors to stop, and a native vector env instead (Gymnasium's vector entry point
        # takes no additional wrappers); its passive checker is off, since after a reset
        # that failed it raises TypeError at the next step (Gymnasium 1.x) where the env
        # says to reset again, and check_env passes on every id (tests/envs).
        additional_wrappers=_SAFETY if _robot else (),
        vector_entry_point=None if _robot else _VECTOR_ENTRY,
        disable_env_checker=not _robot,
        nondeterministic=_robot,
        kwargs=_kwargs,
    )
