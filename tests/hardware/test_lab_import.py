"""A lab's recording in (hardware.lab.importer, ``tensegrity-gym import``): a simulated
recording written out as a lab's CSV logs and ranges file, imported back as a bag, gives
the same samples and the same estimates as the bag it came from."""

from __future__ import annotations

from typing import TYPE_CHECKING

import gymnasium as gym
import numpy as np
import pytest

import tensegrity_gym  # noqa: F401  (registers the envs)
from hardware.bag.reader import BagReader
from hardware.lab import LabFileError, import_recording, load_lab_map, write_logs
from tensegrity_gym.model.samples import RgbdFrame

if TYPE_CHECKING:
    from pathlib import Path

    from tensegrity_gym.model.samples import Sample

ENV_ID = "tensegrity_gym/ThreeBarRoll-v0"


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """40 random steps of the 3-bar robot recorded to a bag."""
    root = tmp_path_factory.mktemp("lab_import")
    env = gym.make(ENV_ID, estimator="oracle", calibration="true", record_dir=root / "runs")
    env.reset(seed=0)
    for _ in range(40):
        env.step(env.action_space.sample())
    env.close()
    return root / "runs" / "episode_000"


def _contents(bag: Path) -> tuple[list[Sample], list[tuple[float, np.ndarray]], BagReader]:
    """A bag's samples (RGB-D left out), its commands with their times, its reader."""
    with BagReader(bag) as reader:
        periods = list(reader.periods())
    samples = [s for p in periods for s in p.samples if not isinstance(s, RgbdFrame)]
    commands = [(periods[k - 1].t_end, p.command) for k, p in enumerate(periods) if k > 0]
    return samples, commands, reader  # type: ignore[return-value]


@pytest.fixture(scope="module")
def exported(recorded: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The recording as a lab's files: CSV logs per kind, a ranges file, a map."""
    samples, commands, reader = _contents(recorded)
    folder = tmp_path_factory.mktemp("logs")
    write_logs(folder, samples, reader.description, clock_origin_ns=reader.clock_origin_ns,
               commands=commands)  # fmt: skip
    return folder


@pytest.fixture(scope="module")
def imported(recorded: Path, exported: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    with BagReader(recorded) as reader:
        d, calibration = reader.description, reader.calibration
    out = tmp_path_factory.mktemp("imported") / "bag"
    summary = import_recording([exported], load_lab_map(exported / "map.yaml"), d, calibration, out)
    assert summary["command_source"] == "recorded" and summary["control_period"] == 0.1
    return out


def test_the_files_round_trip_to_the_same_samples(recorded: Path, imported: Path) -> None:
    before, commands_before, r0 = _contents(recorded)
    after, commands_after, r1 = _contents(imported)
    assert r1.clock_origin_ns == r0.clock_origin_ns
    key = lambda s: (s.t, type(s).__name__, getattr(s, "rod", -1))  # noqa: E731
    before, after = sorted(before, key=key), sorted(after, key=key)
    assert [type(s) for s in after] == [type(s) for s in before]
    for a, b in zip(after, before, strict=True):
        assert repr(a) == repr(b)  # every field, bit for bit
    assert len(commands_after) == len(commands_before)
    for (ta, ca), (tb, cb) in zip(commands_after, commands_before, strict=True):
        assert ta == tb and np.array_equal(ca, cb)


def test_the_imported_bag_estimates_as_the_original(
    recorded: Path, imported: Path, tmp_path: Path
) -> None:
    from agents.recordings.offline import estimate_bag

    estimate_bag(recorded, "ukf", tmp_path / "a", progress=False)
    estimate_bag(imported, "ukf", tmp_path / "b", progress=False)
    a, b = np.load(tmp_path / "a" / "estimates.npz"), np.load(tmp_path / "b" / "estimates.npz")
    assert set(a.files) == set(b.files)
    for name in a.files:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def test_without_commands_the_encoders_are_held(
    recorded: Path, exported: Path, tmp_path: Path
) -> None:
    with BagReader(recorded) as reader:
        d, calibration = reader.description, reader.calibration
    lab_map = load_lab_map(exported / "map.yaml")
    files = [exported / name for name in lab_map.files if name != "commands.csv"]
    summary = import_recording(files, lab_map, d, calibration, tmp_path / "bag")
    assert summary["command_source"] == "encoders held"
    samples, commands, _ = _contents(tmp_path / "bag")
    encoders = [s for s in samples if type(s).__name__ == "EncoderSample"]
    t, held = commands[5]
    last = [s for s in encoders if s.t <= t][-1]
    assert np.array_equal(held, last.rest_lengths)


@pytest.mark.parametrize(
    ("doc", "match"),
    [
        ("files: {}\n", r"a lab map is a mapping with 'files'"),
        ("files: {a.csv: {kind: sonar}}\n", r"files\.a\.csv\.kind: 'sonar' is not one of imu"),
        ("files: {a.csv: {kind: imu, unit: {}}}\n", r"files\.a\.csv\.unit: unknown field"),
        ("files: {a.csv: {kind: imu}}\nrobots: x\n", r"robots: unknown field"),
    ],
)  # fmt: skip
def test_bad_lab_maps_are_one_line(tmp_path: Path, doc: str, match: str) -> None:
    (tmp_path / "map.yaml").write_text(doc)
    with pytest.raises(LabFileError, match=match):
        load_lab_map(tmp_path / "map.yaml")


def test_bad_logs_are_one_line(exported: Path, tmp_path: Path, recorded: Path) -> None:
    with BagReader(recorded) as reader:
        d, calibration = reader.description, reader.calibration
    (tmp_path / "imu.csv").write_text("t,rod,ax,ay,az,gx,gy,gz\n1,red,0,0,9.8,0,0,x\n")
    (tmp_path / "map.yaml").write_text("files: {imu.csv: {kind: imu, units: {gyro: rpm}}}\n")
    lab_map = load_lab_map(tmp_path / "map.yaml")
    with pytest.raises(LabFileError, match=r"imu\.csv: units\.gyro: 'rpm' is not one of"):
        import_recording([tmp_path / "imu.csv"], lab_map, d, calibration, tmp_path / "b1")
    (tmp_path / "map.yaml").write_text("files: {imu.csv: {kind: imu}}\n")
    lab_map = load_lab_map(tmp_path / "map.yaml")
    with pytest.raises(LabFileError, match=r"imu\.csv: line 2: gz 'x' is not a number"):
        import_recording([tmp_path / "imu.csv"], lab_map, d, calibration, tmp_path / "b2")
    with pytest.raises(LabFileError, match=r"other\.csv: not one of the files"):
        import_recording([tmp_path / "other.csv"], lab_map, d, calibration, tmp_path / "b3")


def test_import_from_the_command_line(exported: Path, tmp_path: Path) -> None:
    from agents.cli import main

    out = tmp_path / "bag"
    assert main(["import", str(exported), "--out", str(out)]) == 0
    with BagReader(out) as reader:
        assert reader.description.name == "three_bar"
        assert reader.run_info["commands"] == "recorded"
    assert main(["import", str(exported), "--out", str(out)]) == 2  # exists
