"""System identification from a recorded run (issue 16, ``tensegrity-gym identify``)."""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
import pytest

from agents.cli import main
from agents.identification.identify import (
    COARSE_SHARE,
    COARSE_STRIDE,
    IdentifyError,
    apply_parameters,
    factor_bounds,
    factor_names,
    identify_run,
    imu_windows,
    parameter_values,
    recorded_trajectory,
    replay_imu,
    replay_sim,
    segment_errors,
    segments_of,
)
from agents.identification.imu import imu_features, window_scores, without_imu
from agents.identification.report import fit_notes
from hardware.recording import MemorySink, RecordedRun, RecordingBackend
from tensegrity_gym.envs.factory import make_env
from tensegrity_gym.model.description import dump_robot, load_robot, loads_robot
from tensegrity_gym.model.description import load_robot as load
from tensegrity_gym.model.lie import quat_from_rotvec, quat_rotate
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
    # The budget counts candidates on every window: a coarse one costs a quarter.
    budget = COARSE_STRIDE * COARSE_SHARE * 48 + (1 - COARSE_SHARE) * 48
    assert result.evaluations <= budget + 2 * 10  # a generation past each stage at most
    fitted = [c.stiffness for c in result.description.cables]
    assert fitted[0] == pytest.approx(NOMINAL.cables[0].stiffness * result.factors[0])


TRUE_ROD_LENGTHS = (1.04, 1.0, 0.97)
"""The recorded robot's rod lengths against the nominal's (a tape measure's centimetre)."""


def test_the_geometry_group_has_a_factor_per_rod_and_passive_cable() -> None:
    names = factor_names(["geometry"], NOMINAL)
    passive = [c.name for c in NOMINAL.cables if not c.actuated]
    assert names == [f"rod_length[{r.name}]" for r in NOMINAL.rods] + [
        f"rest_length[{c}]" for c in passive
    ]
    fitted = apply_parameters(NOMINAL, names[1:2], np.log([1.05]))
    lengths = [r.length for r in fitted.rods]
    assert lengths == [
        NOMINAL.rods[0].length,
        1.05 * NOMINAL.rods[1].length,
        NOMINAL.rods[2].length,
    ]
    assert parameter_values(fitted, names[1]) == lengths[1]
    rest = apply_parameters(NOMINAL, names[-1:], np.log([0.9])).rest_lengths
    changed = np.flatnonzero(rest != NOMINAL.rest_lengths)
    assert [NOMINAL.cables[k].name for k in changed] == passive[-1:]
    np.testing.assert_allclose(rest[changed], 0.9 * NOMINAL.rest_lengths[changed], rtol=1e-12)
    # A rod made longer keeps its centre and axis, its nodes moved apart: written out,
    # the fitted robot loads again (a rod's nodes must lie its length apart).
    again = loads_robot(dump_robot(fitted))
    ends = again.initial_positions[list(again.rods[1].nodes)]
    assert np.linalg.norm(ends[1] - ends[0]) == pytest.approx(lengths[1], rel=1e-9)
    nominal_ends = NOMINAL.initial_positions[list(NOMINAL.rods[1].nodes)]
    np.testing.assert_allclose(ends.mean(axis=0), nominal_ends.mean(axis=0), atol=1e-12)
    with pytest.raises(IdentifyError, match=r"has no factor 'rod_length\[purple\]'"):
        apply_parameters(NOMINAL, ["rod_length[purple]"], np.zeros(1))
    # A rod searched within 15 %, a rest length within 20 %, the global factors 2x.
    np.testing.assert_allclose(
        np.exp(factor_bounds([*names[:1], names[-1], "damping"])), [1.15, 1.2, 2.0]
    )
    with pytest.raises(IdentifyError, match=r"give one of them$"):
        factor_names(["rest", "geometry"], NOMINAL)


@pytest.mark.slow  # 192 fits of a 10 s recording (96 left the rods 1.5 % off)
def test_rod_lengths_off_the_description_are_found() -> None:
    """Rods 4 % long and 3 % short in the world, nominal in the description: the
    geometry group (three rods, three passive rest lengths) finds each rod to 0.5 %
    and leaves the rest lengths near 1; the CoM replay error falls tenfold."""
    names = factor_names(["geometry"], NOMINAL)[:3]
    run = _record(apply_parameters(NOMINAL, names, np.log(TRUE_ROD_LENGTHS)), 10.0)
    result = identify_run(run, ["geometry"], description=NOMINAL, max_evaluations=192,
                          workers=2)  # fmt: skip
    np.testing.assert_allclose(result.factors[:3], TRUE_ROD_LENGTHS, atol=0.005)
    np.testing.assert_allclose(result.factors[3:], 1.0, atol=0.01)
    assert result.com_after.mean() < result.com_before.mean() / 10 and not result.at_bound


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


