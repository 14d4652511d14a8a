"""docs/extending.md's worked examples run as written: each section's ```python blocks
marked ``<!-- run -->`` are executed in order in one fresh namespace, and the asserts
they hold are what the page claims (an estimator made through ``gym.make`` steps to a
finite observation, a task's argument is refused by name, a robot without UWB is
refused the UKF, a sensor kind records to a bag and reads back, ...).

What the examples register (estimators, tasks, sensor kinds, Gymnasium ids) is removed
again afterwards, so that no other test sees it."""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING

import gymnasium as gym
import numpy as np
import pytest

import tensegrity_gym  # noqa: F401  (registers the ids the examples make)
from hardware.bag.kinds import sensor_kinds, unregister_sensor_kind
from tensegrity_gym.model.registry import ESTIMATORS, TASKS

if TYPE_CHECKING:
    from collections.abc import Iterator

PAGE = Path(__file__).parents[1] / "docs" / "extending.md"
MARK = "<!-- run -->"
RUN_BLOCK = re.compile(r"^<!-- run -->\n```python\n(.*?)^```$", re.M | re.S)


def sections(text: str) -> dict[str, list[str]]:
    """``## `` heading -> the code of its run-marked python blocks, in order."""
    out: dict[str, list[str]] = {}
    for part in re.split(r"^## ", text, flags=re.M)[1:]:
        title, _, body = part.partition("\n")
        out[title.strip()] = RUN_BLOCK.findall(body)
    return out


SECTIONS = sections(PAGE.read_text(encoding="utf-8"))
EXPECTED = {
    "A new estimator": 3,
    "A new task": 3,
    "A new robot": 4,
    "A new sensor kind": 4,
}
"""Sections whose examples run, and how many blocks each has: a block that lost its
marker, or a fence the pattern no longer finds, fails here instead of going untested."""


def test_every_marked_block_is_found() -> None:
    text = PAGE.read_text(encoding="utf-8")
    assert text.count(MARK) == sum(EXPECTED.values())
    assert {k: len(v) for k, v in SECTIONS.items() if v} == EXPECTED


@pytest.fixture
def registries(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A scratch working folder (the examples write files into it), and the registries
    as they were before, restored after."""
    monkeypatch.chdir(tmp_path)
    estimators, tasks = set(ESTIMATORS.names()), set(TASKS.names())
    kinds = {k.name for k in sensor_kinds()}
    ids = set(gym.registry)
    try:
        yield tmp_path
    finally:
        for name in set(ESTIMATORS.names()) - estimators:
            ESTIMATORS.unregister(name)
        for name in set(TASKS.names()) - tasks:
            TASKS.unregister(name)
        for kind in sensor_kinds():
            if kind.name not in kinds:
                unregister_sensor_kind(kind.name)
        for env_id in set(gym.registry) - ids:
            del gym.registry[env_id]


@pytest.mark.parametrize("section", sorted(EXPECTED))
def test_the_examples_run(section: str, registries: Path) -> None:
    namespace: dict[str, object] = {"__name__": f"extending_{section.replace(' ', '_')}"}
    for k, code in enumerate(SECTIONS[section]):
        where = f"docs/extending.md, {section!r}, block {k + 1}"
        # dont_inherit: the page's code runs as a reader's would, without this module's
        # `from __future__ import annotations`.
        exec(compile(code, where, "exec", dont_inherit=True), namespace)
    if section == "A new estimator":
        assert "shifted_shape" in ESTIMATORS.names()
        obs = namespace["obs"]
        assert isinstance(obs, np.ndarray) and np.all(np.isfinite(obs))
    elif section == "A new task":
        assert "stand_up" in TASKS.names() and "my_lab/ThreeBarStandUp-v0" in gym.registry
    elif section == "A new robot":
        assert (registries / "three_bar_heavy.yaml").is_file()
        assert "my_lab/ThreeBarHeavyGoTo-v0" in gym.registry
    elif section == "A new sensor kind":
        assert "barometer" in {k.name for k in sensor_kinds()}
        assert (registries / "bags" / "episode_000").is_dir()
