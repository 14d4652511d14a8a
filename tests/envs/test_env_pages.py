"""The generated env pages (``docs/envs``, ``scripts/env_pages.py``): they are what the
script writes now, their observation tables are the envs' spaces, and every registered
id has one."""

from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
import pytest

if TYPE_CHECKING:
    from collections.abc import Iterator
    from types import ModuleType

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs" / "envs"
FIX = "run `python scripts/env_pages.py` to regenerate the env pages"


def _load() -> ModuleType:
    """scripts/env_pages.py, imported as a module."""
    spec = importlib.util.spec_from_file_location("env_pages", ROOT / "scripts" / "env_pages.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


pages = _load()
IDS = pages.registered_ids()
SIMULATED = [i for i in IDS if not pages.is_hardware(gym.spec(i))]


@pytest.fixture(scope="module")
def envs() -> Iterator[dict[tuple[str, str], Any]]:
    """The made envs by (robot, task), shared by the tests; closed after the module."""
    made: dict[tuple[str, str], Any] = {}
    yield made
    for env in made.values():
        env.close()


@pytest.fixture(scope="module")
def generated(tmp_path_factory: pytest.TempPathFactory, envs: dict[Any, Any]) -> Path:
    """The pages as the script writes them now, in a fresh folder."""
    out = tmp_path_factory.mktemp("envs")
    pages.generate(out, envs)
    return out


def _relative(paths: set[Path], root: Path) -> set[str]:
    return {p.relative_to(root).as_posix() for p in paths}


def test_the_committed_pages_are_what_the_script_writes(generated: Path) -> None:
    fresh = _relative(pages.generated_pages(generated), generated)
    committed = _relative(pages.generated_pages(DOCS), DOCS) if DOCS.is_dir() else set()
    assert committed == fresh, f"pages missing {sorted(fresh - committed)}, stale " \
                               f"{sorted(committed - fresh)}: {FIX}"  # fmt: skip
    stale = [
        name
        for name in sorted(fresh)
        if (DOCS / name).read_text(encoding="utf-8")
        != (generated / name).read_text(encoding="utf-8")
    ]
    assert not stale, f"out of date: {stale}: {FIX}"


def _section_table(text: str, section: str) -> list[list[str]]:
    """The cells of the first table after the heading ``section``, header dropped."""
    body = text.split(f"\n## {section}\n", 1)[1]
    rows: list[list[str]] = []
    for line in body.splitlines():
        if line.startswith("|"):
            rows.append([c.strip() for c in line.strip("|").split(" | ")])
        elif rows:
            break
    return rows[2:]


def _summary(text: str, key: str) -> str:
    found = re.search(rf"^\| {key} \| (.+) \|$", text, re.MULTILINE)
    assert found, f"no '{key}' row in the page's summary table: {FIX}"
    return found[1]


@pytest.mark.parametrize("env_id", SIMULATED)
def test_the_observation_table_is_the_space(env_id: str, envs: dict[Any, Any]) -> None:
    facts = pages.simulated_facts(env_id, envs)
    path = DOCS / facts.page
    assert path.is_file(), f"{env_id} has no page {path}: {FIX}"
    text = path.read_text(encoding="utf-8")
    space = envs[(facts.description.name, facts.task_name)].observation_space
    assert int(_summary(text, "Observation size")) == space.shape[0]
    low, high = np.full(space.shape, np.nan), np.full(space.shape, np.nan)
    covered = 0
    for index, _meaning, _units, lo, hi in _section_table(text, "Observation space"):
        start, _, last = index.partition("-")
        stop = int(last or start) + 1
        assert int(start) == covered, f"{env_id}: the table skips or repeats index {covered}"
        low[int(start) : stop], high[int(start) : stop] = float(lo), float(hi)
        covered = stop
    assert covered == space.shape[0], f"{env_id}: the table covers {covered} entries"
    np.testing.assert_allclose(low, space.low, rtol=1e-5, err_msg=f"{env_id}: low")
    np.testing.assert_allclose(high, space.high, rtol=1e-5, err_msg=f"{env_id}: high")
    actions = _section_table(text, "Action space")
    assert len(actions) == envs[(facts.description.name, facts.task_name)].action_space.shape[0]


def test_every_registered_id_has_a_page() -> None:
    assert SIMULATED and len(SIMULATED) < len(IDS), "expected simulated and hardware ids"
    index = (DOCS / "index.md").read_text(encoding="utf-8")
    for env_id in IDS:
        name = env_id.partition("/")[2]
        hardware = pages.is_hardware(gym.spec(env_id))
        page = DOCS / ("hardware" if hardware else "") / f"{name}.md"
        assert page.is_file(), f"{env_id} has no page {page}: {FIX}"
        assert f"`{env_id}`" in page.read_text(encoding="utf-8"), f"{page} is not {env_id}'s"
        assert f"`{env_id}`" in index, f"index.md lists no {env_id}: {FIX}"


def test_the_layout_covers_an_observed_gait() -> None:
    """With residual actions and ``observe_base``, the env's layout (the task's, then
    the gait's action) still spans its observation space entry by entry."""
    env = gym.make("tensegrity_gym/ThreeBarRoll-v0", residual_gait=0.5, observe_base=True)
    try:
        space: Any = env.observation_space
        fields = env.unwrapped.observation_layout()  # type: ignore[attr-defined]
        assert [f.start for f in fields[1:]] == [f.stop for f in fields[:-1]]
        assert fields[0].start == 0 and fields[-1].stop == space.shape[0]
        for f in fields:
            assert np.all(space.low[f.start : f.stop] == f.low), f
            assert np.all(space.high[f.start : f.stop] == f.high), f
        obs, _ = env.reset(seed=0)
        assert obs.shape == space.shape
    finally:
        env.close()
