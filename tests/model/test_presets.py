"""One preset, one place: a robot's YAML gives its env ids, its gait and (by id) its
training hyperparameters; every preset gets every id."""

from __future__ import annotations

import re
from pathlib import Path

import gymnasium as gym
import pytest

import tensegrity_gym
from agents.training.train import ALGORITHMS, config_entry, load_hyperparams
from tensegrity_gym.model.description import (
    PRESETS,
    DescriptionError,
    dump_robot,
    load_robot,
    loads_robot,
)
from tensegrity_gym.model.registry import TASKS
from tests.conftest import ENV_IDS

TODAY = [
    "tensegrity_gym/ThreeBarRoll-v0",
    "tensegrity_gym/ThreeBarLargeRoll-v0",
    "tensegrity_gym/SuperBallRoll-v0",
    "tensegrity_gym_hardware/ThreeBarRoll-v0",
    "tensegrity_gym_hardware/SuperBallRoll-v0",
]


def expected_ids() -> dict[str, dict[str, str]]:
    """Every preset's ids, from the parsed descriptions (not from the package's reader)."""
    out = {}
    for preset in PRESETS:
        d = load_robot(preset)
        for task, (word, _) in tensegrity_gym.TASK_IDS.items():
            out[f"tensegrity_gym/{d.display_name}{word}-v0"] = {"robot": preset, "task": task}
            if d.hardware:
                out[f"tensegrity_gym_hardware/{d.display_name}{word}-v0"] = {
                    "robot": preset,
                    "task": task,
                    "driver": "zenoh/tcp/127.0.0.1:7447",
                }
    return out


def test_every_preset_gets_every_id_and_nothing_else() -> None:
    expected = expected_ids()
    assert sorted(expected) == ENV_IDS
    assert set(TODAY) <= set(expected)
    assert {"tensegrity_gym/ThreeBarLargeGoTo-v0", "tensegrity_gym/SuperBallGoTo-v0"} <= set(
        expected
    )
    for env_id, kwargs in expected.items():
        spec = gym.spec(env_id)
        assert spec.kwargs == kwargs
        assert spec.nondeterministic == ("driver" in kwargs)
        robot = "driver" in kwargs
        assert [w.name for w in spec.additional_wrappers] == (["StopOnError"] if robot else [])
        assert (spec.vector_entry_point is None) == robot
        steps = tensegrity_gym.TASK_IDS[kwargs["task"]][1]
        assert spec.max_episode_steps == steps


def test_the_id_table_names_every_registered_task() -> None:
    assert set(tensegrity_gym.TASK_IDS) == set(TASKS.names())


@pytest.mark.parametrize("env_id", ENV_IDS)
@pytest.mark.parametrize("algo", ALGORITHMS)
def test_every_id_has_hyperparameters(env_id: str, algo: str) -> None:
    params = load_hyperparams(algo, env_id)
    assert params["n_timesteps"] > 0 and params["policy"] == "MlpPolicy"


def test_a_goto_id_takes_its_robots_rolling_entry() -> None:
    entries = ["tensegrity_gym/ThreeBarRoll-v0", "tensegrity_gym_hardware/ThreeBarRoll-v0"]
    assert config_entry(entries, "tensegrity_gym/ThreeBarGoTo-v0") == entries[0]
    assert config_entry(entries, "tensegrity_gym_hardware/ThreeBarGoTo-v0") == entries[1]
    assert config_entry(entries, "tensegrity_gym/SuperBallGoTo-v0") is None
    assert config_entry(entries, "tensegrity_gym/Nope-v0") is None


def test_the_package_reads_the_header_as_the_parser_does(tmp_path: Path) -> None:
    for preset in PRESETS:
        d = load_robot(preset)
        text = Path(d.source).read_text()
        assert tensegrity_gym._header(text) == {
            "name": d.name,
            "display_name": d.display_name,
            "hardware": d.hardware,
        }
    # Anywhere in the file, quoted or not; nested keys of the same name are not read.
    text = dump_robot(load_robot("three_bar")).replace("display_name: ThreeBar\n", "")
    text = text.replace("hardware: true\n", "") + "hardware: true\ndisplay_name: 'Tri'\n"
    assert tensegrity_gym._header(text) == {"name": "three_bar", "hardware": True,
                                            "display_name": "Tri"}  # fmt: skip


def test_gait_round_trips_and_bad_gaits_name_the_field() -> None:
    d = load_robot("three_bar_large")
    assert d.gait is not None and len(d.gait.faces) >= 3
    assert loads_robot(dump_robot(d)) == d
    text = Path(d.source).read_text()
    bad = {
        "gait.faces[0].face[0]": text.replace("face: [n1, n2, n5]", "face: [n9, n2, n5]"),
        "gait.faces[0].contract[0]": text.replace("contract: [a0, a2, a4]", "contract: [p6]"),
        "gait.faces[0].others": text.replace("others: out", "others: slack", 1),
        "gait.hold_steps": text.replace("hold_steps: 25", "hold_steps: 0"),
        "gait.faces[1].face": text.replace("face: [n0, n3, n4]", "face: [n5, n2, n1]"),
        "display_name": text.replace("display_name: ThreeBarLarge", "display_name: 3bar"),
    }
    for field, broken in bad.items():
        assert broken != text, field
        with pytest.raises(DescriptionError, match="^" + re.escape(f"robot.yaml: {field}: ")):
            loads_robot(broken, "robot.yaml")
