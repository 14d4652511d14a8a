"""UWB self-calibration (estimation.uwb_calibration, Caluwaerts et al. 2016 III-C).

The ranges come from the project's own sensor model (``UwbModel.sample``): on the
resting pose of the 3-bar robot rolled edge over edge across the anchors (a rigid
kinematic roll, no physics: seconds, not minutes), and, in the slow tests, on the
simulated robot under its gait. No anchor position is handed to the calibrator.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

from estimation.uwb_calibration import (
    CalibrationConfig,
    CalibrationError,
    CalibrationFileError,
    CalibrationResult,
    calibrate_ranges,
    calibrate_samples,
    check_samples,
    lm,
    load_calibration,
    rigid_alignment_rms,
    save_calibration,
    solve,
)
from estimation.uwb_calibration.assemble import assemble, start_positions, with_contacts
from estimation.uwb_calibration.problem import JointState
from estimation.uwb_calibration.rounds import range_table, sample_rows
from estimation.uwb_calibration.solve import gauge_mask
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.model.kinematics import weighted_kabsch
from tensegrity_gym.model.protocols import SensorCalibration
from tensegrity_gym.model.samples import UwbRangeSample
from tensegrity_gym.sim.sensors import UwbModel

if TYPE_CHECKING:
    from pathlib import Path

    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription

RATE = 15.0  # UWB rounds per second
FAST = CalibrationConfig(n_starts=1, max_samples=800)


def _rotation(axis: NDArray[np.float64], angle: float) -> NDArray[np.float64]:
    u = axis / np.linalg.norm(axis)
    K = np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])
    return np.asarray(np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K)


def _roll_edge(
    P: NDArray[np.float64], r: NDArray[np.float64], a: int, b: int, third: int
) -> tuple[NDArray[np.float64], float]:
    """The axis through nodes a, b signed so that ``third`` lifts, and the angle (rad)
    at which the next node comes down onto the floor."""
    axis = P[b] - P[a]
    if (_rotation(axis, 0.01) @ (P[third] - P[a]))[2] < (P[third] - P[a])[2]:
        axis = -axis
    others = [k for k in range(len(P)) if k not in (a, b)]
    for angle in np.radians(np.arange(0.5, 180.0, 0.25)):
        Q = (P - P[a]) @ _rotation(axis, angle).T + P[a]
        if np.any(Q[others, 2] < r[others] - 1e-4):
            return axis, float(angle - np.radians(0.25))
    raise AssertionError("the robot does not come down")


def _pick_edge(
    P: NDArray[np.float64],
    face: NDArray[np.intp],
    want: NDArray[np.float64],
    rng: np.random.Generator,
) -> tuple[int, int, int]:
    """The edge of the support ``face`` to roll over (its two nodes, then the third):
    the one facing ``want`` (a unit heading), give or take some noise."""
    centre = P[face].mean(axis=0)[:2]
    best: tuple[float, int, int, int] | None = None
    for a, b, c in ((0, 1, 2), (1, 2, 0), (0, 2, 1)):
        out = 0.5 * (P[face[a]] + P[face[b]])[:2] - centre
        score = float(out @ want / np.linalg.norm(out) + 0.3 * rng.standard_normal())
        if best is None or score > best[0]:
            best = (score, int(face[a]), int(face[b]), int(face[c]))
    assert best is not None
    return best[1], best[2], best[3]


def roll_frames(
    d: RobotDescription, rng: np.random.Generator, seconds: float, radius: float
) -> list[NDArray[np.float64]]:
    """Node positions (n, 3) at each UWB round: the resting pose rolled edge over edge
    (1 s a roll, 1 s at rest) toward waypoints on a circle of ``radius`` m."""
    P, r, L = d.initial_positions.copy(), d.node_radii, d.characteristic_length
    frames: list[NDArray[np.float64]] = []
    heading = rng.uniform(0.0, 2.0 * np.pi)
    while len(frames) < seconds * RATE:
        frames += [P.copy()] * int(RATE)
        com = P.mean(axis=0)
        goal = radius * np.array([np.cos(heading), np.sin(heading)])
        if np.linalg.norm(goal - com[:2]) < 0.5 * L:
            heading += rng.uniform(1.0, 2.5)
            goal = radius * np.array([np.cos(heading), np.sin(heading)])
        face = np.argsort(P[:, 2] - r)[:3]
        want = (goal - com[:2]) / (np.linalg.norm(goal - com[:2]) + 1e-12)
        a, b, third = _pick_edge(P, face, want, rng)
        axis, stop = _roll_edge(P, r, a, b, third)
        for k in range(1, int(RATE) + 1):
            frames.append((P - P[a]) @ _rotation(axis, stop * k / RATE).T + P[a])
        P = frames[-1].copy()
    return frames[: int(seconds * RATE)]


def uwb_run(
    d: RobotDescription,
    frames: list[NDArray[np.float64]],
    seed: int,
    *,
    move: tuple[int, NDArray[np.float64]] | None = None,
) -> tuple[list[UwbRangeSample], UwbModel]:
    """The rounds ``UwbModel`` gives for ``frames`` in the world drawn from ``seed``
    (anchors, offsets, loss: the same seed, the same world); ``move``: (anchor,
    displacement m (3,)) moves one anchor after the world is drawn. The truth is the
    model's: ``model.anchors``, ``model.offsets``."""
    model = UwbModel(d.sensors.uwb, d)
    world = np.random.default_rng(seed)
    draw_world = getattr(model, "draw_world", None)  # the world apart from the episode
    if draw_world is not None:
        draw_world(world)
    model.reset(world)
    if move is not None:
        model.anchors = model.anchors.copy()
        model.anchors[move[0]] += move[1]
    snaps = [
        SimpleNamespace(t=round((k + 1) / RATE, 3), node_positions=f) for k, f in enumerate(frames)
    ]
    return model.sample(snaps, np.random.default_rng(seed + 1)), model  # type: ignore[arg-type]


