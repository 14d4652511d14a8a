"""UWB self-calibration at the conditions real labs have (issue: a lab's own recordings).

The recordings are simulated to have them (:mod:`tensegrity_gym.sim.carried`): SUPERball
carried by hand through a 10 x 15 m room with anchors up to 4.7 m high, each
endcap-anchor pair ranged at 1-3 Hz with 30 % lost, no robot-robot ranging, every
offset near a common 4 m, 1 % multipath. Nothing about the truth is handed over.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
import pytest

from estimation.uwb_calibration import calibrate_samples, rigid_alignment_rms
from estimation.uwb_calibration.floor import parse_floor_hint
from estimation.uwb_calibration.geometry import (
    floor_frame_errors,
    rigid_alignment_errors,
    tilt_degrees,
)
from estimation.uwb_calibration.rounds import (
    at_sample_times,
    local_rates,
    merge_rounds,
    range_table,
    sample_rows,
)
from estimation.uwb_calibration.timing import fitted_to_rates
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.sim.carried import LAB_ROOM, LabRanging, carried_recording
from tests.estimation.test_uwb_calibration import FAST, roll_frames, uwb_run

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from estimation.uwb_calibration import CalibrationResult
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.sim.carried import CarriedRecording

pytestmark = pytest.mark.xdist_group("lab_calibration")  # the recording's fixtures, once

SECONDS = 150.0
HEIGHTS = {a: xyz[2] for a, xyz in enumerate(LAB_ROOM)}


@pytest.fixture(scope="module")
def superball() -> RobotDescription:
    return load_robot("superball")


@pytest.fixture(scope="module")
def carried(superball: RobotDescription) -> CarriedRecording:
    return carried_recording(superball, np.random.default_rng(3), seconds=SECONDS, imu_rate=50.0)


@pytest.fixture(scope="module")
def with_imu(superball: RobotDescription, carried: CarriedRecording) -> CalibrationResult:
    return calibrate_samples(carried.uwb + carried.imu, superball, floor_hint="0=4.7")


def test_carried_robot_with_imu_and_one_height(
    with_imu: CalibrationResult, carried: CarriedRecording
) -> None:
    """The issue's target: anchors within 10 cm, the floor within 2 degrees, from
    1-3 Hz pairs, no robot-robot ranges, a 4 m common offset, a carried robot."""
    r = with_imu
    assert r.floor == "gravity+hint" and r.frame == "floor"
    assert np.max(rigid_alignment_errors(r.anchors, carried.anchors)) <= 0.10
    assert tilt_degrees(r.anchors, carried.anchors) <= 2.0
    # In the floor frame, the tilt's share added: 0.5 deg is 13 cm over the room.
    assert np.max(floor_frame_errors(r.anchors, carried.anchors)) <= 0.20
    assert abs(r.mean_offset - 4.0) <= 0.05  # found from the data, not assumed 0
    assert r.extras["sample_period"] > 0.3  # lengthened for 1-3 Hz pairs
    assert np.count_nonzero(r.robot_pair_count) == 0
    assert "floor" not in r.verdict  # the floor is settled: no doubt about it


@pytest.mark.slow  # a recording and solve of its own; the bench's 1 Hz case covers it too
def test_carried_robot_ranged_at_one_hz_per_pair(superball: RobotDescription) -> None:
    """The issue's slowest ranging, every pair at exactly 1 Hz: a sample lasts about
    1 s, over which the carried robot moves some 30 cm; the ranges moved to their
    sample's time keep the anchors within 10 cm."""
    ranging = replace(LabRanging(), pair_rate=(1.0, 1.0))
    rec = carried_recording(superball, np.random.default_rng(0), seconds=180.0, ranging=ranging)
    r = calibrate_samples(rec.uwb + rec.imu, superball, floor_hint="0=4.7")
    assert r.floor == "gravity+hint"
    assert r.extras["sample_period"] > 0.8
    assert np.max(rigid_alignment_errors(r.anchors, rec.anchors)) <= 0.10
    assert tilt_degrees(r.anchors, rec.anchors) <= 2.0


