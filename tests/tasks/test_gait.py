"""The scripted gaits roll the robot: the CoM moves and the support face changes; the
1.45 m robot's named gaits go forward, backward, and turn left and right."""

from __future__ import annotations

import argparse
import importlib.util
import logging
import re
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from agents.cli import main
from agents.gait import heading_change, run_gait
from tensegrity_gym.envs.factory import make_roll_env
from tensegrity_gym.model.description import (
    DescriptionError,
    dump_robot,
    load_robot,
    loads_robot,
    robot_document,
)
from tensegrity_gym.model.randomization import Randomization
from tensegrity_gym.tasks.gaits import FaceGait, gait_table, ramp_toward

LARGE = "tensegrity_gym/ThreeBarLargeRoll-v0"
ROOT = Path(__file__).resolve().parents[2]


def test_three_bar_gait_rolls_face_to_face(tmp_path) -> None:
    summary = run_gait("tensegrity_gym/ThreeBarRoll-v0", steps=120, seed=1, out=tmp_path)
    assert not summary["diverged"]
    assert summary["face_changes"] >= 3, "it flips from one base triangle to the next"
    assert summary["distance"] > 0.4  # metres in 12 s; the robot is 0.36 m long
    # The gait reads the UKF's estimate, and the estimate follows the truth while rolling.
    assert summary["estimator"] == "ukf"
    assert summary["estimation_error_max"] < 0.05
    assert (tmp_path / "com_path.png").stat().st_size > 10_000
    assert (tmp_path / "summary.json").exists()


def test_superball_gait_goes_through_face_transitions(tmp_path) -> None:
    summary = run_gait("tensegrity_gym/SuperBallRoll-v0", steps=110, seed=2, out=tmp_path)
    assert not summary["diverged"]
    assert summary["face_changes"] >= 2
    assert summary["distance"] > 1.0  # metres; SUPERball's rods are 1.5 m
    assert summary["estimation_error_rms"] < 0.05


def test_large_three_bar_gait_rolls_it_forward(tmp_path) -> None:
    # The gait of three_bar_large.yaml (scripts/find_gait.py; its comment says how far).
    summary = run_gait("tensegrity_gym/ThreeBarLargeRoll-v0", steps=140, seed=0, out=tmp_path)
    assert not summary["diverged"]
    assert summary["face_changes"] >= 4
    start, end = np.array(summary["com_start"]), np.array(summary["com_end"])
    assert end[0] - start[0] > 1.5  # metres forward in 14 s; its rods are 1.45 m
    assert abs(end[1] - start[1]) < 0.5 * (end[0] - start[0])  # forward, not sideways
    # The UKF follows it: 2.3 cm RMS, its worst step 10.4 cm on an AMD EPYC host (under
    # 10 on the machine before): a roll's chaos carries a CPU's last bits into that one
    # transient, so the bound on it leaves room, and the RMS says the estimate follows.
    assert summary["estimation_error_rms"] < 0.04
    assert summary["estimation_error_max"] < 0.15


def test_gait_rejects_a_robot_without_one_and_bad_table() -> None:
    env = make_roll_env("three_bar")
    bare = replace(env.backend.description, gait=None)
    with pytest.raises(ValueError, match=r"no gait table for robot 'three_bar'.*find_gait"):
        FaceGait(bare, env.task)
    with pytest.raises(TypeError, match="decode"):
        FaceGait(env.backend.description, object())  # type: ignore[arg-type]
    env.close()
    env = make_roll_env("three_bar")
    with pytest.raises(ValueError, match="bad gait table entry"):
        FaceGait(env.backend.description, env.task, table={(0, 1, 2): ((9,), "hold")})
    env.close()


def test_gait_state_resets() -> None:
    env = make_roll_env("three_bar")
    gait = FaceGait(env.backend.description, env.task)
    obs, _ = env.reset(seed=0)
    first = [gait(obs) for _ in range(3)]
    gait.reset()
    again = [gait(obs) for _ in range(3)]
    assert all(np.array_equal(a, b) for a, b in zip(first, again, strict=True))
    env.close()


def test_ramp_toward_steps_at_most_its_share_of_the_range() -> None:
    commanded = np.array([-1.0, 0.5, 0.9], dtype=np.float32)
    target = np.array([1.0, 0.45, -1.0], dtype=np.float32)
    nxt = ramp_toward(commanded, target, 10)
    np.testing.assert_allclose(nxt, [-0.8, 0.45, 0.7], atol=1e-6)  # 2 / 10 a step at most
    assert nxt.dtype == np.float32
    np.testing.assert_array_equal(ramp_toward(commanded, target, 0), target)
    for _ in range(10):
        commanded = ramp_toward(commanded, target, 10)
    np.testing.assert_array_equal(commanded, target)  # the whole range in 10 steps