def offset_errors(
    result: CalibrationResult, truth: NDArray[np.float64], n: int
) -> tuple[float, float]:
    """RMS (m) of the robot-anchor and of the robot-robot offsets against ``truth``."""
    ra = result.offsets[n:, :n] - truth[n:, :n]
    iu = np.triu_indices(n, 1)
    rr = result.offsets[:n, :n][iu] - truth[:n, :n][iu]
    return float(np.sqrt(np.mean(ra**2))), float(np.sqrt(np.mean(rr**2)))


@pytest.fixture(scope="module")
def three_bar() -> RobotDescription:
    return load_robot("three_bar")


@pytest.fixture(scope="module")
def roll(three_bar: RobotDescription) -> list[NDArray[np.float64]]:
    return roll_frames(three_bar, np.random.default_rng(1), 180.0, radius=1.2)


@pytest.fixture(scope="module")
def run(
    three_bar: RobotDescription, roll: list[NDArray[np.float64]]
) -> tuple[list[UwbRangeSample], UwbModel]:
    return uwb_run(three_bar, roll, seed=7)


@pytest.fixture(scope="module")
def calibrated(
    three_bar: RobotDescription, run: tuple[list[UwbRangeSample], UwbModel]
) -> CalibrationResult:
    return calibrate_samples(run[0], three_bar, config=FAST, rng=np.random.default_rng(0))


def test_anchors_and_offsets_without_known_anchors(
    three_bar: RobotDescription,
    run: tuple[list[UwbRangeSample], UwbModel],
    calibrated: CalibrationResult,
) -> None:
    _, model = run
    assert rigid_alignment_rms(calibrated.anchors, model.anchors) <= 0.02
    robot_anchor, robot_robot = offset_errors(calibrated, model.offsets, three_bar.n_nodes)
    assert robot_anchor <= 0.015
    assert robot_robot <= 0.015
    assert calibrated.quality == "good", calibrated.verdict
    assert calibrated.offsets.shape == (14, 14)
    np.testing.assert_allclose(calibrated.offsets, calibrated.offsets.T)


def test_floor_frame_gauge_and_mirror(
    run: tuple[list[UwbRangeSample], UwbModel], calibrated: CalibrationResult
) -> None:
    """Anchor 0 above the origin, anchor 1 above +x, z up from the floor the robot
    rests on (the truth's z = 0), and the robot's handedness, not its mirror image."""
    a, truth = calibrated.anchors, run[1].anchors
    assert a[0, 0] == 0.0 and a[0, 1] == 0.0 and a[1, 1] == 0.0 and a[1, 0] > 0.0
    dz = a[:, 2] - truth[:, 2]  # heights above the floor, not above anchor 0
    assert abs(np.mean(dz)) < 0.03 and np.max(np.abs(dz)) < 0.08, dz
    mirrored = truth * np.array([1.0, -1.0, 1.0])
    assert rigid_alignment_rms(a, mirrored) > 10 * rigid_alignment_rms(a, truth)
    assert calibrated.mirror in ("kept", "flipped")
    gauge = calibrated.anchors_in_anchor_frame()
    assert np.allclose(gauge[0], 0.0) and abs(gauge[1, 1]) < 1e-12 and abs(gauge[2, 2]) < 1e-9