@pytest.mark.slow  # a third solve of the recording: the bench's cases cover it too
def test_carried_robot_with_imu_alone_says_the_height_is_a_guess(
    superball: RobotDescription, carried: CarriedRecording
) -> None:
    r = calibrate_samples(carried.uwb + carried.imu, superball)
    assert r.floor == "gravity"
    assert tilt_degrees(r.anchors, carried.anchors) <= 2.0
    assert "the floor's height is a guess" in r.verdict and "0=4.7" in r.verdict


@pytest.mark.slow  # a fourth solve: the bench's three-heights case covers it too
def test_carried_robot_with_a_height_hint_alone(
    superball: RobotDescription, carried: CarriedRecording
) -> None:
    """No IMU: three tape-measured anchor heights give the floor (of the two tilts
    three heights leave, the one with the robot and the anchors above the floor)."""
    hint = " ".join(f"{a}={HEIGHTS[a]}" for a in (0, 4, 5))
    r = calibrate_samples(carried.uwb, superball, floor_hint=hint)
    assert r.floor == "hint"
    assert tilt_degrees(r.anchors, carried.anchors) <= 2.0
    assert np.max(floor_frame_errors(r.anchors, carried.anchors)) <= 0.15


@pytest.mark.slow  # a second solve of the recording; the verdict's words are checked below
def test_carried_robot_without_imu_or_hint_says_what_to_give(
    superball: RobotDescription, carried: CarriedRecording
) -> None:
    r = calibrate_samples(carried.uwb, superball)
    assert r.floor == "none" and r.frame == "anchors"
    assert r.quality == "doubtful"
    assert "the floor cannot be told from ranges alone" in r.verdict
    assert "floor hint" in r.verdict
    # The constellation itself is still right, whatever its frame.
    assert rigid_alignment_rms(r.anchors, carried.anchors) <= 0.05


def test_rolled_robot_without_robot_robot_ranges(superball: RobotDescription) -> None:
    """A rolled robot whose modules never range each other: the offsets are then per
    robot-anchor pair only, the floor still the one it rests on."""
    d = load_robot("three_bar")
    frames = roll_frames(d, np.random.default_rng(1), 120.0, radius=1.2)
    samples, model = uwb_run(d, frames, seed=7)
    anchors_only = []
    for s in samples:
        keep = np.any(np.asarray(s.pairs) >= d.n_nodes, axis=1)
        anchors_only.append(replace(s, times=s.times[keep], pairs=s.pairs[keep],
                                    ranges=s.ranges[keep]))  # fmt: skip
    r = calibrate_samples(anchors_only, d, config=FAST, rng=np.random.default_rng(0))
    assert r.floor == "contacts"
    assert rigid_alignment_rms(r.anchors, model.anchors) <= 0.03
    assert np.count_nonzero(r.robot_pair_count) == 0


def test_time_constants_follow_the_rates(
    superball: RobotDescription, carried: CarriedRecording
) -> None:
    """1-3 Hz pairs lengthen the samples and the start's window; 15 Hz rounds keep
    the settings' defaults."""
    t, i, j, m, index = sample_rows(carried.uwb)
    table = range_table(t, i, j, m, n_nodes=12, n_anchors=8, round_gap=0.05, rounds=index)
    fitted, rates = fitted_to_rates(FAST, table, 8)
    assert 1.0 <= rates.pair <= 3.0 * 0.8  # 1-3 Hz drawn, 30 % lost
    assert 0.3 <= fitted.sample_period <= 1.0
    assert fitted.window >= fitted.sample_period
    assert fitted.first_span >= 10 * fitted.sample_period
    d = load_robot("three_bar")
    samples, _ = uwb_run(d, roll_frames(d, np.random.default_rng(2), 20.0, radius=1.0), seed=3)
    t, i, j, m, index = sample_rows(samples)
    table = range_table(t, i, j, m, n_nodes=6, n_anchors=8, round_gap=0.03, rounds=index)
    fitted, _ = fitted_to_rates(FAST, table, 8)
    assert fitted.sample_period == FAST.sample_period and fitted.window == FAST.window
    assert fitted.rate_span == FAST.rate_span


