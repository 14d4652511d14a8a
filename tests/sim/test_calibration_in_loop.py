"""What the estimators are handed of the UWB calibration (issue 15): a world drawn once
per env, the choice of ``gym.make(..., calibration=)``, and where the choice is shown."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
import pytest

import tensegrity_gym  # noqa: F401  (registers the envs)
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.model.protocols import UwbCalibration
from tensegrity_gym.sim.backend import SimBackend
from tensegrity_gym.sim.sensors import ANCHOR_PLACEMENT_STD

if TYPE_CHECKING:
    from pathlib import Path

ENV_ID = "tensegrity_gym/ThreeBarRoll-v0"


def test_the_lab_is_drawn_once_per_world_seed_and_kept_across_resets() -> None:
    d = load_robot("three_bar")
    backend = SimBackend(d, world_seed=3)
    backend.reset(np.random.default_rng(0))
    first = backend.true_calibration
    backend.reset(np.random.default_rng(1))
    again = backend.true_calibration
    # Antenna delays and anchor stands do not change between runs.
    np.testing.assert_array_equal(first.uwb_offsets, again.uwb_offsets)
    np.testing.assert_array_equal(first.anchors, again.anchors)
    other = SimBackend(d, world_seed=4)
    other.reset(np.random.default_rng(0))
    assert np.abs(other.true_calibration.uwb_offsets - first.uwb_offsets).max() > 0.01
    # The anchors stand near the layout the description gives, not on it.
    moved = np.abs(first.anchors - d.anchors)
    assert 0 < moved.max() < 5 * ANCHOR_PLACEMENT_STD
    backend.close()
    other.close()


def test_onto_layout_turns_and_shifts_along_the_floor_only() -> None:
    """A floor frame's anchors (turned about z, shifted, heights off by a few cm) come
    onto the floor plan by a turn and a shift in the ground plane: their heights above
    the floor are kept, and a mirror image is not taken for the plan."""
    from tensegrity_gym.envs.calibration_run import onto_layout

    layout = load_robot("three_bar").anchors
    angle, shift = 2.1, np.array([0.7, -1.3, 0.0])
    c, s = np.cos(angle), np.sin(angle)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    heights = np.random.default_rng(0).normal(0.0, 0.03, len(layout))
    floor_frame = layout @ turn.T + shift + np.outer(heights, [0.0, 0.0, 1.0])
    placed = onto_layout(floor_frame, layout)
    np.testing.assert_allclose(placed[:, :2], layout[:, :2], atol=1e-12)
    np.testing.assert_array_equal(placed[:, 2], floor_frame[:, 2])
    mirrored = onto_layout(floor_frame * np.array([1.0, -1.0, 1.0]), layout)
    assert np.abs(mirrored[:, :2] - layout[:, :2]).max() > 0.5


def test_calibration_true_hands_the_simulators_own_and_says_so() -> None:
    env = gym.make(ENV_ID, estimator="oracle", calibration="true", world_seed=2)
    _, info = env.reset(seed=0)
    backend = env.unwrapped.backend  # type: ignore[attr-defined]
    assert info["calibration"] == "true"
    np.testing.assert_array_equal(backend.calibration.anchors, backend.true_calibration.anchors)
    np.testing.assert_array_equal(backend.calibration.anchors, backend.true_uwb.anchors)
    env.close()


def test_a_lab_calibration_replaces_anchors_and_offsets_only() -> None:
    d = load_robot("three_bar")
    backend = SimBackend(d)
    backend.reset(np.random.default_rng(0))
    truth = backend.true_calibration
    lab = UwbCalibration(truth.anchors + 0.01, truth.uwb_offsets + 0.02, source="lab.yaml")
    backend.uwb_calibration = lab
    used = backend.calibration
    np.testing.assert_allclose(used.anchors, truth.anchors + 0.01)
    np.testing.assert_allclose(used.uwb_offsets, truth.uwb_offsets + 0.02)
    np.testing.assert_array_equal(used.camera_pose, truth.camera_pose)
    wrong = UwbCalibration(truth.anchors[:4], truth.uwb_offsets, source="other_lab.yaml")
    with pytest.raises(ValueError, match=r"calibration 'other_lab.yaml' has 4 anchors .* has 8"):
        wrong.applied_to(truth)
    backend.close()


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"calibration": 5}, r"make: calibration=5 must be one of \['estimated', 'true'\]"),
        ({"calibration": "guessed"}, r"make: calibration='guessed' is neither one of"),
        ({"world_seed": -1}, r"make: world_seed=-1 must be an int >= 0"),
        ({"world_seed": 1.5}, r"make: world_seed=1.5 must be an int >= 0"),
    ],
)
def test_bad_calibration_arguments_are_refused_by_name(
    kwargs: dict[str, Any], message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        gym.make(ENV_ID, estimator="oracle", **kwargs)


def test_a_bag_has_no_true_calibration(tmp_path: Path) -> None:
    env = gym.make(ENV_ID, estimator="oracle", calibration="true", record_dir=tmp_path)
    env.reset(seed=0)
    for _ in range(3):
        env.step(env.action_space.sample())
    env.close()
    with pytest.raises(ValueError, match=r"calibration='true' is the simulator's own"):
        gym.make(ENV_ID, driver=f"bag:{tmp_path / 'episode_000'}", calibration="true")
    # The run info keeps the simulator's anchors and offsets beside the bag's own.
    from hardware.bag.reader import BagReader

    with BagReader(tmp_path / "episode_000") as bag:
        assert bag.run_info["calibration"] == "true"
        truth = np.asarray(bag.run_info["true_calibration"]["anchors"])
        np.testing.assert_allclose(truth, bag.calibration.anchors)


def test_a_robot_without_uwb_gets_the_nominal_layout_never_the_truth() -> None:
    from dataclasses import replace

    d = load_robot("three_bar")
    bare = replace(d, carries=tuple(sorted(d.sample_kinds - {"uwb"})))
    env = gym.make(ENV_ID, robot=bare, estimator="oracle")
    _, info = env.reset(seed=0)
    backend = env.unwrapped.backend  # type: ignore[attr-defined]
    assert info["calibration"] == "nominal"
    np.testing.assert_array_equal(backend.calibration.anchors, d.anchors)
    offsets = backend.calibration.uwb_offsets
    assert np.all(offsets[~np.eye(len(offsets), dtype=bool)] == d.sensors.uwb.offset_mean)
    assert np.abs(backend.calibration.anchors - backend.true_calibration.anchors).max() > 0
    env.close()


def test_the_default_is_the_calibrators_estimate_close_to_the_truth() -> None:
    # The first make of the robot in this world runs the calibration; later ones (and
    # other tests) read it from the cache.
    env = gym.make(ENV_ID, estimator="ukf")
    _, info = env.reset(seed=0)
    backend = env.unwrapped.backend  # type: ignore[attr-defined]
    used, truth = backend.calibration, backend.true_calibration
    assert info["calibration"] == "estimated"
    n = backend.description.n_nodes
    anchor_error = np.linalg.norm(used.anchors - truth.anchors, axis=1)
    # In the lab's floor-plan frame: the anchors' own errors plus the fit onto the plan.
    assert 0 < anchor_error.max() < 0.15, anchor_error
    offset_error = used.uwb_offsets[n:, :n] - truth.uwb_offsets[n:, :n]
    assert 0 < np.sqrt(np.mean(offset_error**2)) < 0.03
    env.close()


def _lab_file(tmp_path: Path, shift: float) -> tuple[Path, Any]:
    from estimation.uwb_calibration import save_calibration

    d = load_robot("three_bar")
    backend = SimBackend(d)
    backend.reset(np.random.default_rng(0))
    truth = backend.true_calibration
    backend.close()
    path = tmp_path / "lab.yaml"
    lab = UwbCalibration(truth.anchors + shift, truth.uwb_offsets).applied_to(truth)
    save_calibration(path, lab, robot=d.name)
    return path, truth


def test_a_calibration_file_is_what_the_estimators_get(tmp_path: Path) -> None:
    path, truth = _lab_file(tmp_path, 0.02)
    env = gym.make(ENV_ID, estimator="ukf", calibration=path)
    _, info = env.reset(seed=0)
    used = env.unwrapped.backend.calibration  # type: ignore[attr-defined]
    assert info["calibration"] == str(path)
    np.testing.assert_allclose(used.anchors, truth.anchors + 0.02)
    env.close()


def _recorded(tmp_path: Path, steps: int) -> Path:
    """A bag of ``steps`` random steps of the 3-bar robot, with the true calibration."""
    env = gym.make(ENV_ID, estimator="oracle", calibration="true", record_dir=tmp_path / "runs")
    env.reset(seed=0)
    for _ in range(steps):
        env.step(env.action_space.sample())
    env.close()
    return tmp_path / "runs" / "episode_000"


def test_estimate_reruns_a_bag_with_another_calibration_against_the_truth(
    tmp_path: Path,
) -> None:
    from agents.recordings.offline import estimate_bag

    bag = _recorded(tmp_path, 25)
    path, _ = _lab_file(tmp_path, 0.03)
    recorded = estimate_bag(bag, "ukf", tmp_path / "a", progress=False)[0]
    other = estimate_bag(bag, "ukf", tmp_path / "b", progress=False, calibration=path)[0]
    assert recorded["calibration"] == "recorded"
    assert recorded["calibration_against_true"]["anchor_rms_m"] == 0
    assert other["calibration"] == str(path)
    against = other["calibration_against_true"]
    assert against["anchor_rms_m"] == pytest.approx(0.03 * np.sqrt(3), abs=1e-4)
    assert against["robot_anchor_offset_rms_m"] == 0


def test_calibrate_writes_a_file_and_refuses_a_bag_without_enough_ranges(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from agents.cli import main

    bag = _recorded(tmp_path, 3)
    out = tmp_path / "lab.yaml"
    assert main(["calibrate", str(bag), "--out", str(out)]) == 2
    assert not out.exists()
    assert main(["calibrate", "--out", str(out)]) == 2  # neither a bag nor an env
    assert main(["calibrate", "--env", ENV_ID, "--seconds", "30", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "verdict:" in printed and "anchor 7:" in printed
    from estimation.uwb_calibration import load_calibration

    assert load_calibration(out).anchors.shape == (8, 3)


def test_a_failed_calibration_is_refused_and_not_cached(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A calibration whose verdict is "failed" is never handed to an estimator: make
    says why in one line, and nothing is cached to be read next time."""
    from types import SimpleNamespace

    import tensegrity_gym.envs.calibration_run as calibration_run

    monkeypatch.setenv("TENSEGRITY_GYM_CACHE", str(tmp_path))
    verdict = "failed: residual spread 400 mm (ranges and geometry disagree)"
    monkeypatch.setattr(
        calibration_run, "record_calibration_run", lambda *a, **k: SimpleNamespace(samples=[])
    )
    monkeypatch.setattr(
        calibration_run,
        "lab_calibration",
        lambda *a: SimpleNamespace(quality="failed", verdict=verdict),
    )
    d = load_robot("three_bar")
    with pytest.raises(ValueError, match=r"did not calibrate \(failed: residual spread") as e:
        calibration_run.estimated_uwb_calibration(d, world_seed=5)
    assert "\n" not in str(e.value)
    assert not list(tmp_path.rglob("*.yaml"))