def test_multipath_outliers_do_not_pull(
    three_bar: RobotDescription, run: tuple[list[UwbRangeSample], UwbModel]
) -> None:
    """10 % of the ranges 0.5 to 3 m too long."""
    samples, model = run
    rng = np.random.default_rng(3)
    spoiled = []
    for s in samples:
        ranges = s.ranges.copy()
        hit = rng.random(len(ranges)) < 0.1
        ranges[hit] += rng.uniform(0.5, 3.0, int(hit.sum()))
        spoiled.append(UwbRangeSample(s.t, s.times, s.pairs, ranges))
    result = calibrate_samples(spoiled, three_bar, config=FAST, rng=np.random.default_rng(0))
    assert rigid_alignment_rms(result.anchors, model.anchors) <= 0.025
    assert offset_errors(result, model.offsets, three_bar.n_nodes)[0] <= 0.02
    assert not result.flagged_anchors, result.verdict
    assert 0.08 < result.extras["screened_share"] < 0.12  # the jumps found before the solve


def test_anchor_moved_after_calibration_is_flagged(
    three_bar: RobotDescription, roll: list[NDArray[np.float64]], calibrated: CalibrationResult
) -> None:
    """The same world (seed), later ranges: as calibrated they fit; with anchor 3
    moved 30 cm they flag it, and only it."""
    frames = roll[: int(30 * RATE)]
    same, _ = uwb_run(three_bar, frames, seed=7)
    assert check_samples(calibrated, same, three_bar, n_samples=100).verdict == "fits"
    later, _ = uwb_run(three_bar, frames, seed=7, move=(3, 0.3 * np.array([0.6, 0.8, 0.0])))
    check = check_samples(calibrated, later, three_bar, n_samples=100)
    assert check.flagged_anchors == (3,), check.verdict


@pytest.mark.parametrize("mirrored", ["all", "high"])
def test_a_start_mirrored_under_the_floor_is_turned_back(
    three_bar: RobotDescription,
    run: tuple[list[UwbRangeSample], UwbModel],
    monkeypatch: pytest.MonkeyPatch,
    mirrored: str,
) -> None:
    """The robot moves in a slab a few tenths of a metre thick, so a start can settle
    on the anchors' mirror image through that slab (the high anchors under the floor,
    at a lower cost than the truth on noisy ranges), or on the mirror image of some
    anchors only (each is placed by its own ranges: seen on a 3-bar built off its
    description). Forced onto either, the solve still ends above the floor, on the
    truth."""
    samples, model = run
    solution = calibrate_samples(samples, three_bar, config=FAST, rng=np.random.default_rng(0))
    mirror = solution.anchors.copy()
    # "high": every other anchor above 0.5 m, as the description-error world had it.
    rows = np.arange(len(mirror)) if mirrored == "all" else np.flatnonzero(mirror[:, 2] > 0.5)[::2]
    mirror[rows, 2] = 2.0 * three_bar.initial_positions[:, 2].mean() - mirror[rows, 2]
    assert mirror[:, 2].min() < -0.3  # the mirror image is under the floor
    start = JointState(mirror, np.full(len(solution.anchors) * 6 + 15, solution.mean_offset),
                       solution.mean_offset, np.zeros((0, 3)))  # fmt: skip
    monkeypatch.setattr(solve, "_grow", lambda run, _: start)
    result = calibrate_samples(samples, three_bar, config=FAST, rng=np.random.default_rng(0))
    assert result.anchors[:, 2].min() > 0.1, result.anchors
    assert rigid_alignment_rms(result.anchors, model.anchors) <= 0.02
    assert result.quality == "good", result.verdict


def test_known_anchors_give_their_frame(
    three_bar: RobotDescription, run: tuple[list[UwbRangeSample], UwbModel]
) -> None:
    """Three anchors measured by hand (the paper's way): the result is in their frame."""
    samples, model = run
    known = {a: model.anchors[a] for a in (0, 2, 4)}
    result = calibrate_samples(samples, three_bar, known_anchors=known, config=FAST)
    assert result.frame == "known"
    np.testing.assert_allclose(result.anchors[[0, 2, 4]], model.anchors[[0, 2, 4]], atol=0.01)
    assert np.sqrt(np.mean(np.sum((result.anchors - model.anchors) ** 2, axis=1))) <= 0.03
    with pytest.raises(ValueError, match="2 anchors given, at least 3"):
        calibrate_samples(samples, three_bar, known_anchors={0: (0.0, 0.0, 1.0), 1: (1.0, 0, 0)})