def _slopes_one_by_one(pair: NDArray[np.intp], t: NDArray[np.float64],
                       m: NDArray[np.float64], span: float,
                       fit: NDArray[np.bool_]) -> NDArray[np.float64]:  # fmt: skip
    """The reference: np.polyfit over each row's window, row by row."""
    out = np.zeros(len(m))
    for k in range(len(m)):
        near = (pair == pair[k]) & (np.abs(t - t[k]) <= span) & fit
        if len(np.unique(t[near])) >= 2:
            out[k] = np.polyfit(t[near] - t[k], m[near], 1)[0]
    return out


def test_local_rates_match_a_row_by_row_fit() -> None:
    """The vectorised rate fit equals a per-row least-squares line, outliers left out."""
    rng = np.random.default_rng(4)
    k = 400
    pair = rng.integers(0, 7, k)
    t = np.sort(rng.uniform(0.0, 30.0, k))
    m = 3.0 + 0.2 * np.sin(t + pair) + rng.normal(0.0, 0.03, k)
    fit = rng.random(k) > 0.1
    fast = local_rates(pair, t, m, 1.3, fit)
    np.testing.assert_allclose(fast, _slopes_one_by_one(pair, t, m, 1.3, fit), atol=1e-9)


def test_ranges_move_to_their_samples_time() -> None:
    """A pair whose range grows 0.4 m/s, ranged about once a second and pooled into
    1 s samples: each range is moved to its sample's time; a multipath range (left
    out of the fit) bends no rate."""
    rng = np.random.default_rng(5)
    t = np.arange(0.0, 20.0, 0.9) + rng.uniform(0.0, 0.1, 23)
    m = 5.0 + 0.4 * t
    m[10] += 1.0  # a reflected path
    i, j = np.full(len(t), 6 + 2), np.full(len(t), 1)  # anchor 2, module 1
    table = merge_rounds(range_table(t, i, j, m, n_nodes=6, n_anchors=4, round_gap=0.01), 1.0)
    good = np.arange(len(t)) != 10
    moved = at_sample_times(table, 1.5, (good, np.zeros(0, dtype=bool)))
    sample_t = table.round_times[table.a_round]
    assert np.max(np.abs(sample_t - t)) > 0.3  # the samples pool ranges far apart
    np.testing.assert_allclose(moved.a_range[good], 5.0 + 0.4 * sample_t[good], atol=1e-9)
    np.testing.assert_allclose(moved.a_time, sample_t)
    assert abs(moved.a_range[10] - (6.0 + 0.4 * sample_t[10])) < 1e-9
    bent = at_sample_times(table, 1.5)  # the outlier in the fit: its neighbours move off
    assert np.max(np.abs(bent.a_range[good] - moved.a_range[good])) > 0.01


@pytest.mark.parametrize(
    ("text", "heights"),
    [("0=4.7 1=4.5", {0: 4.7, 1: 4.5}), ("0,1,2,3=4.6", dict.fromkeys(range(4), 4.6)),
     ("2=.5;3=-0.1", {2: 0.5, 3: -0.1}), ("ccw=0,1,2", {})],
)  # fmt: skip
def test_floor_hints_read(text: str, heights: dict[int, float]) -> None:
    assert dict(parse_floor_hint(text).heights) == heights


@pytest.mark.parametrize("text", ["", "0=x", "a=1", "0:4.7", "0=4.7 =2", "ccw=0,1", "ccw=1,1,2"])
def test_bad_floor_hints_are_one_line(text: str) -> None:
    with pytest.raises(ValueError, match=r"^floor hint: ") as e:
        parse_floor_hint(text)
    assert "\n" not in str(e.value)


def test_a_hint_naming_an_anchor_the_robot_lacks_is_one_line(
    superball: RobotDescription, carried: CarriedRecording
) -> None:
    with pytest.raises(ValueError, match=r"anchor 9 is not one of the description's 8 anchors"):
        calibrate_samples(carried.uwb[:50], superball, floor_hint="9=1.0")


