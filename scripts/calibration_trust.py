"""How the cached-calibration check (estimation.uwb_calibration.trust.range_fit) judges an
honest calibration on ranges from worlds it was not made in: the robot as built differs
from its description (a `Randomization` preset's draw: masses, stiffness, rest lengths,
friction, UWB noise and loss), beside the check on ranges of the robot as described.

    python scripts/calibration_trust.py --robot three_bar --worlds 0 1 2 --draws 3

Per world: a calibration from a run of --seconds under the nominal robot (as the env's
cache holds), then 3 s of fresh ranges (the check's length) from the nominal robot and
from --draws robots drawn from --randomization; prints the worst anchor's residual
against its allowance (mm) and whether the check passes. The check uses the nominal
description throughout, as the env does.
"""

from __future__ import annotations

import argparse

import numpy as np

from estimation.uwb_calibration.trust import range_fit
from tensegrity_gym.envs.calibration_run import (
    CHECK_SECONDS,
    _simulate,
    lab_calibration,
    record_calibration_run,
)
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.model.randomization import resolve_randomization


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robot", default="three_bar")
    parser.add_argument("--worlds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--draws", type=int, default=3)
    parser.add_argument("--randomization", default="strong")
    parser.add_argument("--seconds", type=float, default=120.0)
    args = parser.parse_args()
    nominal = load_robot(args.robot)
    ranges = resolve_randomization(args.randomization)
    assert ranges is not None
    print("world  robot        found mm  allowed mm  passes")
    for world in args.worlds:
        run = record_calibration_run(nominal, world_seed=world, seconds=args.seconds)
        cached = lab_calibration(run.samples, nominal, seed=world)
        robots = [("nominal", nominal)]
        draws = np.random.default_rng([world, 7])
        robots += [(f"draw {k}", ranges.draw(nominal, draws).robot) for k in range(args.draws)]
        for name, robot in robots:
            legs = np.random.default_rng([world, 11])
            fresh = _simulate(robot, world, CHECK_SECONDS, legs, 0.1, 0.001).samples
            fit = range_fit(cached, fresh, nominal)
            print(f"{world:5d}  {name:10s} {1e3 * fit.found:9.0f} {1e3 * fit.allowed:11.0f}"
                  f"  {fit.fits}")  # fmt: skip


if __name__ == "__main__":
    main()