def test_too_few_samples_is_one_line_with_counts(
    three_bar: RobotDescription, run: tuple[list[UwbRangeSample], UwbModel]
) -> None:
    with pytest.raises(CalibrationError, match=r"^\d+ usable samples .* 60 needed$") as e:
        calibrate_samples(run[0][:40], three_bar)
    assert "\n" not in str(e.value)
    with pytest.raises(CalibrationError, match="0 usable samples"):
        calibrate_samples([], three_bar)


def test_same_seed_same_calibration(
    three_bar: RobotDescription, run: tuple[list[UwbRangeSample], UwbModel]
) -> None:
    config = CalibrationConfig(n_starts=1, max_samples=150, start_samples=60)
    samples = run[0][: int(40 * RATE)]
    first = calibrate_samples(samples, three_bar, config=config, rng=np.random.default_rng(5))
    second = calibrate_samples(samples, three_bar, config=config, rng=np.random.default_rng(5))
    np.testing.assert_array_equal(first.anchors, second.anchors)
    np.testing.assert_array_equal(first.offsets, second.offsets)
    assert first.verdict == second.verdict


def test_arrays_and_time_grouping_match_the_samples(
    three_bar: RobotDescription, run: tuple[list[UwbRangeSample], UwbModel]
) -> None:
    """Rows grouped by their times make the same rounds as the samples they came in."""
    t, i, j, m, index = sample_rows(run[0])
    n, A = three_bar.n_nodes, len(three_bar.anchors)
    by_time = range_table(t, i, j, m, n_nodes=n, n_anchors=A, round_gap=0.5 / RATE)
    by_sample = range_table(t, i, j, m, n_nodes=n, n_anchors=A, round_gap=0.5 / RATE, rounds=index)
    np.testing.assert_array_equal(by_time.a_round, by_sample.a_round)
    np.testing.assert_array_equal(by_time.r_round, by_sample.r_round)
    assert by_time.n_rounds == len(run[0])
    with pytest.raises(ValueError, match=r"row 0: module pair \(3, 3\)"):
        range_table([0.0], [3], [3], [1.0], n_nodes=n, n_anchors=A, round_gap=0.03)
    with pytest.raises(ValueError, match="1-D of one length"):
        calibrate_ranges([0.0, 1.0], [0], [7], [1.0], three_bar)


def test_save_load_round_trip(tmp_path: Path, calibrated: CalibrationResult) -> None:
    path = tmp_path / "calibration.yaml"
    save_calibration(path, calibrated, robot="three_bar")
    loaded = load_calibration(path)
    assert loaded.robot == "three_bar" and loaded.frame == "floor"
    np.testing.assert_allclose(loaded.anchors, calibrated.anchors)
    np.testing.assert_allclose(loaded.offsets, calibrated.offsets)
    assert loaded.result is not None
    assert loaded.result.verdict == calibrated.verdict
    assert loaded.result.anchor_stats == calibrated.anchor_stats
    camera = SensorCalibration(calibrated.offsets, calibrated.anchors, 2.0 * np.eye(3), np.eye(4))
    save_calibration(tmp_path / "sensor.yaml", camera)
    again = load_calibration(tmp_path / "sensor.yaml").to_calibration()
    np.testing.assert_allclose(again.camera_intrinsics, camera.camera_intrinsics)
    np.testing.assert_allclose(again.uwb_offsets, camera.uwb_offsets)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d.pop("anchors"), r"calibration.yaml: anchors: missing field$"),
        (lambda d: d.update(version=2), r"version: expected 1, got 2$"),
        (lambda d: d.update(colour="red"), r"colour: unknown field$"),
        (
            lambda d: d.update(anchors=[[0.0, 1.0]]),
            r"anchors: expected shape \(k, 3\), got \(1, 2\)$",
        ),
        (lambda d: d["offsets"][0].__setitem__(1, 9.0), r"offsets: must be symmetric"),
        (lambda d: d.update(frame="lab"), r"frame: expected one of floor, known, anchors"),
        (lambda d: d["result"].pop("verdict"), r"result.verdict: missing field$"),
    ],
)
def test_bad_calibration_files(
    tmp_path: Path, calibrated: CalibrationResult, edit: Any, message: str
) -> None:
    import yaml

    path = tmp_path / "calibration.yaml"
    save_calibration(path, calibrated)
    doc = yaml.safe_load(path.read_text())
    edit(doc)
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(CalibrationFileError, match=message) as e:
        load_calibration(path)
    assert "\n" not in str(e.value)