def test_a_counterclockwise_hint_settles_an_undecided_handedness(
    with_imu: CalibrationResult, carried: CarriedRecording
) -> None:
    """Where the robot's shape cannot tell the constellation from its mirror image, three
    anchors the lab knows turn counter-clockwise seen from above do; where the shape can
    and the hint disagrees, the verdict says so."""
    from estimation.uwb_calibration.calibrate import _handed
    from estimation.uwb_calibration.config import CalibrationConfig
    from estimation.uwb_calibration.verdict import judge

    mirrored = replace(with_imu, anchors=with_imu.anchors * [1.0, -1.0, 1.0], mirror="undecided")
    assert "give three anchors counter-clockwise" in judge(mirrored, CalibrationConfig())[0]
    settled = _handed(mirrored, parse_floor_hint("ccw=0,1,2"))
    assert settled.mirror == "hint"
    np.testing.assert_allclose(settled.anchors, with_imu.anchors)
    assert np.max(rigid_alignment_errors(settled.anchors, carried.anchors)) <= 0.10
    disagreed = _handed(with_imu, parse_floor_hint("ccw=0,2,1"))
    assert disagreed.mirror == with_imu.mirror
    assert "turn the other way" in judge(disagreed, CalibrationConfig())[0]


def test_a_result_without_a_floor_says_what_to_give(with_imu: CalibrationResult) -> None:
    """The verdict of a carried robot's result with no floor source (neither IMU nor
    hint): the floor cannot be told, and which hint tells it."""
    from estimation.uwb_calibration.config import CalibrationConfig
    from estimation.uwb_calibration.verdict import judge

    none = replace(with_imu, floor="none", frame="anchors")
    verdict = judge(none, CalibrationConfig())[0]
    assert verdict.startswith("doubtful: ")
    assert "the floor cannot be told from ranges alone" in verdict and "floor hint" in verdict


@pytest.mark.parametrize(
    "hint", ["0=4.7 4=0.4 5=1.1", "0=4.7 1=4.5 2=4.6 3=4.4", "1=4.5 6=0.5 7=2.3"]
)
def test_anchor_heights_tell_the_floor_in_any_frame(hint: str, carried: CarriedRecording) -> None:
    """Three (or coplanar) anchor heights leave two mirror-image floors; the one with no
    anchor under it is found, from the truth turned every way (no solve: fast)."""
    from estimation.uwb_calibration.floor import floor_from_hint
    from tensegrity_gym.model.lie import so3_exp

    rng = np.random.default_rng(0)
    modules = carried.nodes.reshape(-1, 3)
    for _ in range(20):
        R = so3_exp(rng.normal(0.0, 2.0, 3))
        shift = rng.normal(0.0, 3.0, 3)
        found = floor_from_hint(carried.anchors @ R.T + shift, parse_floor_hint(hint),
                                modules @ R.T + shift)  # fmt: skip
        assert found is not None
        up, height, misfit = found
        assert np.degrees(np.arccos(np.clip(up @ (R @ [0.0, 0.0, 1.0]), -1, 1))) < 0.5
        assert abs(height + up @ shift) < 0.05 and misfit < 0.1


def test_gravity_along_the_true_rod_axes_gives_up(
    superball: RobotDescription, carried: CarriedRecording
) -> None:
    """The accelerometers' share of the floor's error: with the true module positions
    (no solve), the rods' axial readings give up within 0.1 degrees, so that what the
    calibration loses is the solve's rod axes, not the readings."""
    from estimation.uwb_calibration.floor import GravityRows, floor_from_gravity
    from tensegrity_gym.model.kinematics import uwb_module_positions

    imu = carried.imu
    gravity = GravityRows(np.array([s.t for s in imu]), np.array([s.rod for s in imu]),
                          np.array([s.accel for s in imu]))  # fmt: skip
    modules = uwb_module_positions(superball, carried.nodes)  # (T, n, 3)
    slot = np.arange(modules.shape[0] * modules.shape[1]).reshape(modules.shape[:2])
    found = floor_from_gravity(modules.reshape(-1, 3), slot, carried.times, gravity, superball,
                               0.25)  # fmt: skip
    assert found is not None
    assert np.degrees(np.arccos(np.clip(found[0][2], -1.0, 1.0))) < 0.1