def test_a_ramped_gait_moves_its_commands_at_the_ramps_rate() -> None:
    env = make_roll_env("three_bar")
    gait = FaceGait(env.backend.description, env.task)
    assert gait.ramp_steps == 11  # three_bar.yaml's
    obs, _ = env.reset(seed=0)
    actions = np.array([gait(obs) for _ in range(gait.hold_steps + gait.settle_steps)])
    steps = np.abs(np.diff(np.vstack([gait.hold_action, actions]), axis=0))
    assert steps.max() <= 2.0 / 11 + 1e-6
    target = gait.action_for_face(gait.support_face(obs))
    np.testing.assert_array_equal(actions[gait.hold_steps - 1], target)  # reached in the hold
    assert not np.array_equal(actions[0], target)
    np.testing.assert_allclose(actions[-1], gait.hold_action, atol=1e-6)  # back by the rest
    stepped = FaceGait(env.backend.description, env.task, ramp_steps=0)
    stepped.reset()
    np.testing.assert_array_equal(stepped(obs), target)
    with pytest.raises(ValueError, match=r"ramp_steps from 0 to hold_steps \(got 26\)"):
        FaceGait(env.backend.description, env.task, ramp_steps=26)
    env.close()


def test_a_ramp_longer_than_the_hold_is_refused_naming_the_field() -> None:
    doc = robot_document(load_robot("three_bar"))
    doc["gait"]["ramp_steps"] = 30
    with pytest.raises(DescriptionError, match=r"^robot.yaml: gait.ramp_steps: expected at most "):
        loads_robot(yaml.safe_dump(doc, sort_keys=False), "robot.yaml")


def test_the_ramp_keeps_the_gait_rolling_with_unequal_motors() -> None:
    # A flip is dynamic: contracted at once by motors 25 % apart, the three cables stop it
    # on the face between two of the table's, and it falls back every period. Along a
    # ramp slower than the slowest motor they contract together and it rolls on.
    env = make_roll_env(
        "three_bar", estimator="oracle", randomization=Randomization(motor_speed=(0.75, 1.25))
    )
    travel = {}
    for ramp in (0, 11):
        gait = FaceGait(env.backend.description, env.task, ramp_steps=ramp)
        obs, _ = env.reset(seed=1003)
        start = env.backend.ground_truth().com[:2].copy()
        for _ in range(140):
            obs, *_ = env.step(gait(obs))
        travel[ramp] = float(np.linalg.norm(env.backend.ground_truth().com[:2] - start))
    env.close()
    assert travel[0] < 0.1, travel  # metres in 14 s: stalled
    assert travel[11] > 0.5, travel


# ----------------------------------------------------------------- named gaits


def test_named_gaits_load_and_round_trip() -> None:
    d = load_robot("three_bar_large")
    assert list(d.gaits) == ["forward", "backward", "left", "right"]
    assert d.gaits["forward"] is d.gait
    assert loads_robot(dump_robot(d)) == d
    three_bar = load_robot("three_bar")
    assert list(three_bar.gaits) == ["forward", "steer"]  # its gait first, then gaits:
    assert three_bar.gait is not None and three_bar.gait.ramp_steps == 11
    assert loads_robot(dump_robot(three_bar)) == three_bar  # ramp_steps round-trips
    assert replace(d, gait=None).gaits.keys() == {"backward", "left", "right"}


def _broken(doc: dict[str, Any], field: str) -> dict[str, Any]:
    """``doc`` with the gaits field ``field`` made wrong."""
    gaits = doc["gaits"]
    if field == "gaits.left.faces[1].contract[0]":
        gaits["left"]["faces"][1]["contract"] = ["p6"]
    elif field == "gaits.right.hold_steps":
        gaits["right"]["hold_steps"] = 0
    elif field == "gaits.right.ramp_steps":
        gaits["right"]["ramp_steps"] = -1
    elif field == "gaits.backward.faces[0].face":
        gaits["backward"]["faces"][0]["face"] = ["n0", "n1"]
    elif field == "gaits.forward":
        gaits["forward"] = doc["gait"]
    elif field == "gaits.Left":
        gaits["Left"] = gaits.pop("left")
    elif field == "gaits":
        doc["gaits"] = [gaits["left"]]
    return doc


@pytest.mark.parametrize(
    "field",
    [
        "gaits.left.faces[1].contract[0]",
        "gaits.right.hold_steps",
        "gaits.right.ramp_steps",
        "gaits.backward.faces[0].face",
        "gaits.forward",
        "gaits.Left",
        "gaits",
    ],
)
def test_a_bad_named_gait_names_the_file_and_field(field: str) -> None:
    doc = _broken(robot_document(load_robot("three_bar_large")), field)
    with pytest.raises(DescriptionError, match="^" + re.escape(f"robot.yaml: {field}: ")):
        loads_robot(yaml.safe_dump(doc, sort_keys=False), "robot.yaml")


