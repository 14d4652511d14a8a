"""Every subcommand turns a user's typical mistake into one line and exit status 2;
a traceback only with --verbose."""

from __future__ import annotations

import logging
import subprocess
import sys
from typing import TYPE_CHECKING

import pytest

from agents.cli import main

if TYPE_CHECKING:
    from pathlib import Path

MISTAKES = {
    "demo": ["demo", "--timesteps", "0"],
    "train": ["train", "--env", "tensegrity_gym/Nope-v0", "--out", "{tmp}/t"],
    "evaluate": ["evaluate", "{tmp}/no_run", "--out", "{tmp}/e"],
    "gait": ["gait", "--env", "tensegrity_gym/Nope-v0", "--out", "{tmp}/g"],
    "bench": ["bench", "--steps", "-3"],
    "bench --cross-world": ["bench", "--cross-world", "stiff", "--steps", "10"],
    "record": ["record", "--policy", "{tmp}/no_run", "--out", "{tmp}/r", "--steps", "2"],
    "estimate": ["estimate", "{tmp}/no_bag", "--out", "{tmp}/x"],
    "import": ["import", "{tmp}/no_logs", "--map", "{tmp}/no_map.yaml", "--out", "{tmp}/b"],
    "estimate --lab-map": [
        "estimate",
        "{tmp}/lab.bag",
        "--lab-map",
        "{tmp}/no_map.yaml",
        "--robot",
        "three_bar",
        "--out",
        "{tmp}/x",
    ],
    "emulate": ["emulate", "--robot", "{tmp}/no_robot.yaml"],
}


@pytest.mark.parametrize("command", sorted(MISTAKES))
def test_a_typical_mistake_is_one_line_and_exit_2(
    command: str, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    argv = [a.format(tmp=tmp_path) for a in MISTAKES[command]]
    by_argparse = False
    with caplog.at_level(logging.ERROR):
        try:
            code = main(argv)
        except SystemExit as exit_:  # argparse refuses a malformed option itself
            code, by_argparse = int(exit_.code or 0), True
    assert code == 2
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert by_argparse or len(errors) == 1, [r.getMessage() for r in errors]
    for record in errors:
        assert "\n" not in record.getMessage() and record.exc_info is None


@pytest.mark.parametrize(
    "argv", [["train", "--out", "{tmp}/t", "--ray", "local"], ["bench", "--ray", "local"]]
)
def test_ray_without_ray_says_how_to_install_it(
    argv: list[str],
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray fails, as when not installed
    with caplog.at_level(logging.ERROR):
        assert main([a.format(tmp=tmp_path) for a in argv]) == 2
    [error] = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert "pip install tensegrity-gym[ray]" in error and "\n" not in error


def test_verbose_shows_the_traceback(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.ERROR):
        code = main(["--verbose", "gait", "--env", "tensegrity_gym/Nope-v0"])
    assert code == 2
    assert any(r.exc_info is not None for r in caplog.records)


def test_the_installed_command_prints_no_traceback(tmp_path: Path) -> None:
    run = subprocess.run(
        [sys.executable, "-m", "agents.cli", "estimate", str(tmp_path / "none"), "--out",
         str(tmp_path / "x")],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert run.returncode == 2
    assert "Traceback" not in run.stderr
    lines = [ln for ln in run.stderr.splitlines() if ln.startswith("ERROR")]
    assert len(lines) == 1 and "no such file" in lines[0], run.stderr


def test_the_commands_are_listed_in_their_order() -> None:
    """The registry gives ``--help`` its subcommands in this order, each with a parser."""
    from agents.cli import COMMANDS, build_parser

    names = [c.name for c in COMMANDS]
    assert names == ["demo", "train", "evaluate", "gait", "bench", "record", "estimate",
                     "calibrate", "import", "view", "identify", "emulate"]  # fmt: skip
    parser = build_parser()
    for name in names:
        with pytest.raises(SystemExit) as exit_:
            parser.parse_args([name, "--help"])
        assert exit_.value.code == 0
