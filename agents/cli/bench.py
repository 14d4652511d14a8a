"""``bench``: the env's speed and memory, and the optional studies, as JSON."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from agents.cli.arguments import (
    Command,
    add_engine,
    add_ray,
    count,
    non_negative_float,
    positive_int,
)

if TYPE_CHECKING:
    import argparse

__all__ = ["COMMANDS"]


def add_bench(bench: argparse.ArgumentParser) -> None:
    """``bench``'s options: the steps of each measurement (0 skips one), the studies
    (:func:`_add_studies`), the engine, Ray and the output file."""
    bench.add_argument("--steps", type=positive_int, default=2000, help="env steps timed per env")
    bench.add_argument(
        "--memory-steps",
        type=count,
        default=100_000,
        help="env steps of the memory test (0: skip)",
    )
    bench.add_argument(
        "--bag-minutes",
        type=non_negative_float,
        default=10.0,
        help="minutes of 3-bar recording whose reading and replay are timed (0: skip)",
    )
    bench.add_argument(
        "--link-steps",
        type=count,
        default=300,
        help="10 Hz steps of the robot-link latency test against the emulator (0: skip)",
    )
    bench.add_argument(
        "--soak-minutes",
        type=non_negative_float,
        default=0.0,
        help="minutes of emulated operation watched for memory and latency growth",
    )
    _add_studies(bench)
    add_engine(bench)
    add_ray(bench, "measure the Ray vec env (the JSON's ray) and run --estimation's jobs as tasks")
    bench.add_argument("--out", default=None, help="also write the JSON to this file")


def _add_studies(bench: argparse.ArgumentParser) -> None:
    """``bench``'s optional studies, each run only when asked for."""
    bench.add_argument(
        "--estimation",
        action="store_true",
        help="also run the estimation study (Caluwaerts et al. 2016 on SUPERball), the UKF's "
        "speed against filterpy's, the ICP tracker's figures and Tong et al. 2024's table "
        "(the invariant EKF on the 1.45 m robot, beside the UKF)",
    )
    bench.add_argument(
        "--sim2real",
        action="store_true",
        help="also run the UKF in randomised worlds (none, mild, strong) and the "
        "identification of a 3-bar robot recorded 30 %% off its description",
    )
    bench.add_argument(
        "--engines",
        action="store_true",
        help="also compare the physics engines: MuJoCo's env against its bare mj_step and "
        "against PyBullet's, with the oracle and the UKF (needs tensegrity-gym[mujoco])",
    )
    bench.add_argument(
        "--cross-world",
        nargs="*",
        default=None,
        metavar="WORLD",
        help="also score every estimator on worlds it was not tuned in (other_engine, "
        "description_error, stiff_contacts), 3 seeds, rolling and turning; name worlds to "
        "score only those beside own (needs tensegrity-gym[mujoco])",
    )
    bench.add_argument(
        "--cross-world-estimators",
        nargs="+",
        default=None,
        metavar="ESTIMATOR",
        help="the estimators --cross-world scores (default: ukf, ukf_exact_lengths, "
        "ukf_large, inekf, icp)",
    )
    bench.add_argument(
        "--streams",
        action="store_true",
        help="also score the UKF and the invariant EKF on sensor streams as a lab's robot "
        "gives them: readings lost, late, jittered, biased, coarse; headings disturbed; "
        "UWB ranges through a body or lost (3 seeds, rolling and turning)",
    )
    bench.add_argument(
        "--lab-calibration",
        action="store_true",
        help="also calibrate the UWB anchors at a lab's conditions: SUPERball carried through "
        "a 10 x 15 m room, 1-3 Hz pairs, no robot-robot ranges, a 4 m common offset",
    )
    bench.add_argument(
        "--training",
        action="store_true",
        help="also time PPO and SAC training with the UKF in the loop (4,096 steps each): "
        "env steps/s and the shares of physics, sensors, estimator and policy update",
    )


def run_bench(args: argparse.Namespace) -> int:
    """``bench``: run the benchmarks; print their JSON (and write it to ``--out``)."""
    from agents.benchmarks.suite import run_benchmarks

    results = run_benchmarks(
        speed_steps=args.steps,
        memory_steps=args.memory_steps,
        estimation=args.estimation,
        bag_minutes=args.bag_minutes,
        link_steps=args.link_steps,
        soak_minutes=args.soak_minutes,
        sim2real=args.sim2real,
        ray_address=args.ray,
        engines=args.engines,
        engine=args.engine,
        cross_world=_cross_world(args),
        streams=args.streams,
        lab_calibration=args.lab_calibration,
        training=args.training,
    )
    text = json.dumps(results, indent=2)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text + "\n")
    sys.stdout.write(text + "\n")
    return 0


def _cross_world(args: argparse.Namespace) -> dict[str, tuple[str, ...]] | bool:
    """``bench_cross_world``'s arguments from ``--cross-world`` and its estimators: the
    named worlds with the own one (every world where none is named); False without it.
    An unknown world or estimator is refused before any benchmark runs."""
    from agents.benchmarks.cross_world import ESTIMATOR_ROBOTS, WORLDS

    if args.cross_world is None:
        if args.cross_world_estimators is not None:
            raise ValueError("--cross-world-estimators needs --cross-world")
        return False
    for flag, names, known in (("--cross-world", args.cross_world, WORLDS),
                               ("--cross-world-estimators", args.cross_world_estimators or (),
                                ESTIMATOR_ROBOTS)):  # fmt: skip
        unknown = [n for n in names if n not in known]
        if unknown:
            raise ValueError(f"{flag}: unknown {unknown[0]!r}; choose from {', '.join(known)}")
    worlds = tuple(WORLDS) if not args.cross_world else ("own", *args.cross_world)
    chosen: dict[str, tuple[str, ...]] = {"worlds": tuple(dict.fromkeys(worlds))}
    if args.cross_world_estimators is not None:
        chosen["estimators"] = tuple(dict.fromkeys(args.cross_world_estimators))
    return chosen


COMMANDS = (Command("bench", "measure env speed and memory; print JSON", add_bench, run_bench),)
"""The subcommands of this module, in ``--help``'s order."""