def test_face_gait_takes_a_gait_by_name_and_lists_them_for_another() -> None:
    env = make_roll_env("three_bar_large")
    d = env.backend.description
    left = FaceGait(d, env.task, gait="left")
    assert left.gait == "left" and left.table == gait_table(d, "left") != gait_table(d)
    assert (left.hold_steps, left.settle_steps) == (d.gaits["left"].hold_steps, 10)
    names = re.escape("['backward', 'forward', 'left', 'right']")
    with pytest.raises(ValueError, match=f"named 'sideways'.*{names}.*find_gait"):
        FaceGait(d, env.task, gait="sideways")
    env.close()


def test_the_cli_refuses_a_gait_the_robot_lacks_in_one_line(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.ERROR):
        code = main(["gait", "--env", LARGE, "--gait", "sideways", "--out", str(tmp_path / "g")])
    assert code == 2
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "\n" not in errors[0] and "'left'" in errors[0], errors
    assert not (tmp_path / "g").exists()


def test_heading_change() -> None:
    t = np.radians(np.arange(0.0, 91.0, 10.0))
    arc = np.stack([np.sin(t), 1.0 - np.cos(t)], axis=1)  # a quarter circle to the left
    assert heading_change(arc) == pytest.approx(80.0)  # from the first chord to the last
    assert heading_change(arc[:, ::-1], 2) == pytest.approx(-70.0)  # mirrored: right
    assert heading_change(np.zeros((5, 2))) == 0.0
    u = np.linspace(0.0, 4.0 * np.pi, 41)
    loop = np.stack([np.cos(u), np.sin(u)], axis=1)
    assert heading_change(loop) == pytest.approx(702.0)  # twice round, unwrapped


# ------------------------------------------- what the 1.45 m robot's gaits do

# Measured on the oracle (run_gait, seeds 0 to 3, since the motors keep a minimum
# tension and backward was searched again): in 140 steps backward goes 2.3 to 3.0 m, the
# cosine of its move to forward's -0.99 to -1.00.
BACKWARD_MIN, BACKWARD_COS = 1.5, -0.7
# In 420 steps (12 periods), the heading changes +15 to +51 deg on left (seed 1: +21),
# -25 to -43 deg on right (all of its gaits but left drift right, the prism being
# chiral). A turn shows over whole cycles: in 150 steps right has not done two of its own.
TURNS = [("left", 420, 10.0), ("right", 420, 20.0)]
# Steps to 5 m of CoM path from rest to rest, seed 0 (the YAML's comments), plus one
# period (since the motors keep a minimum tension forward no longer stalls on seed 0;
# it does on seed 2, after 4 m). The left turn rocks on the spot more than it rolls:
# 3.4 m in 700 steps, 4.3 m in 900, 5.3 m in 1100 (seed 0, the oracle).
TRAVEL_STEPS = [("backward", 315), ("left", 1100), ("right", 315), ("forward", 385)]


def _run(gait: str, steps: int, seed: int) -> dict[str, Any]:
    return run_gait(LARGE, steps=steps, seed=seed, estimator="oracle", gait=gait)


def _moved(summary: dict[str, Any]) -> np.ndarray:
    return np.subtract(summary["com_end"], summary["com_start"])[:2]


@pytest.mark.parametrize("seed", [0, 3])
def test_backward_goes_the_other_way_from_forward(seed: int) -> None:
    # The reset's yaw is random, so the two are compared from the same seed.
    forward, backward = _moved(_run("forward", 140, seed)), _moved(_run("backward", 140, seed))
    assert np.linalg.norm(backward) > BACKWARD_MIN  # metres in 14 s
    cos = forward @ backward / (np.linalg.norm(forward) * np.linalg.norm(backward))
    assert cos < BACKWARD_COS


@pytest.mark.parametrize(("gait", "steps", "least"), TURNS)
def test_left_turns_left_and_right_turns_right(gait: str, steps: int, least: float) -> None:
    summary = _run(gait, steps, seed=1)
    assert not summary["diverged"]
    sign = 1.0 if gait == "left" else -1.0
    assert sign * summary["heading_change_deg"] > least, summary["heading_change_deg"]


@pytest.mark.slow
@pytest.mark.parametrize(("gait", "steps"), TRAVEL_STEPS)
def test_each_gait_travels_5_m(gait: str, steps: int) -> None:
    # Tong et al. 2024 (table II) wants runs of 5 m at least: CoM path from rest to rest.
    assert _run(gait, steps, seed=0)["rest_path_length"] > 5.0


