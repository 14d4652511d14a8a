"""``identify``: a robot's physical parameters fitted to a recorded run."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING

from agents.cli.arguments import Command, add_lab_map, count, positive_float, positive_int

if TYPE_CHECKING:
    import argparse

__all__ = ["COMMANDS"]


def add_identify(ide: argparse.ArgumentParser) -> None:
    """``identify``'s options: the bag, the parameters fitted, the model, the search."""
    from agents.identification.identify import GROUPS, MAX_EVALUATIONS, MODELS

    ide.add_argument("bag", help="a bag with commands, encoders and a trajectory")
    ide.add_argument("--out", required=True, help="the fitted robot description to write (YAML)")
    ide.add_argument(
        "--params", default="stiffness,damping,rest,friction,motor",
        help=f"comma-separated parameter groups, of {', '.join(sorted(GROUPS))} (mass "
        "only without stiffness and damping: the motion cannot tell them apart; geometry, "
        "a factor per rod length and passive rest length, instead of rest)",
    )  # fmt: skip
    ide.add_argument("--robot", default=None, help="start from this preset or YAML, not the bag's")
    ide.add_argument("--model", choices=sorted(MODELS), default="sim",
                     help="the simulator's physics, or the UKF's spring-mass model")  # fmt: skip
    ide.add_argument("--segment-seconds", type=positive_float, default=2.0,
                     help="length of a segment (at least one control period)")  # fmt: skip
    ide.add_argument("--max-evaluations", type=positive_int, default=MAX_EVALUATIONS,
                     help="the search's budget, in candidates scored on every IMU window "
                     "(half of it is spent first on a quarter of the windows, four "
                     "candidates to one)")  # fmt: skip
    ide.add_argument("--workers", type=positive_int, default=None,
                     help="processes (default: one per core)")  # fmt: skip
    ide.add_argument("--seed", type=count, default=0, help="seeds CMA-ES")
    ide.add_argument(
        "--imu-windows", type=count, default=300,
        help="periods at most (spread over the bag) whose IMU readings the fit compares "
        "with the replay's, each replayed from its recorded start; 0: fit the node "
        "positions over the segments instead (damping then weakly determined)",
    )  # fmt: skip
    add_lab_map(ide)


def run_identify(args: argparse.Namespace) -> int:
    """``identify``: fit the parameters; print what was written."""
    from agents.identification.report import identify_command
    from agents.recordings.importing import as_bag

    with as_bag(args.bag, args.lab_map, args.robot) as bag:
        result = identify_command(
            bag, Path(args.out), params=[p for p in args.params.split(",") if p],
            robot=args.robot, model=args.model, segment_seconds=args.segment_seconds,
            max_evaluations=args.max_evaluations, workers=args.workers, seed=args.seed,
            imu_windows=args.imu_windows,
        )  # fmt: skip
    sys.stdout.write(result + "\n")
    return 0


COMMANDS = (
    Command(
        "identify",
        "fit a robot's physical parameters to a recorded run (multiple shooting, CMA-ES)",
        add_identify,
        run_identify,
    ),
)
"""The subcommands of this module."""