def test_unreadable_calibration_files(tmp_path: Path) -> None:
    with pytest.raises(CalibrationFileError, match=r"missing\.yaml: cannot read"):
        load_calibration(tmp_path / "missing.yaml")
    (tmp_path / "bad.yaml").write_text("anchors: [1, 2\n")
    with pytest.raises(CalibrationFileError, match=r"bad\.yaml: not YAML"):
        load_calibration(tmp_path / "bad.yaml")


def test_normal_equations_match_finite_differences(
    three_bar: RobotDescription, run: tuple[list[UwbRangeSample], UwbModel]
) -> None:
    """The Levenberg-Marquardt gradient (Schur-eliminated structure) is the cost's."""
    samples, model = run
    d, config = three_bar, CalibrationConfig()
    t, i, j, m, index = sample_rows(samples[:300])
    table = range_table(t, i, j, m, n_nodes=6, n_anchors=8, round_gap=0.03, rounds=index)
    valid = table.valid_modules(4)
    rounds = np.flatnonzero(valid.any(axis=1))[:5]
    p = assemble(table, rounds, valid, d, gauge_mask(8), config).problem
    rng = np.random.default_rng(2)
    iu = np.triu_indices(6, 1)
    offsets = np.concatenate([model.offsets[6:, :6].ravel(), model.offsets[:6, :6][iu]])
    anchors = d.anchors + 0.01 * rng.standard_normal((8, 3))
    state = JointState(
        anchors, offsets + 0.01, 0.3, start_positions(p, anchors, offsets[:48]) + 0.01
    )
    p = with_contacts(p, state, 0.05)
    layout = lm._Layout.of(p)
    _, gl, _, _, gg = lm._accumulate(p.rows(state), layout, p, "soft_l1", 2.0)

    def cost(step_g: NDArray[np.float64], step_l: NDArray[np.float64]) -> float:
        return lm._cost(p.rows(p.moved(state, step_g, step_l)), "soft_l1", 2.0)

    eps, G, V = 1e-6, p.n_global, p.n_positions
    numeric = np.array([(cost(e, np.zeros((V, 3))) - cost(-e, np.zeros((V, 3)))) / (2 * eps)
                        for e in eps * np.eye(G)])  # fmt: skip
    np.testing.assert_allclose(gg, numeric, rtol=1e-5, atol=1e-4)
    local = gl.reshape(layout.n_samples, -1, 3)[p.position_sample, layout.local]
    e = np.zeros((V, 3))
    e[0, 2] = eps
    assert local[0, 2] == pytest.approx(
        (cost(np.zeros(G), e) - cost(np.zeros(G), -e)) / (2 * eps), rel=1e-5
    )


@pytest.mark.slow
def test_anchor_moved_during_calibration_is_flagged(
    three_bar: RobotDescription, roll: list[NDArray[np.float64]]
) -> None:
    half = len(roll) // 2
    first, _ = uwb_run(three_bar, roll[:half], seed=7)
    second, _ = uwb_run(three_bar, roll[half:], seed=7, move=(5, np.array([0.0, 0.3, 0.0])))
    shifted = [
        UwbRangeSample(s.t + half / RATE, s.times + half / RATE, s.pairs, s.ranges) for s in second
    ]
    result = calibrate_samples(
        first + shifted, three_bar, config=FAST, rng=np.random.default_rng(0)
    )
    assert 5 in result.flagged_anchors, result.verdict
    assert result.quality == "doubtful"


@pytest.mark.slow
@pytest.mark.parametrize("robot", ["three_bar", "superball"])
def test_simulated_calibration_run(robot: str) -> None:
    """The two-minute calibration run of the simulated robot under its gait (the one
    ``gym.make`` calibrates from), the description's packet loss: issue 15's figures
    (anchors within 2 cm after a rigid alignment, offsets within 1.5 cm), the robot's
    handedness, and every anchor above the floor."""
    from tensegrity_gym.envs.calibration_run import record_calibration_run

    d = load_robot(robot)
    run_ = record_calibration_run(d, world_seed=0)
    truth = run_.world
    result = calibrate_samples(run_.samples, d, rng=np.random.default_rng(0))
    R, shift = weighted_kabsch(result.anchors, truth.anchors, np.ones(len(truth.anchors)))
    assert rigid_alignment_rms(result.anchors, truth.anchors) <= 0.02
    assert np.linalg.det(R) > 0.0 and np.all(np.isfinite(shift))
    robot_anchor, robot_robot = offset_errors(result, truth.offsets, d.n_nodes)
    assert robot_anchor <= 0.015 and robot_robot <= 0.015
    assert result.anchors[:, 2].min() > 0.0, result.verdict
    assert len(run_.frames) >= 1150 and run_.frames[-1][1].shape == (d.n_nodes, 3)
