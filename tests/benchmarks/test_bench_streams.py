"""The stream-faults benchmark: each fault edits the stream it names, and only it, the
same way for the same seed, and the bench scores an estimator on each."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pytest

from agents.benchmarks.estimation import record_face_transition
from agents.benchmarks.streams import STREAM_FAULTS, StreamFault, _late, bench_streams, with_fault
from tensegrity_gym.model.lie import quat_conjugate, quat_multiply, quat_to_rotvec
from tensegrity_gym.model.samples import AhrsSample, EncoderSample, ImuSample, UwbRangeSample

if TYPE_CHECKING:
    from hardware.recording import RecordedRun


@pytest.fixture(scope="module")
def run() -> RecordedRun:
    return record_face_transition("tensegrity_gym/ThreeBarRoll-v0", 0, 20, calibration="true")


def _all(r: RecordedRun, kind: type) -> list:
    return [s for st in [r.start, *r.steps] for s in st.samples if isinstance(s, kind)]


def test_lost_readings_are_of_the_named_kind_and_the_same_for_the_same_seed(
    run: RecordedRun,
) -> None:
    lossy = with_fault(run, STREAM_FAULTS["imu_lost_fifth"], 3)
    share = 1.0 - len(_all(lossy, ImuSample)) / len(_all(run, ImuSample))
    assert 0.15 < share < 0.25, share
    for kind in (AhrsSample, EncoderSample, UwbRangeSample):
        assert len(_all(lossy, kind)) == len(_all(run, kind)), kind
    again = with_fault(run, STREAM_FAULTS["imu_lost_fifth"], 3)
    assert [s.t for s in _all(again, ImuSample)] == [s.t for s in _all(lossy, ImuSample)]
    assert len(_all(with_fault(run, STREAM_FAULTS["clean"], 3), ImuSample)) == len(
        _all(run, ImuSample)
    )
    # Every other reading of each rod, whatever the clock's origin (here off the 5 ms grid)
    later = with_fault(run, StreamFault("", _late((ImuSample,), 86_400.0025)), 0)
    for r in (run, later):
        half = with_fault(r, STREAM_FAULTS["imu_half_rate"], 0)
        for rod in (0, 1):
            t = [s.t for s in _all(r, ImuSample) if s.rod == rod]
            kept = [s.t for s in _all(half, ImuSample) if s.rod == rod]
            assert kept == t[::2], (rod, kept[:3], t[:3])


def test_late_biased_and_coarse_streams_are_edited_as_named(run: RecordedRun) -> None:
    late = with_fault(run, STREAM_FAULTS["imu_late"], 0)
    shift = [b.t - a.t for a, b in zip(_all(run, ImuSample), _all(late, ImuSample), strict=True)]
    np.testing.assert_allclose(shift, 0.01, atol=1e-12)
    enc = [b.t - a.t for a, b in zip(_all(run, EncoderSample), _all(late, EncoderSample),
                                    strict=True)]  # fmt: skip
    assert not np.any(enc)
    for st in late.steps:  # each step's samples still arrive in time order
        assert [s.t for s in st.samples] == sorted(s.t for s in st.samples)
    biased = with_fault(run, STREAM_FAULTS["imu_bias"], 0)
    a, b = _all(run, ImuSample)[0], _all(biased, ImuSample)[0]
    np.testing.assert_allclose(b.gyro - a.gyro, [0.02, -0.015, 0.01])
    coarse = _all(with_fault(run, STREAM_FAULTS["encoders_coarse"], 0), EncoderSample)[-1]
    np.testing.assert_allclose(coarse.rest_lengths * 1000.0, np.round(coarse.rest_lengths * 1000.0))
    assert np.any(coarse.rest_lengths != _all(run, EncoderSample)[-1].rest_lengths)


def test_a_heading_off_one_rod_turns_that_rods_ahrs_about_the_vertical(run: RecordedRun) -> None:
    turned = with_fault(run, STREAM_FAULTS["heading_off_one_rod"], 0)
    for before, after in zip(_all(run, AhrsSample), _all(turned, AhrsSample), strict=True):
        turn = quat_to_rotvec(quat_multiply(after.quaternion, quat_conjugate(before.quaternion)))
        expected = [0.0, 0.0, np.radians(30.0)] if before.rod == 1 else [0.0, 0.0, 0.0]
        np.testing.assert_allclose(turn, expected, atol=1e-9)


def test_ranges_through_a_body_are_a_tenth_and_long(run: RecordedRun) -> None:
    through = with_fault(run, STREAM_FAULTS["uwb_through_a_body"], 5)
    added = np.concatenate([b.ranges - a.ranges for a, b in
                            zip(_all(run, UwbRangeSample), _all(through, UwbRangeSample),
                                strict=True)])  # fmt: skip
    assert set(np.round(added, 9)) <= {0.0, 0.3}
    assert 0.05 < np.mean(added > 0) < 0.15


def test_the_bench_refuses_an_unknown_fault_before_recording_anything() -> None:
    with pytest.raises(ValueError, match=r"unknown stream fault 'imu_lost'; choose from \["):
        bench_streams(("ukf",), ("imu_lost",), seeds=(0,), steps=5)


@pytest.mark.slow  # two recorded runs and four replays, 8 s: the default run is near 15 min
def test_the_bench_scores_each_fault() -> None:
    result = bench_streams(("ukf",), ("clean", "uwb_sparse"), seeds=(0,), steps=30)
    rows = result["rows"]["ukf"]
    assert set(rows) == {"clean", "uwb_sparse"} and rows["clean"]["runs"] == 2
    for fault, row in rows.items():
        assert all(np.isfinite(v) for v in row["mean"].values()), (fault, row["mean"])
        assert row["mean"]["com_rmse_m"] < 0.05, (fault, row["mean"])
    assert result["faults"]["uwb_sparse"] == "four in five UWB rounds lost"
