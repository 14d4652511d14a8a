"""A lab's UWB ranges file in (hardware.lab.ranges): CSV and NPZ, id maps, units, errors,
and ``tensegrity-gym calibrate FILE``."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest

from estimation.uwb_calibration.rounds import sample_rows
from hardware.lab import LabFileError, load_id_map, read_ranges, write_ranges
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.sim.carried import LabRanging, carried_recording

if TYPE_CHECKING:
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.sim.carried import CarriedRecording

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "lab"


@pytest.fixture(scope="module")
def superball() -> RobotDescription:
    return load_robot("superball")


@pytest.fixture(scope="module")
def short(superball: RobotDescription) -> CarriedRecording:
    ranging = LabRanging(robot_ranging=True)  # robot-robot rows go through the file too
    return carried_recording(superball, np.random.default_rng(5), seconds=20.0, ranging=ranging)


@pytest.mark.parametrize("suffix", [".csv", ".npz"])
def test_a_recording_round_trips_bit_for_bit(
    tmp_path: Path, superball: RobotDescription, short: CarriedRecording, suffix: str
) -> None:
    path = tmp_path / f"ranges{suffix}"
    write_ranges(path, short.uwb, superball.n_nodes)
    rows = read_ranges(path, superball)
    t, i, j, m, _ = sample_rows(short.uwb)
    order = np.argsort(t, kind="stable")
    np.testing.assert_array_equal(rows.t, t[order])  # the recording starts at 0 s
    np.testing.assert_array_equal(rows.ranges, m[order])
    pairs = np.sort(np.column_stack([i, j])[order], axis=1)
    np.testing.assert_array_equal(np.sort(np.column_stack([rows.module_i, rows.module_j]), axis=1),
                                  pairs)  # fmt: skip
    again = rows.samples()
    assert sum(len(s.times) for s in again) == len(t)


def test_lab_ids_names_units_and_clock(tmp_path: Path, superball: RobotDescription) -> None:
    """Lab ids (text), endcaps by name, anchors by index, ms and mm, an epoch clock."""
    (tmp_path / "ids.yaml").write_text(
        'nodes: {"0x1A": n0, "0x1B": 1}\nanchors: {"101": 0, "102": 7}\n'
        "units: {time: ms, range: mm}\n"
    )
    (tmp_path / "r.csv").write_text(
        "range,anchor,t,node,rssi\n"
        "5123.0,101,1465000000250.0,0x1A,-80\n"
        "6000.5,102,1465000000100.0,0x1B,-81\n"
        "7000.0,999,1465000000300.0,0x1B,-82\n"
    )
    ids = load_id_map(tmp_path / "ids.yaml", superball)
    rows = read_ranges(tmp_path / "r.csv", superball, ids)
    assert rows.clock_origin_ns == 1_465_000_000 * 10**9
    assert rows.t.tolist() == [0.1, 0.25]  # ms on an epoch clock, to the nanosecond
    np.testing.assert_allclose(rows.ranges, [6.0005, 5.123])
    np.testing.assert_array_equal(rows.module_i, [1, 0])
    np.testing.assert_array_equal(rows.module_j, [12 + 7, 12 + 0])


@pytest.mark.parametrize(
    ("name", "text", "match"),
    [
        ("r.csv", "t,node,range\n1,0,2\n", r"r\.csv: line 1: no column 'anchor'"),
        ("r.csv", "t,node,anchor,range\n1,0,12,abc\n",
         r"r\.csv: line 2: range 'abc' is not a number"),
        ("r.csv", "t,node,anchor,range\n1,0\n", r"r\.csv: line 2: 2 fields, the header has 4"),
        ("r.csv", "t,node,anchor,range\n1,70,80,2\n", r"no row names two modules the id map knows"),
        ("r.txt", "t,node,anchor,range\n", r"r\.txt: a ranges file is \.csv or \.npz"),
        ("r.npz", "not a zip", r"r\.npz: not an NPZ ranges file"),
    ],
)  # fmt: skip
def test_bad_ranges_files_are_one_line(
    tmp_path: Path, superball: RobotDescription, name: str, text: str, match: str
) -> None:
    (tmp_path / name).write_text(text)
    with pytest.raises(LabFileError, match=match) as e:
        read_ranges(tmp_path / name, superball)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("nodes: {}\n", r"a mapping with 'nodes' and 'anchors'"),
        ("nodes: {a: n99}\nanchors: {}\n", r"nodes\.a: 'n99' is not one of superball's endcaps"),
        ("nodes: {}\nanchors: {b: 8}\n", r"anchors\.b: 8 is not one of superball's 8 anchors"),
        ("nodes: {}\nanchors: {}\nunits: {time: h}\n", r"units\.time: 'h' is not one of s, ms"),
        ("nodes: {}\nanchors: {}\nextra: 1\n", r"extra: unknown field"),
        ("nodes: {a: 0}\nanchors: {a: 0}\n", r"anchors\.a: the lab id is named twice"),
    ],
)  # fmt: skip
def test_bad_id_maps_are_one_line(
    tmp_path: Path, superball: RobotDescription, text: str, match: str
) -> None:
    (tmp_path / "ids.yaml").write_text(text)
    with pytest.raises(LabFileError, match=match):
        load_id_map(tmp_path / "ids.yaml", superball)


def test_the_example_file_reads(superball: RobotDescription) -> None:
    ids = load_id_map(EXAMPLE / "ids.yaml", superball)
    rows = read_ranges(EXAMPLE / "ranges.csv", superball, ids)
    assert len(rows.t) > 1000 and np.all(np.diff(rows.t) >= 0)
    assert set(np.unique(rows.module_i)) <= set(range(12))
    assert set(np.unique(rows.module_j)) <= set(range(12, 20))


@pytest.mark.slow  # 32-35 s on a fresh clone; the default run is at its 15 minutes
def test_calibrate_a_ranges_file_from_the_command_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    from agents.cli import main
    from estimation.uwb_calibration import load_calibration

    out = tmp_path / "lab.yaml"
    ranges, ids = str(EXAMPLE / "ranges.csv"), str(EXAMPLE / "ids.yaml")
    with caplog.at_level(logging.ERROR):
        assert main(["calibrate", ranges, "--ids", ids, "--out", str(out)]) == 2  # no --robot
        assert main(["calibrate", ranges, "--ids", ids, "--robot", "superball",
                     "--floor", "0=x", "--out", str(out)]) == 2  # fmt: skip
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 2 and all("\n" not in e for e in errors)
    assert "name its robot" in errors[0]
    assert "floor hint: cannot read '0=x'" in errors[1]
    assert not out.exists()
    assert main(["calibrate", ranges, "--ids", ids, "--robot", "superball",
                 "--floor", "0=4.7 4=0.4 5=1.1", "--out", str(out)]) == 0  # fmt: skip
    assert "verdict:" in capsys.readouterr().out
    saved = load_calibration(out)
    assert saved.anchors.shape == (8, 3) and saved.frame == "floor"
    assert saved.result is not None and saved.result.floor == "hint"