@pytest.mark.parametrize("engine", ["pybullet", pytest.param("mujoco", marks=pytest.mark.slow)])
def test_identify_writes_a_robot_the_env_loads(tmp_path: Path, engine: str) -> None:
    """The command on a recorded bag (from either engine: identification simulates in
    PyBullet whatever recorded it): a robot YAML gym.make, the simulator and the UKF
    load, and a report with the parameters and the errors before and after."""
    bag_dir = tmp_path / "bags"
    env = make_env(NOMINAL, estimator="oracle", calibration="true", record_dir=bag_dir,
                   engine=engine)  # fmt: skip
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
    markdown = (report / "report.md").read_text()
    assert markdown.count("| damping |") == 1 and "fitted to the IMU's readings over" in markdown
    assert "**Note:**" not in markdown  # the bag has an IMU: damping is not weakly fitted
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


def _imu_scores(d: RobotDescription, windows: list) -> np.ndarray:
    readings = [w.imu for w in windows]
    return window_scores(d, readings, replay_imu(d, windows, 0.1, 0.001))


def test_the_imu_readings_of_the_true_robot_replay_to_the_noise(stiffer: RecordedRun) -> None:
    """Replayed over one period from each recorded state, the true robot's IMUs read
    what the recorded ones did to within the sensors' noise in most periods (a score
    of 1 is the noise), the nominal robot's a hundred times further off; started
    without the spin its gyro read, the replay is further off too."""
    frames, _ = recorded_trajectory(stiffer)
    windows = imu_windows(stiffer, frames, 0.001, most=50)
    assert len(windows) == 50 and windows[0].imu is not None
    assert windows[0].imu.features.shape == (20, 3, 3)
    names = factor_names(["stiffness"], NOMINAL)
    true = apply_parameters(NOMINAL, names, np.log(TRUE_STIFFNESS))
    scores = _imu_scores(true, windows)
    assert np.median(scores) < 3.0, scores
    assert np.median(_imu_scores(NOMINAL, windows)) > 100 * np.median(scores)
    still = [replace(w, spin=np.zeros_like(w.spin)) for w in windows]
    assert np.any(np.abs(windows[5].spin) > 0.1)  # the rods spin as the robot rolls
    assert np.mean(_imu_scores(true, still)) > 2 * np.mean(scores)


def test_a_replay_does_not_depend_on_the_one_before(stiffer: RecordedRun) -> None:
    """Each replay is started on its own contacts (PyBullet warm-starts its solver from
    the last step): the windows in reverse order score as in order, where a world
    teleported from the previous window's end read a hundred times the noise."""
    frames, _ = recorded_trajectory(stiffer)
    windows = imu_windows(stiffer, frames, 0.001, most=34)
    names = factor_names(["stiffness"], NOMINAL)
    true = apply_parameters(NOMINAL, names, np.log(TRUE_STIFFNESS))
    forward = _imu_scores(true, windows)
    backward = _imu_scores(true, windows[::-1])[::-1]
    np.testing.assert_allclose(backward, forward, rtol=0.05, atol=0.2)


def test_imu_features_ignore_the_spin_angle() -> None:
    """What is compared of a reading does not depend on the rod's unknown spin angle
    about its own axis (body z)."""
    rng = np.random.default_rng(0)
    accel, gyro = rng.normal(size=(2, 5, 3))
    spin = quat_from_rotvec(np.array([0.0, 0.0, 1.1]))
    turned = imu_features(quat_rotate(spin, accel), quat_rotate(spin, gyro))
    np.testing.assert_allclose(turned, imu_features(accel, gyro), atol=1e-12)
    assert not np.allclose(imu_features(accel[:, ::-1], gyro), imu_features(accel, gyro))


