"""The steering gait: several contractions per face, each with the move it makes, and
FaceGait choosing the one that rolls furthest toward the goal; it rolls toward any
heading and to goals, which the forward gait cannot."""

from __future__ import annotations

import cmath
import math
import re
from typing import Any

import numpy as np
import pytest
import yaml

from agents.evaluate import GAIT_POLICY, STEER_POLICY, gait_policy
from tensegrity_gym.envs.factory import make_env, make_roll_env
from tensegrity_gym.model.description import (
    STEER_GAIT,
    DescriptionError,
    dump_robot,
    load_robot,
    loads_robot,
    robot_document,
)
from tensegrity_gym.tasks.gaits import FaceGait, face_yaw, lowest_face, turned


def test_the_steering_gait_loads_and_round_trips() -> None:
    d = load_robot("three_bar")
    steer = d.gaits[STEER_GAIT]
    faces = [e.face for e in steer.faces]
    assert len(set(faces)) < len(faces)  # faces have several entries to choose from
    assert all(e.move is not None and e.to is not None for e in steer.faces)
    assert all(e.to != e.face for e in steer.faces)  # every entry leaves its face
    assert loads_robot(dump_robot(d)) == d
    assert d.gait is not None and all(e.move is None for e in d.gait.faces)


def _broken(doc: dict[str, Any], field: str) -> dict[str, Any]:
    faces = doc["gaits"]["steer"]["faces"]
    if field == "gaits.steer.faces[1]":
        del faces[1]["to"]  # a move without the face it leads to
    elif field == "gaits.steer.faces[0].move":
        faces[0]["move"] = [0.1, 0.2]
    elif field == "gaits.steer.faces[2].to":
        faces[2]["to"] = ["n0", "n1", "n9"]
    elif field == "gait.faces[1].face":  # a plain gait's face listed twice
        doc["gait"]["faces"][1]["face"] = doc["gait"]["faces"][0]["face"]
    return doc


@pytest.mark.parametrize(
    "field",
    [
        "gaits.steer.faces[1]",
        "gaits.steer.faces[0].move",
        "gaits.steer.faces[2].to",
        "gait.faces[1].face",
    ],
)
def test_a_bad_steering_entry_names_the_file_and_field(field: str) -> None:
    doc = _broken(robot_document(load_robot("three_bar")), field)
    with pytest.raises(DescriptionError, match="^" + re.escape(f"robot.yaml: {field}")):
        loads_robot(yaml.safe_dump(doc, sort_keys=False), "robot.yaml")


def _reference_choice(gait: FaceGait, face: tuple[int, ...], yaw: float) -> int:
    """The index among the face's entries a slow reference chooses: complex numbers for
    the turns, every pair of moves over two periods written out."""
    entries = [e for e in gait_entries(gait) if e.face == face]
    best, chosen = -math.inf, -1
    for i, e in enumerate(entries):
        first = complex(e.move[0], e.move[1]) * cmath.exp(1j * yaw)
        then = [
            (complex(f.move[0], f.move[1]) * cmath.exp(1j * (yaw + e.move[2]))).real
            for f in gait_entries(gait)
            if f.face == e.to
        ]
        total = first.real + (max(then) if then else 0.0)
        if total > best:
            best, chosen = total, i
    return chosen


def gait_entries(gait: FaceGait) -> Any:
    return gait.task.description.gaits[STEER_GAIT].faces


def test_the_choice_matches_a_slow_reference_at_every_yaw() -> None:
    env = make_roll_env("three_bar", estimator="oracle")
    gait = FaceGait(env.backend.description, env.task, gait=STEER_GAIT)
    assert gait.steers
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    positions = env.task.decode(obs).positions.astype(np.float64)
    face = lowest_face(positions)
    entries = [e for e in gait_entries(gait) if e.face == face]
    seen = set()
    for angle in rng.uniform(-np.pi, np.pi, 24):
        spun = positions.copy()
        spun[:, :2] = turned(positions[:, :2], angle)
        yaw = face_yaw(spun, face)
        chosen = entries[_reference_choice(gait, face, yaw)]
        expected = np.ones(6, dtype=np.float32) if chosen.others == "out" else gait.hold_action
        expected = expected.copy()
        expected[list(chosen.contract)] = -1.0
        np.testing.assert_array_equal(gait.action_for_face(face, spun), expected)
        seen.add(chosen)
    assert len(seen) >= 2  # the goal's direction changes the choice
    env.close()


def _progress(task: str, gait: str, seed: int, steps: int, **kwargs: Any) -> float:
    """Metres the true CoM came toward the goal (along its heading, or to its point)."""
    env = make_env("three_bar", task, estimator="oracle", **kwargs)
    policy = FaceGait(env.backend.description, env.task, gait=gait)
    obs, _ = env.reset(seed=seed)
    start = env.backend.ground_truth().com[:2].copy()
    for _ in range(steps):
        obs, *_ = env.step(policy(obs))
    end = env.backend.ground_truth().com[:2]
    if task == "roll":
        out = float((end - start) @ env.task.direction)
    else:
        goal = env.task.goal
        out = float(np.linalg.norm(goal - start) - np.linalg.norm(goal - end))
    env.close()
    return out


# Measured on the oracle, 210 steps (6 periods) from reset(0): the steering gait makes
# 0.41 to 0.76 m toward each of the four headings; the forward gait rolls its own way,
# backward for two of them.
HEADINGS = (0.0, 0.5 * np.pi, np.pi, -0.5 * np.pi)


def test_the_steering_gait_rolls_toward_every_heading() -> None:
    steer = [_progress("roll", STEER_GAIT, 0, 210, goal_heading=h) for h in HEADINGS]
    forward = [_progress("roll", "forward", 0, 210, goal_heading=h) for h in HEADINGS]
    assert min(steer) > 0.3, steer
    assert min(forward) < 0.0, forward  # the forward gait cannot aim
    assert np.mean(steer) > np.mean(forward) + 0.3


def test_the_steering_gait_comes_to_a_goal_point() -> None:
    # The go-to task's goal frame points at the goal, which moves on once reached.
    assert _progress("goto", STEER_GAIT, 1, 210) > 0.3


def test_residual_actions_correct_the_gait_named_by_base_gait() -> None:
    env = make_roll_env("three_bar", estimator="oracle", residual_gait=0.5, base_gait="steer")
    assert isinstance(env.action_base, FaceGait) and env.action_base.gait == STEER_GAIT
    env.close()
    with pytest.raises(ValueError, match=r"^make: base_gait: .*'sideways'.*\['forward', 'steer'\]"):
        make_roll_env("three_bar", residual_gait=0.5, base_gait="sideways")


def test_evaluate_has_a_steering_gait_row_where_the_robot_has_one() -> None:
    three_bar = gait_policy("tensegrity_gym/ThreeBarRoll-v0", STEER_POLICY)
    assert three_bar is not None and three_bar.name == STEER_POLICY
    assert gait_policy("tensegrity_gym/ThreeBarLargeRoll-v0", STEER_POLICY) is None
    assert gait_policy("tensegrity_gym/ThreeBarLargeRoll-v0", GAIT_POLICY) is not None
