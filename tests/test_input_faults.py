"""Faults a hostile but fair user found (terrain, command-line flags, bags, make's
arguments, dropped envs): each gives one line that names what is wrong and where, or
the right result, instead of a crash, a traceback or a silent wrong answer."""

from __future__ import annotations

import gc
import json
import logging
from typing import TYPE_CHECKING

import gymnasium as gym
import numpy as np
import pybullet
import pytest
import yaml

import tensegrity_gym  # noqa: F401  (registers the ids)
from agents.cli import main
from tensegrity_gym.model.description import DescriptionError, load_robot
from tensegrity_gym.model.randomization import Randomization
from tensegrity_gym.sim.terrain import MAX_SLOPE, Terrain
from tensegrity_gym.sim.world import MAX_HEIGHTFIELD_POINTS
from tests.fault_matrix import absurd_ranges, robot_bag

if TYPE_CHECKING:
    from pathlib import Path

ENV = "tensegrity_gym/ThreeBarRoll-v0"


def run_cli(argv: list[str], caplog: pytest.LogCaptureFixture) -> tuple[int, str]:
    """Exit status and the one error line of ``tensegrity-gym argv`` (argparse's own
    refusals included, from its usage message on stderr)."""
    caplog.clear()
    with caplog.at_level(logging.ERROR):
        try:
            code = main(argv)
        except SystemExit as exit_:
            return int(exit_.code or 0), "argparse"
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) <= 1, errors
    assert all("\n" not in e for e in errors), errors
    return code, errors[0] if errors else ""


# ---------------------------------------------------------------------- terrain


def _height_map(folder: Path, heights: np.ndarray, **sidecar: object) -> Path:
    path = folder / "map.npy"
    np.save(path, heights)
    (folder / "map.yaml").write_text(yaml.safe_dump({"cell_size": 0.1, **sidecar}))
    return path


def test_a_terrain_pybullet_cannot_hold_is_refused_at_make_with_the_limit() -> None:
    # 3000 x 3000 crashed the process with SIGSEGV at reset.
    side = int(np.ceil(np.sqrt(MAX_HEIGHTFIELD_POINTS))) + 1
    big = Terrain(np.zeros((side, side)), 0.01, name="big")
    with pytest.raises(ValueError, match=r"^make: terrain 'big' has .* at most 4,194,304"):
        gym.make(ENV, terrain=big)


def test_a_nan_terrain_origin_is_refused_by_name(tmp_path: Path) -> None:
    path = _height_map(tmp_path, np.zeros((4, 4)), origin=[float("nan"), float("nan")])
    with pytest.raises(ValueError, match=r"map\.npy'?: origin=\[nan, nan\] must be two finite"):
        gym.make(ENV, terrain=str(path))
    with pytest.raises(ValueError, match="origin"):
        Terrain(np.zeros((3, 3)), 1.0, (float("nan"), 0.0))
    with pytest.raises(ValueError, match="origin"):
        Terrain(np.zeros((3, 3)), 1.0, (0.0,))  # type: ignore[arg-type]


def test_a_mis_scaled_height_map_is_refused_naming_height_scale(tmp_path: Path) -> None:
    # height_scale=1e6 used to end in a SettleError blaming "0 UWB ranges".
    heights = np.random.default_rng(0).random((20, 20))
    path = _height_map(tmp_path, heights, height_scale=1e6)
    with pytest.raises(ValueError, match=r"steeper than 100 .*height_scale"):
        gym.make(ENV, terrain=str(path))
    # The same map at a sane scale is taken.
    path = _height_map(tmp_path, heights, height_scale=0.05)
    gym.make(ENV, terrain=str(path)).close()


def test_the_built_terrains_are_within_the_slope_limit() -> None:
    from tensegrity_gym.sim.terrain import TERRAINS

    d = load_robot("three_bar")
    for name in TERRAINS.names():
        terrain = TERRAINS[name](d, np.random.default_rng(0))
        assert terrain.steepest_slope < MAX_SLOPE / 10, name


# ---------------------------------------------------------------------- flags


