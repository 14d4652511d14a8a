"""System identification from a recorded run (issue 16, ``tensegrity-gym identify``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pytest

from agents.cli import main
from agents.identify import (
    IdentifyError,
    apply_parameters,
    factor_names,
    identify_run,
    recorded_trajectory,
    replay_sim,
    segment_errors,
    segments_of,
)
from hardware.recording import MemorySink, RecordedRun, RecordingBackend
from tensegrity_gym.envs.factory import make_env
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.model.description import load_robot as load
from tensegrity_gym.tasks.gaits import FaceGait

if TYPE_CHECKING:
    from pathlib import Path

    from tensegrity_gym.model.description import RobotDescription

NOMINAL = load_robot("three_bar")
TRUE_STIFFNESS = (1.3, 0.8)  # actuated, passive: the recorded robot's against the nominal


def _record(d: RobotDescription, seconds: float, gait: bool = True) -> RecordedRun:
    """The robot ``d`` under its gait (or holding still) for ``seconds``, with the truth."""
    env = make_env(d, estimator="oracle", calibration="true")
    sink = MemorySink()
    env.backend = RecordingBackend(env.backend, sink)
    obs, _ = env.reset(seed=0)
    policy = FaceGait(d, env.task)
    hold = env.targets_to_action(d.rest_lengths[d.actuated])
    for _ in range(round(seconds / env.backend.control_period)):
        obs, *_ = env.step(policy(obs) if gait else hold)
    env.close()
    return sink.run


@pytest.fixture(scope="module")
def stiffer() -> RecordedRun:
    names = factor_names(["stiffness"], NOMINAL)
    return _record(apply_parameters(NOMINAL, names, np.log(TRUE_STIFFNESS)), 10.0)


def test_the_true_parameters_replay_the_recording_exactly(stiffer: RecordedRun) -> None:
    """The simulator restarted from the recorded state with the recorded robot's own
    description replays each segment to the millimetre (what makes the fit possible);
    the nominal one does not."""
    frames, source = recorded_trajectory(stiffer)
    assert source == "ground truth"
    segments = segments_of(stiffer, frames, 2.0)
    assert len(segments) == 5 and segments[0].commands.shape == (20, 6)
    names = factor_names(["stiffness"], NOMINAL)
    true = apply_parameters(NOMINAL, names, np.log(TRUE_STIFFNESS))
    com_true, _ = segment_errors(true, segments, replay_sim(true, segments, 0.1, 0.001))
    com_nominal, _ = segment_errors(NOMINAL, segments, replay_sim(NOMINAL, segments, 0.1, 0.001))
    assert com_true.max() < 0.003, com_true
    assert com_nominal.mean() > 3 * com_true.mean(), (com_nominal, com_true)


@pytest.mark.slow
def test_stiffness_is_recovered_and_the_open_loop_error_falls(stiffer: RecordedRun) -> None:
    result = identify_run(stiffer, ["stiffness"], description=NOMINAL, max_evaluations=48,
                          workers=2)  # fmt: skip
    assert result.names == ("actuated_stiffness", "passive_stiffness")
    np.testing.assert_allclose(result.factors, TRUE_STIFFNESS, rtol=0.1)
    assert result.com_after.mean() < result.com_before.mean() / 3
    assert result.evaluations <= 48 + 10  # one generation past the budget at most
    fitted = [c.stiffness for c in result.description.cables]
    assert fitted[0] == pytest.approx(NOMINAL.cables[0].stiffness * result.factors[0])


def test_a_robot_that_hardly_moves_is_one_line(stiffer: RecordedRun) -> None:
    still = _record(NOMINAL, 5.0, gait=False)
    with pytest.raises(IdentifyError, match=r"moved \d+ mm at most .* too little motion") as e:
        identify_run(still, ["damping"], workers=1)
    assert "\n" not in str(e.value)
    with pytest.raises(IdentifyError, match=r"unknown parameter group 'stifness'; choose from"):
        identify_run(stiffer, ["stifness"])
    with pytest.raises(IdentifyError, match=r"mass cannot be fitted with stiffness or damping"):
        identify_run(stiffer, ["stiffness", "mass"])
    with pytest.raises(IdentifyError, match=r"unknown model 'mujoco'"):
        identify_run(stiffer, ["damping"], model="mujoco")


def test_identify_writes_a_robot_the_env_loads(tmp_path: Path) -> None:
    """The command on a recorded bag: a robot YAML gym.make, the simulator and the UKF
    load, and a report with the parameters and the errors before and after."""
    bag_dir = tmp_path / "bags"
    env = make_env(NOMINAL, estimator="oracle", calibration="true", record_dir=bag_dir)
    obs, _ = env.reset(seed=1)
    gait = FaceGait(NOMINAL, env.task)
    for _ in range(50):
        obs, *_ = env.step(gait(obs))
    env.close()
    bag = next(bag_dir.iterdir())
    out = tmp_path / "fitted.yaml"
    code = main(["identify", str(bag), "--out", str(out), "--params", "damping",
                 "--max-evaluations", "12", "--workers", "1"])  # fmt: skip
    assert code == 0
    fitted = load(out)
    assert fitted.n_cables == NOMINAL.n_cables and fitted.name == NOMINAL.name
    report = tmp_path / "fitted_identify"
    assert (report / "report.md").read_text().count("| damping |") == 1
    assert (report / "paths.png").stat().st_size > 1000
    again = make_env(out, estimator="ukf", calibration="true")
    again.reset(seed=0)
    again.close()


def test_identify_refuses_a_bad_bag_in_one_line(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    assert main(["identify", str(tmp_path / "missing"), "--out", str(tmp_path / "x.yaml")]) == 2
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert len(errors) == 1 and "missing: no such bag" in errors[0]
    assert "\n" not in errors[0]
    assert not (tmp_path / "x.yaml").exists()