def test_a_bag_without_imu_is_fitted_on_the_nodes_with_a_note(stiffer: RecordedRun) -> None:
    bare = without_imu(stiffer)
    frames, _ = recorded_trajectory(bare)
    assert imu_windows(bare, frames, 0.001) == []
    assert all(not s.spin.any() for s in segments_of(bare, frames, 2.0))
    result = identify_run(bare, ["damping"], description=NOMINAL, max_evaluations=4,
                          workers=1)  # fmt: skip
    assert len(result.imu_before) == 0 and len(result.com_before) == 5
    (note,) = fit_notes(result)
    assert "no IMU readings were fitted" in note and "damping factor is weakly determined" in note
    with_imu = identify_run(stiffer, ["damping"], description=NOMINAL, max_evaluations=4,
                            workers=1, imu_windows_most=20)  # fmt: skip
    assert len(with_imu.imu_before) == 20 and fit_notes(with_imu) == []


def test_the_search_scores_a_quarter_of_the_windows_first() -> None:
    """The budget is in candidates scored on every IMU window: half of it goes to four
    times as many candidates scored on every fourth window of the bag, the same ones
    whatever the chunks (workers); with too few windows (or none), one stage."""
    from agents.identification.identify import _stages

    chunks = [(slice(0, 15), slice(0, 150)), (slice(15, 30), slice(150, 300))]
    (coarse, coarse_until), (fine, fine_until) = _stages(chunks, 320)
    assert [s for s, _ in coarse] == [s for s, _ in chunks] and fine == chunks
    assert (coarse_until, fine_until) == (640, 800)
    assert _stages(chunks, 3)[0][1] == 8 and _stages(chunks, 3)[1][1] == 9  # 2 coarse, 1 fine

    def chosen(chunks: list[tuple[slice, slice]]) -> list[int]:
        return [i for _, w in _stages(chunks, 320)[0][0] for i in range(300)[w]]

    assert chosen(chunks) == list(range(0, 300, 4))
    three = [(slice(0, 10), slice(0, 99)), (slice(10, 20), slice(99, 201)),
             (slice(20, 30), slice(201, 300))]  # fmt: skip
    assert chosen(three) == list(range(0, 300, 4))
    few = [(slice(0, 15), slice(0, 20)), (slice(15, 30), slice(20, 39))]
    assert _stages(few, 320) == [(few, 320)]
    none = [(slice(0, 15), slice(0, 0)), (slice(15, 30), slice(0, 0))]
    assert _stages(none, 320) == [(none, 320)]


def test_a_state_set_in_flight_steps_as_the_run_it_was_taken_from() -> None:
    """The cables' damping after a teleport acts on the stretching rate the set
    velocities give (not on none, for one step): a vibrating robot in the air, set
    again in the state it had, steps as it did (a 5 mm/s kick otherwise)."""
    from tensegrity_gym.sim.world import PhysicsWorld

    world = PhysicsWorld(NOMINAL, 0.001)
    world.set_node_positions(NOMINAL.initial_positions + np.array([0.0, 0.0, 1.0]))
    rng = np.random.default_rng(0)
    position, quaternion, _, _ = (np.asarray(a) for a in world.rod_states())
    world.set_rod_states(position, quaternion, rng.normal(0, 0.3, (3, 3)),
                         rng.normal(0, 3.0, (3, 3)))  # fmt: skip
    hold = NOMINAL.rest_lengths[NOMINAL.actuated].tolist()
    world.advance(20, hold, [False] * 20)
    state = [np.asarray(a) for a in world.rod_states()]
    before = world.advance(1, hold, [True])[0]
    world.set_rod_states(*state)
    again = world.advance(1, hold, [True])[0]
    world.close()
    kick = np.subtract(again.rod_linear_velocities, before.rod_linear_velocities)
    assert np.abs(kick).max() < 5e-4


@pytest.mark.slow  # 48 fits of a 10 s recording; the default run fits others
def test_a_factor_that_ends_at_its_bound_is_named_not_reported_as_measured() -> None:
    """A robot whose cables are three times as stiff as its description, fitted within
    the search's factor of two: the stiffness ends at the bound, and the result and
    the report's notes name it with the range searched, instead of a value."""
    names = factor_names(["stiffness"], NOMINAL)
    run = _record(apply_parameters(NOMINAL, names, np.log([3.0, 1.0])), 10.0)
    result = identify_run(run, ["stiffness"], description=NOMINAL, max_evaluations=48,
                          workers=2)  # fmt: skip
    assert result.factors[0] > 1.9
    assert result.at_bound == {"actuated_stiffness": (0.5, 2.0)}
    note = next(n for n in fit_notes(result) if n.startswith("actuated_stiffness"))
    assert "ended at the bound of the search" in note and "searched 0.5-2" in note
    assert "passive_stiffness" not in " ".join(fit_notes(result))
