"""The UWB self-calibration on worlds it was not tuned in: the MuJoCo engine, and a robot
departing from its description (``randomization="description"``, world draw 0), the
calibrator keeping the nominal description. Prints one JSON line.

    python scripts/calibration_other_worlds.py ROBOT mujoco|description
"""

from __future__ import annotations

import json
import sys

import numpy as np

from agents.benchmarks.calibration import _errors
from tensegrity_gym.envs.calibration_run import lab_calibration, record_calibration_run
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.model.randomization import resolve_randomization


def main() -> None:
    robot, world = sys.argv[1], sys.argv[2]
    d = load_robot(robot)
    if world == "mujoco":
        run = record_calibration_run(d, world_seed=0, seconds=120.0, engine="mujoco")
    else:
        randomization = resolve_randomization("description")
        assert randomization is not None
        drawn = randomization.draw(d, np.random.default_rng(0)).robot
        run = record_calibration_run(drawn, world_seed=0, seconds=120.0)
    result = lab_calibration(run.samples, d, 0)
    sys.stdout.write(json.dumps({"robot": robot, "world": world, **_errors(result, run)}) + "\n")


if __name__ == "__main__":
    main()
