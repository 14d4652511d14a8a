"""The README's front door holds: its quickstart runs and prints finite numbers, and its
env table gives each simulated id's observation and action sizes as the envs have them."""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING

import gymnasium as gym

import tensegrity_gym

if TYPE_CHECKING:
    import pytest

README = (Path(__file__).parents[1] / "README.md").read_text()


def test_the_readme_is_a_short_front_door() -> None:
    assert len(README.splitlines()) <= 200
    assert README.index("bash scripts/setup.sh") < README.index("## Quickstart")


def test_the_quickstart_runs(capsys: pytest.CaptureFixture[str]) -> None:
    block = re.search(r"## Quickstart\n\n```python\n(.*?)```", README, re.S)
    assert block is not None, "README.md: the quickstart block is gone"
    code = block.group(1).replace("range(300)", "range(3)")  # three steps say enough
    exec(compile(code, "README.md quickstart", "exec"), {})
    printed = capsys.readouterr().out
    assert printed.strip() and "nan" not in printed.lower()


def test_the_env_table_gives_the_sizes() -> None:
    row = r"^\| `tensegrity_gym/(\w+)Roll-v0`, `…GoTo-v0` \|.*?\| (\d+), (\d+) / (\d+) \|"
    rows = re.findall(row, README, re.M)
    robots = {i.split("/")[1].removesuffix("Roll-v0") for i in tensegrity_gym.env_ids()
              if i.endswith("Roll-v0")}  # fmt: skip
    assert {r[0] for r in rows} == robots
    for robot, roll, goto, act in rows:
        for task, size in (("Roll", roll), ("GoTo", goto)):
            env = gym.make(f"tensegrity_gym/{robot}{task}-v0")
            assert env.observation_space.shape == (int(size),), (robot, task)
            assert env.action_space.shape == (int(act),), (robot, task)
            env.close()
