"""Faults of the UWB calibration's cache, files and arguments (issue 39): a cached
calibration is checked against the scene and against fresh ranges before it is used,
and recalibrated (logged) where it does not fit; a path or an argument that would
fail is refused in one line before any run; nothing half-written is left behind.

The honest cache is a short calibration run (15 s: seconds, not minutes); where a
test makes the calibrator run again, its result is that honest one, so that only the
decision and the files are tested here (the calibrator's own tests are elsewhere).
"""

from __future__ import annotations

import logging
import math
import os
import re
import shutil
from dataclasses import replace
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
import pytest

import tensegrity_gym  # noqa: F401  (registers the envs)
import tensegrity_gym.envs.calibration_run as calibration_run
from estimation.uwb_calibration import (
    CalibrationFileError,
    load_calibration,
    save_calibration,
)
from estimation.uwb_calibration.trust import scene_mismatch
from tensegrity_gym.envs.calibration import CACHE_VARIABLE, cache_path, load_uwb_calibration
from tensegrity_gym.model.description import load_robot

if TYPE_CHECKING:
    from collections.abc import Iterator
    from pathlib import Path

    from estimation.uwb_calibration import CalibrationFile
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import UwbCalibration

ENV_ID = "tensegrity_gym/ThreeBarRoll-v0"
SECONDS = 15.0  # a short calibration run: enough samples (about 75 of 60), 3 s to make
WORLD = 0


@pytest.fixture(scope="module")
def three_bar() -> RobotDescription:
    return load_robot("three_bar")


@pytest.fixture(scope="module")
def honest(tmp_path_factory: pytest.TempPathFactory, three_bar: RobotDescription) -> Path:
    """A cache file the calibration run made in world 0 (a module's own cache folder)."""
    root = tmp_path_factory.mktemp("honest_cache")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(CACHE_VARIABLE, str(root))
        calibration_run.estimated_uwb_calibration(three_bar, world_seed=WORLD, seconds=SECONDS)
        return cache_path(three_bar, WORLD, SECONDS)


@pytest.fixture
def cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, three_bar: RobotDescription) -> Path:
    """This test's cache folder (empty) and the path the world-0 calibration takes."""
    monkeypatch.setenv(CACHE_VARIABLE, str(tmp_path / "cache"))
    return cache_path(three_bar, WORLD, SECONDS)


@pytest.fixture
def recalibrations(monkeypatch: pytest.MonkeyPatch, honest: Path) -> Iterator[list[int]]:
    """Counts the calibration runs made; each gives the honest calibration back."""
    made: list[int] = []
    result = load_calibration(honest).result
    assert result is not None

    def run(*args: Any, **kwargs: Any) -> SimpleNamespace:
        made.append(1)
        return SimpleNamespace(samples=[])

    monkeypatch.setattr(calibration_run, "record_calibration_run", run)
    monkeypatch.setattr(calibration_run, "lab_calibration", lambda *a: result)
    yield made


def _cache_with(path: Path, honest: Path, **fields: Any) -> CalibrationFile:
    """``honest``'s calibration with ``fields`` (anchors, offsets) replaced, at ``path``."""
    file = load_calibration(honest)
    assert file.result is not None
    changed = replace(file.result, **fields)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_calibration(path, changed, robot=file.robot)
    return file


def _recalibrated(
    three_bar: RobotDescription, caplog: pytest.LogCaptureFixture, recalibrations: list[int]
) -> tuple[UwbCalibration, str]:
    """The calibration the env gets over the cache, and the one warning it logged, after
    asserting that it calibrated once again."""
    with caplog.at_level(logging.WARNING):
        used = calibration_run.estimated_uwb_calibration(
            three_bar, world_seed=WORLD, seconds=SECONDS
        )
    assert recalibrations == [1]
    [warning] = _warnings(caplog)
    return used, warning


def _warnings(caplog: pytest.LogCaptureFixture) -> list[str]:
    """The cache's warnings (the short honest run's verdict, doubtful, is another)."""
    return [
        r.getMessage()
        for r in caplog.records
        if r.levelno == logging.WARNING and r.getMessage().startswith("calibration cache")
    ]


# --------------------------------------------------------------- 1: checked before use