def _find_gait() -> Any:
    """scripts/find_gait.py, imported as a module."""
    spec = importlib.util.spec_from_file_location("find_gait", ROOT / "scripts" / "find_gait.py")
    assert spec is not None and spec.loader is not None
    find_gait = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(find_gait)
    return find_gait


def test_find_gaits_search_restores_the_ramp_with_the_world() -> None:
    """scripts/find_gait.py runs a path on from a saved state: with a ramp cut short by
    the rest, the command the ramp had reached is restored with the world, so a path run
    on from its prefix ends where the same path run from the reset does (to PyBullet's
    restore, 1e-5 m; the ramp restarted from the rest lengths ends 6 mm away)."""
    find_gait = _find_gait()
    args = argparse.Namespace(robot="three_bar", hold=25, settle=5, ramp=11, max_combo=1)
    resumed = find_gait.Rollouts(args, 0, {})
    resumed.outcome((0, 1))  # saves the state after (0,)
    _, commanded = resumed._states[(0,)]
    assert not np.allclose(commanded, resumed.hold)  # the ramp is mid-way there
    face, com, _ = resumed.outcome((0, 2))
    fresh = find_gait.Rollouts(args, 0, {})
    fresh_face, fresh_com, _ = fresh.outcome((0, 2))
    resumed.close()
    fresh.close()
    assert face == fresh_face
    assert np.linalg.norm(com - fresh_com) < 1e-3


class _Outcomes:
    """Stands in for find_gait's Rollouts: where each path leaves the robot, from a dict
    (path -> (face, CoM x, y in m, yaw in rad)); a path it lacks moved nothing."""

    def __init__(self, table: dict[tuple[int, ...], tuple[tuple[int, ...], float, float, float]]):
        self.table = table

    def outcome(self, path: tuple[int, ...]) -> tuple[tuple[int, ...], np.ndarray, float]:
        while path not in self.table:
            path = path[:-1]
        face, x, y, yaw = self.table[path]
        return face, np.array([x, y]), yaw


def test_find_gaits_robust_model_keeps_the_moves_that_hold_from_every_start() -> None:
    """``--steer`` runs the model's outcomes again from the face's other resting states
    (reached from its other neighbours): a move that lands elsewhere from one of them is
    dropped (``--share 1``), kept at a share it meets, and a kept move is the mean of
    where it went, in each start's own frame."""
    find_gait = _find_gait()
    a, b, c = (0, 1, 2), (1, 2, 3), (2, 3, 4)
    quarter = np.pi / 2
    sim = _Outcomes(
        {
            (): (a, 0.0, 0.0, 0.0),
            (0,): (b, 1.0, 0.0, 0.0),  # a -> b, the first way onto b
            (1,): (c, 0.0, 1.0, 0.0),
            (1, 5): (b, 0.0, 2.0, quarter),  # c -> b: b from its other side, turned
            (0, 7): (c, 1.5, 0.0, 0.0),  # on b, move 7 reaches c from both starts
            (1, 5, 7): (c, 0.0, 2.4, quarter),
            (0, 8): (a, 1.0, 0.6, 0.0),  # move 8 reaches a from one start only
            (1, 5, 8): (b, 0.0, 2.0, quarter),
        }
    )
    model = {
        (a, 0): (b, np.array([1.0, 0.0, 0.0])),
        (a, 1): (c, np.array([0.0, 1.0, 0.0])),
        (c, 5): (b, np.array([0.0, 1.0, quarter])),
        (b, 7): (c, np.array([0.5, 0.0, 0.0])),
        (b, 8): (a, np.array([0.0, 0.6, 0.0])),
    }
    paths = {a: (), b: (0,), c: (1,)}
    assert find_gait.arrivals(model, paths, b, 3) == [(0,), (1, 5)]
    kept = find_gait.robust(sim, model, paths, starts=3, share=1.0)
    assert (b, 8) not in kept
    to, move = kept[b, 7]
    assert to == c
    # From (1, 5) the robot faces +y: 0.4 m along +y is 0.4 m ahead in its frame.
    np.testing.assert_allclose(move, [0.45, 0.0, 0.0], atol=1e-12)
    assert (b, 8) in find_gait.robust(sim, model, paths, starts=3, share=0.5)
    assert (b, 8) in find_gait.robust(sim, model, paths, starts=1, share=1.0)


def test_find_gaits_mean_move_averages_turns_on_the_circle() -> None:
    find_gait = _find_gait()
    half = np.pi - 0.02
    moves = np.array([[0.2, 0.0, half], [0.4, 0.2, -half]])
    np.testing.assert_allclose(find_gait.mean_move(moves)[:2], [0.3, 0.1])
    assert abs(abs(find_gait.mean_move(moves)[2]) - np.pi) < 1e-9
    np.testing.assert_allclose(find_gait.mean_move(moves[:1]), moves[0], atol=1e-12)