@pytest.mark.parametrize(
    ("argv", "flag"),
    [
        (["view", "--port", "70000"], "--port"),
        (["view", "--port", "-1"], "--port"),
        (["view", "--speed", "nan"], "--speed"),
        (["identify", "{tmp}/bag", "--out", "{tmp}/o.yaml", "--segment-seconds", "0"],
         "--segment-seconds"),
        (["identify", "{tmp}/bag", "--out", "{tmp}/o.yaml", "--segment-seconds", "nan"],
         "--segment-seconds"),
        (["record", "--out", "{tmp}/r", "--seed", "-1"], "--seed"),
        (["bench", "--bag-minutes", "inf"], "--bag-minutes"),
    ],
)  # fmt: skip
def test_a_flag_out_of_its_range_is_refused_naming_it(
    argv: list[str], flag: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_:
        main([a.format(tmp=tmp_path) for a in argv])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"argument {flag}" in err and "Traceback" not in err


def test_make_refuses_a_viewer_port_out_of_range() -> None:
    with pytest.raises(ValueError, match=r"^make: viewer_port=70000 must be a whole number in"):
        gym.make(ENV, viewer_port=70000)
    with pytest.raises(ValueError, match=r"^make: viewer_speed=nan"):
        gym.make(ENV, viewer_speed=float("nan"))


def test_identify_refuses_segments_shorter_than_a_period() -> None:
    from agents.identification.identify import IdentifyError, identify_run
    from hardware.recording import RecordedRun, RecordedStep, hold_command

    d = load_robot("three_bar")
    run = RecordedRun(d, None, RecordedStep([], hold_command(d), None), [], 0.1)  # type: ignore[arg-type]
    with pytest.raises(IdentifyError, match=r"segment_seconds \(--segment-seconds\) = 0.05"):
        identify_run(run, ["stiffness"], segment_seconds=0.05)


# ---------------------------------------------------------------------- make's arguments


def test_randomization_takes_numpy_float32_bounds() -> None:
    lo, hi = np.float32(0.9), np.float32(1.1)
    r = Randomization(rod_mass=(lo, hi), friction=np.array([0.8, 1.2], dtype=np.float32))
    assert r.rod_mass == (float(lo), float(hi)) and isinstance(r.rod_mass[0], float)
    assert r.friction == (float(np.float32(0.8)), float(np.float32(1.2)))
    hash(r)  # still a frozen, hashable value
    with pytest.raises(ValueError, match=r"rod_mass=\(nan, 1.0\): low and high must be finite"):
        Randomization(rod_mass=(float("nan"), 1.0))
    with pytest.raises(ValueError, match=r"rod_mass=\(True, 1\): low and high must be numbers"):
        Randomization(rod_mass=(True, 1))  # type: ignore[arg-type]


def test_a_broken_description_yaml_is_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "robot.yaml"
    bad.write_text("name: x\nrods: [\n  - {a: 1\n")
    with pytest.raises(DescriptionError) as err:
        load_robot(bad)
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"{bad}: not valid YAML: line 3, column 3")
    binary = tmp_path / "robot2.yaml"
    binary.write_bytes(b"\xb3\x00\xff")
    with pytest.raises(DescriptionError, match=r"not UTF-8 text \(byte 0xb3 at offset 0\)$"):
        load_robot(binary)


# ---------------------------------------------------------------------- bags


def test_a_bag_without_commands_names_the_missing_topic(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    bag = robot_bag(tmp_path / "no_commands", commands=False)
    code, error = run_cli(["estimate", str(bag), "--out", str(tmp_path / "e"), "--no-progress"],
                          caplog)  # fmt: skip
    assert code == 2
    assert "no /commands/rest_length_targets messages" in error, error


def test_absurd_uwb_ranges_are_counted_as_rejected(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    bag = robot_bag(tmp_path / "absurd", edit=absurd_ranges)
    out = tmp_path / "e"
    code, error = run_cli(["estimate", str(bag), "--out", str(out), "--no-progress"], caplog)
    assert code == 0, error
    metrics = json.loads((out / "metrics.json").read_text())
    rejected = metrics["estimator_rejected"]
    assert rejected.get("uwb_range_negative", 0) > 0, rejected
    assert rejected.get("uwb_range_too_long", 0) > 0, rejected
    clean = robot_bag(tmp_path / "clean")
    code, _ = run_cli(["estimate", str(clean), "--out", str(tmp_path / "c"), "--no-progress"],
                      caplog)  # fmt: skip
    assert code == 0
    assert json.loads((tmp_path / "c" / "metrics.json").read_text())["estimator_rejected"] == {}


# ---------------------------------------------------------------------- leaks


def _connected(client: int) -> bool:
    return bool(pybullet.getConnectionInfo(physicsClientId=client)["isConnected"])


def test_an_env_dropped_without_close_releases_its_simulator() -> None:
    clients = []
    for seed in range(3):
        env = gym.make(ENV, render_mode="rgb_array")
        env.reset(seed=seed)
        env.render()  # the floor's own client too
        world = env.unwrapped.backend.world  # type: ignore[attr-defined]
        clients += [world.client, world._floor_client]
        assert all(c >= 0 and _connected(c) for c in clients[-2:])
        del env, world
        gc.collect()
        assert not any(_connected(c) for c in clients)


def test_estimate_refuses_an_out_path_it_cannot_write_before_any_bag(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    bag = robot_bag(tmp_path / "bag")
    for out, says in ((a_file, "is a file, not a folder"), (a_file / "x", "is a file, not")):
        code, error = run_cli(["estimate", str(bag), "--out", str(out), "--no-progress"], caplog)
        assert code == 2 and f"--out '{out}'" in error and says in error, error