def test_an_honest_cache_is_used_as_it_is(
    cache: Path,
    honest: Path,
    recalibrations: list[int],
    three_bar: RobotDescription,
    caplog: pytest.LogCaptureFixture,
) -> None:
    cache.parent.mkdir(parents=True)
    shutil.copy(honest, cache)
    with caplog.at_level(logging.INFO):
        used = calibration_run.estimated_uwb_calibration(
            three_bar, world_seed=WORLD, seconds=SECONDS
        )
    assert recalibrations == [] and _warnings(caplog) == []
    np.testing.assert_array_equal(used.anchors, load_calibration(honest).anchors)
    assert any("fits the first 3 s of ranges" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("shift", [5.0, 0.1], ids=["5 m", "10 cm"])
def test_a_cache_with_its_offsets_shifted_is_recalibrated_and_says_so(
    shift: float,
    cache: Path,
    honest: Path,
    recalibrations: list[int],
    three_bar: RobotDescription,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Well formed, the right counts, anchors on the floor plan: only the ranges tell
    that every robot-anchor offset is ``shift`` m off."""
    n = three_bar.n_nodes
    offsets = load_calibration(honest).offsets.copy()
    offsets[n:, :n] += shift
    offsets[:n, n:] += shift
    file = _cache_with(cache, honest, offsets=offsets)
    used, warning = _recalibrated(three_bar, caplog, recalibrations)
    assert str(cache) in warning and "does not fit the first 3 s of ranges" in warning
    assert "mm, at most 60 mm allowed" in warning and "calibrating again" in warning
    np.testing.assert_array_equal(used.uwb_offsets, file.offsets)
    np.testing.assert_array_equal(load_calibration(cache).offsets, file.offsets)  # rewritten


def test_a_shifted_cache_cannot_widen_its_own_allowance(
    cache: Path,
    honest: Path,
    recalibrations: list[int],
    three_bar: RobotDescription,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The allowance comes from the file's own statistics: an edited spread (infinite)
    counts for at most OWN_RESIDUAL_MOST times the ranging noise."""
    n = three_bar.n_nodes
    honest_file = load_calibration(honest)
    assert honest_file.result is not None
    offsets = honest_file.offsets.copy()
    offsets[n:, :n] += 5.0
    offsets[:n, n:] += 5.0
    stats = tuple(replace(s, spread=math.inf) for s in honest_file.result.anchor_stats)
    _cache_with(cache, honest, offsets=offsets, anchor_stats=stats)
    _, warning = _recalibrated(three_bar, caplog, recalibrations)
    assert "at most 240 mm allowed" in warning, warning


@pytest.mark.parametrize(
    ("move", "reason"),
    [
        (np.array([5.0, 0.0, 0.0]), r"anchor \d stands [45]\.\d\d m from the layout's"),
        (np.array([0.0, 0.0, -5.0]), r"anchor \d stands [45]\.\d\d m from the layout's"),
    ],
    ids=["5 m along x", "5 m down"],
)
def test_a_cache_with_its_anchors_shifted_is_recalibrated_and_says_so(
    move: np.ndarray,
    reason: str,
    cache: Path,
    honest: Path,
    recalibrations: list[int],
    three_bar: RobotDescription,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Every anchor moved alike: ranges alone cannot tell (the robot moves with them);
    the floor plan can."""
    file = _cache_with(cache, honest, anchors=load_calibration(honest).anchors + move)
    used, warning = _recalibrated(three_bar, caplog, recalibrations)
    assert str(cache) in warning
    assert re.search(reason, warning), warning
    np.testing.assert_array_equal(used.anchors, file.anchors)


@pytest.mark.parametrize("world", [1, 2])
def test_honest_caches_pass_in_other_worlds(
    world: int,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    three_bar: RobotDescription,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """No spurious recalibration: a calibration made in a world fits that world's fresh
    ranges (each world draws its own anchors, offsets and clock drift)."""
    monkeypatch.setenv(CACHE_VARIABLE, str(tmp_path))
    first = calibration_run.estimated_uwb_calibration(three_bar, world_seed=world, seconds=12.0)
    monkeypatch.setattr(calibration_run, "lab_calibration", _must_not_run)
    with caplog.at_level(logging.WARNING):
        again = calibration_run.estimated_uwb_calibration(three_bar, world_seed=world, seconds=12.0)
    assert _warnings(caplog) == []
    np.testing.assert_array_equal(first.anchors, again.anchors)


def _must_not_run(*args: Any, **kwargs: Any) -> Any:
    raise AssertionError("a calibration run was made")


@pytest.mark.slow
@pytest.mark.parametrize(("robot", "world"), [("three_bar", 1), ("superball", 0)])
def test_the_default_caches_pass_their_check(
    robot: str, world: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The full 120 s calibration, read back in a new process (the check runs once per
    process and file): used, not made again."""
    d = load_robot(robot)
    monkeypatch.setenv(CACHE_VARIABLE, str(tmp_path))
    first = calibration_run.estimated_uwb_calibration(d, world_seed=world)
    monkeypatch.setattr(calibration_run, "_CHECKED", {})
    monkeypatch.setattr(calibration_run, "lab_calibration", _must_not_run)
    again = calibration_run.estimated_uwb_calibration(d, world_seed=world)
    np.testing.assert_array_equal(first.uwb_offsets, again.uwb_offsets)


# ------------------------------------------------------------ 2: another scene's file


def _four_anchors(path: Path, honest: Path, three_bar: RobotDescription) -> None:
    """``honest`` cut to its first 4 anchors (a well-formed file of another scene)."""
    file = load_calibration(honest)
    keep = list(range(three_bar.n_nodes + 4))
    lab = file.to_calibration()
    lab = replace(lab, anchors=file.anchors[:4], uwb_offsets=file.offsets[np.ix_(keep, keep)])
    path.parent.mkdir(parents=True, exist_ok=True)
    save_calibration(path, lab, robot=three_bar.name)


def test_a_cache_with_another_anchor_count_is_recalibrated_and_says_so(
    cache: Path,
    honest: Path,
    recalibrations: list[int],
    three_bar: RobotDescription,
    caplog: pytest.LogCaptureFixture,
) -> None:
    _four_anchors(cache, honest, three_bar)
    used, warning = _recalibrated(three_bar, caplog, recalibrations)
    assert str(cache) in warning
    assert "it has 4 anchors and 10 UWB modules, robot 'three_bar' has 8 and 14" in warning
    assert used.anchors.shape == (8, 3)


def test_a_cache_of_another_robot_is_recalibrated(
    cache: Path,
    honest: Path,
    recalibrations: list[int],
    three_bar: RobotDescription,
    caplog: pytest.LogCaptureFixture,
) -> None:
    file = load_calibration(honest)
    assert file.result is not None
    cache.parent.mkdir(parents=True)
    save_calibration(cache, file.result, robot="superball")
    _, warning = _recalibrated(three_bar, caplog, recalibrations)
    assert str(cache) in warning and "made for robot 'superball', not 'three_bar'" in warning


def test_a_calibration_file_of_another_scene_is_refused_at_make(
    tmp_path: Path, honest: Path, three_bar: RobotDescription
) -> None:
    """A file cannot be made again: one line naming it, at make, not at the first reset."""
    path = tmp_path / "lab.yaml"
    _four_anchors(path, honest, three_bar)
    message = r"make: calibration=.*lab\.yaml.*not this robot's: it has 4 anchors"
    with pytest.raises(ValueError, match=message) as e:
        gym.make(ENV_ID, estimator="oracle", calibration=path)
    assert "\n" not in str(e.value)


# ------------------------------------------------------ 3: paths, before any run


def test_a_cache_file_that_is_a_folder_is_refused_at_make(
    cache: Path, monkeypatch: pytest.MonkeyPatch, three_bar: RobotDescription
) -> None:
    default = cache_path(three_bar, WORLD, calibration_run.CALIBRATION_SECONDS)
    default.mkdir(parents=True)
    with pytest.raises(ValueError, match=r"calibration cache .* is a folder") as e:
        gym.make(ENV_ID, estimator="oracle")
    message = str(e.value)
    assert str(default) in message and f"${CACHE_VARIABLE}=" in message and "\n" not in message
    # Called directly (a bench), it refuses before any run as well.
    monkeypatch.setattr(calibration_run, "_simulate", _must_not_run)
    monkeypatch.setattr(calibration_run, "record_calibration_run", _must_not_run)
    with pytest.raises(ValueError, match=r"is a folder"):
        calibration_run.estimated_uwb_calibration(three_bar, world_seed=WORLD)


def test_a_cache_folder_under_a_file_is_refused_at_make(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("")
    monkeypatch.setenv(CACHE_VARIABLE, str(blocker / "cache"))
    with pytest.raises(ValueError, match=r"not_a_folder is a file, not a folder") as e:
        gym.make(ENV_ID, estimator="oracle")
    assert f"${CACHE_VARIABLE}={blocker / 'cache'}" in str(e.value)


@pytest.mark.parametrize("where", ["folder", "under a file"])
def test_calibrate_out_is_checked_before_the_run(
    where: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    import agents.recordings.calibrate
    from agents.cli import main

    if where == "folder":
        out = tmp_path / "out.yaml"
        out.mkdir()
    else:
        (tmp_path / "file").write_text("")
        out = tmp_path / "file" / "out.yaml"
    monkeypatch.setattr(agents.recordings.calibrate, "record_calibration_run", _must_not_run)
    with caplog.at_level(logging.ERROR):
        assert main(["calibrate", "--env", ENV_ID, "--out", str(out)]) == 2
    [error] = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert error.startswith(f"calibrate: --out {str(out)!r}")
    assert ("is a folder" if where == "folder" else "is a file, not a folder") in error
    assert not list(tmp_path.rglob("*.part"))


def test_a_failed_write_leaves_nothing_behind(tmp_path: Path, honest: Path) -> None:
    target = tmp_path / "taken"
    target.mkdir()
    (target / "inside").write_text("")  # a folder that os.replace cannot replace
    result = load_calibration(honest).result
    assert result is not None
    with pytest.raises(CalibrationFileError, match=r"taken: cannot write"):
        save_calibration(target, result)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken"]


def test_a_recalibration_that_cannot_write_leaves_no_part_file(
    cache: Path,
    honest: Path,
    recalibrations: list[int],
    three_bar: RobotDescription,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _cache_with(cache, honest, offsets=load_calibration(honest).offsets + 5.0)

    def full_disk(src: object, dst: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", full_disk)
    with pytest.raises(CalibrationFileError, match=r"cannot write: No space left on device"):
        calibration_run.estimated_uwb_calibration(three_bar, world_seed=WORLD, seconds=SECONDS)
    assert not list(cache.parent.glob("*.part"))


# ------------------------------------------------------------ 4: not a calibration


@pytest.mark.parametrize(
    ("content", "what"),
    [
        (b"\x89PNG\r\n\x1a\n\x00\xb3\x01", r"binary \(byte 0x89 at offset 0 is not UTF-8 text\)"),
        (b"", "empty"),
        (b"- 1\n- 2\n", "a YAML list, not a mapping"),
        (b"name: three_bar\nrods: []\n", "no 'version' field"),
    ],
    ids=["binary", "empty", "list", "robot yaml"],
)
def test_not_a_calibration_file_is_one_line_naming_the_argument(
    content: bytes, what: str, tmp_path: Path
) -> None:
    from agents.recordings.offline import estimate_bag

    path = tmp_path / "calibration.bin"
    path.write_bytes(content)
    expected = rf"calibration='.*calibration\.bin': not a calibration file: {what}; "
    with pytest.raises(ValueError, match=r"make: " + expected) as e:
        gym.make(ENV_ID, estimator="oracle", calibration=path)
    assert "\n" not in str(e.value)
    with pytest.raises(CalibrationFileError, match=r"^" + expected):
        load_uwb_calibration(path)
    # estimate --calibration: refused before any bag is opened.
    with pytest.raises(CalibrationFileError, match=r"^--" + expected):
        estimate_bag(tmp_path / "no_bag", "ukf", tmp_path / "out", calibration=path)


# -------------------------------------------------------------- 5: the run's length


@pytest.mark.parametrize("seconds", [math.nan, math.inf, 0, -5, 11.9, 1e9, True, "120"])
def test_seconds_out_of_range_is_one_line_naming_it_and_the_range(
    seconds: object, three_bar: RobotDescription, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(calibration_run, "_simulate", _must_not_run)
    message = rf"seconds={re.escape(repr(seconds))} must be a number of seconds in \[12, 3600\]"
    with pytest.raises(ValueError, match=r"^calibrate: " + message):
        calibration_run.check_seconds(seconds)
    with pytest.raises(ValueError, match=r"^record_calibration_run: " + message):
        calibration_run.record_calibration_run(three_bar, world_seed=0, seconds=seconds)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"^make: " + message):
        calibration_run.estimated_uwb_calibration(three_bar, seconds=seconds)  # type: ignore[arg-type]


def test_the_least_and_most_seconds(three_bar: RobotDescription) -> None:
    assert calibration_run.min_seconds(three_bar) == 12.0  # 60 samples of 0.2 s at 15 Hz
    slow = replace(three_bar, sensors=replace(three_bar.sensors, uwb=replace(
        three_bar.sensors.uwb, rate=2.0)))  # fmt: skip
    assert calibration_run.min_seconds(slow) == 30.0  # a sample per round: 60 rounds
    assert calibration_run.check_seconds(12) == 12.0
    assert calibration_run.check_seconds(3600.0) == 3600.0


@pytest.mark.parametrize("seconds", ["nan", "0", "-5", "1e9"])
def test_calibrate_seconds_is_refused_by_name_before_the_run(
    seconds: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
    capsys: pytest.CaptureFixture[str],
) -> None:
    import agents.recordings.calibrate
    from agents.cli import main

    monkeypatch.setattr(agents.recordings.calibrate, "record_calibration_run", _must_not_run)
    out = tmp_path / "lab.yaml"
    argv = ["calibrate", "--env", ENV_ID, "--seconds", seconds, "--out", str(out)]
    with caplog.at_level(logging.ERROR):
        try:
            code = main(argv)
        except SystemExit as exit_:  # should the flag's argparse type refuse it itself
            code = int(exit_.code or 0)
            error = capsys.readouterr().err.strip().splitlines()[-1]
        else:
            [error] = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert code == 2 and "seconds" in error, error  # the range: see the API's tests
    assert not out.exists()


def test_a_run_lasts_the_seconds_asked(three_bar: RobotDescription) -> None:
    """Legs of 10 s, the last one shorter: 12 s is 12 s of ranging (it was one 10 s leg,
    too short for the 60 samples the calibrator needs)."""
    run = calibration_run.record_calibration_run(three_bar, world_seed=0, seconds=12.0)
    steps = len(run.frames) - 2  # each leg's reset adds its start
    assert steps == 120
    legs = {round(t // 20) for t, _ in run.frames}
    assert legs == {0, 1}


def test_scene_mismatch_names_what_differs(three_bar: RobotDescription, honest: Path) -> None:
    file = load_calibration(honest)
    assert scene_mismatch(file, three_bar) is None
    assert scene_mismatch(file, three_bar, robot="three_bar") is None
    moved = replace(file, anchors=file.anchors + np.array([0.0, 0.6, 0.0]))
    assert re.search(r"anchor \d stands 0\.\d\d m from the layout's \(sensors\.uwb\.anchors\[\d\]",
                     str(scene_mismatch(moved, three_bar)))  # fmt: skip
    assert scene_mismatch(moved, three_bar, layout_tolerance=None) is None


@pytest.mark.parametrize("world_seed", [-1, 1.5, True])
def test_a_bad_world_seed_is_refused_before_the_run(
    world_seed: object, tmp_path: Path, three_bar: RobotDescription
) -> None:
    from agents.recordings.calibrate import calibrate_command

    with pytest.raises(ValueError, match=rf"^calibrate: world_seed={world_seed!r} must be"):
        calibrate_command(
            bag=None, env_id=ENV_ID, seconds=120.0, world_seed=world_seed,  # type: ignore[arg-type]
            robot=None, out=tmp_path / "lab.yaml",
        )  # fmt: skip
    with pytest.raises(ValueError, match=rf"^make: world_seed={world_seed!r} must be"):
        calibration_run.estimated_uwb_calibration(three_bar, world_seed=world_seed)  # type: ignore[arg-type]
