"""``record``, ``estimate``, ``calibrate`` and ``view``: runs written to bags, estimators
run over them, the UWB calibration and the live view."""

from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from agents.cli.arguments import (
    Command,
    add_engine,
    add_lab_map,
    add_randomization,
    add_ray,
    calibration_seconds,
    count,
    env_help,
    non_negative_float,
    port,
    positive_float,
    positive_int,
)
from agents.cli.errors import log, one_line, terminate

if TYPE_CHECKING:
    from tensegrity_gym.model.description import RobotDescription

__all__ = ["COMMANDS"]


def add_record(rec: argparse.ArgumentParser) -> None:
    """``record``'s options: the env, the policy, the episodes, the robot."""
    from tensegrity_gym.model.registry import ESTIMATORS

    rec.add_argument("--env", default="tensegrity_gym/ThreeBarRoll-v0", help=env_help())
    rec.add_argument(
        "--policy",
        default="scripted",
        help="scripted (the robot's face gait), random, or a training run folder (from train)",
    )
    rec.add_argument("--episodes", type=positive_int, default=1, help="episodes (bags)")
    rec.add_argument("--steps", type=positive_int, default=None, help="control steps per episode")
    rec.add_argument("--seed", type=count, default=0, help="episode k uses seed + k")
    rec.add_argument("--estimator", default="ukf", choices=list(ESTIMATORS.names()),
                     help="the estimator run (and recorded) in the loop")  # fmt: skip
    rec.add_argument("--driver", default=None, help="a robot on the network: zenoh/tcp/HOST:PORT")
    add_engine(rec)
    add_randomization(
        rec,
        "record worlds drawn from these ranges at each reset (the draws "
        "go into the bag's /tensegrity/run_info)",
    )
    rec.add_argument("--out", required=True, help="folder for the bags (episode_000, ...)")
    rec.add_argument("--markers", action=argparse.BooleanOptionalAction, default=True,
                     help="write /tf and /tensegrity/markers (what ROS viewers draw) at the "
                     "control rate")  # fmt: skip


def run_record(args: argparse.Namespace) -> int:
    """``record``: write the episodes' bags; print their paths (130 when interrupted,
    SIGTERM unwinding like Ctrl-C so the open bag is closed)."""
    from agents.recordings.offline import record

    signal.signal(signal.SIGTERM, terminate)
    try:
        paths = record(
            args.env,
            args.policy,
            args.episodes,
            Path(args.out),
            steps=args.steps,
            seed=args.seed,
            estimator=args.estimator,
            driver=args.driver,
            markers=args.markers,
            engine=args.engine,
            randomization=args.randomization,
        )
    except KeyboardInterrupt:
        log.warning("interrupted: the bag being written was closed and is complete so far")
        return 130
    for path in paths:
        sys.stdout.write(f"{path}\n")
    return 0


def add_estimate(est: argparse.ArgumentParser) -> None:
    """``estimate``'s options: the bag, the estimator, the robot, the calibration."""
    from tensegrity_gym.model.registry import ESTIMATORS

    est.add_argument("bag", help="a bag, or a folder of bags (one per episode)")
    est.add_argument("--estimator", default="ukf", choices=list(ESTIMATORS.names()),
                     help="the estimator to run over the bag")  # fmt: skip
    est.add_argument("--out", required=True, help="folder for the results")
    est.add_argument(
        "--seed",
        type=count,
        default=0,
        help="seed of the generator handed to the estimator (the ICP tracker's RANSAC draws "
        "from it; the UKF and the oracle are deterministic and draw nothing)",
    )
    est.add_argument(
        "--robot", default=None, help="robot preset or YAML, for a bag without a description"
    )
    est.add_argument(
        "--strict", action="store_true", help="stop at the first bad message instead of skipping"
    )
    est.add_argument("--no-progress", action="store_true", help="no progress bar")
    est.add_argument(
        "--calibration",
        default=None,
        help="a UWB calibration file (tensegrity-gym calibrate) to use instead of the bag's",
    )
    add_lab_map(est)
    add_ray(est, "run each bag as a Ray task (the bags on a path every node reads)")


def _estimate_line(r: dict[str, Any]) -> str:
    """One bag's line of ``estimate``'s output: its length, its errors, what the estimator
    rejected."""
    line = f"{r['bag']}: {r['steps']} steps, {r['duration_s']:.1f} s in {r['wall_s']:.1f} s"
    if "com_rmse_m" in r:
        line += (
            f"; CoM error {100 * r['com_rmse_m']:.2f} cm RMS, "
            f"ATE {100 * r.get('ate_rmse_m', float('nan')):.2f} cm"
        )
    rejected = r.get("estimator_rejected") or {}
    if rejected:
        kinds = ", ".join(f"{k} {v}" for k, v in rejected.items())
        line += f"; {sum(rejected.values())} implausible measurements rejected ({kinds})"
    return line


def _estimated(
    bag: str, args: argparse.Namespace, description: RobotDescription | None
) -> list[dict[str, Any]]:
    """``estimate_bag`` over ``bag`` with ``estimate``'s options."""
    from agents.recordings.offline import estimate_bag

    return estimate_bag(
        bag,
        args.estimator,
        Path(args.out),
        seed=args.seed,
        description=description,
        strict=args.strict,
        progress=not args.no_progress,
        calibration=args.calibration,
        ray_address=args.ray,
    )


def run_estimate(args: argparse.Namespace) -> int:
    """``estimate``: run the estimator over the bags; print a line per bag (2 when a bag
    failed: the others are still estimated and printed)."""
    from agents.recordings.importing import as_bag
    from agents.recordings.offline import BAG_FAILURES, BagsFailedError
    from tensegrity_gym.model.description import load_robot

    failed = None
    try:
        description = load_robot(args.robot) if args.robot else None
        with as_bag(args.bag, args.lab_map, args.robot) as bag:
            results = _estimated(bag, args, description)
    except BagsFailedError as err:  # each failure is logged; the other bags were estimated
        results, failed = err.results, err
    except BAG_FAILURES as err:
        log.error("%s", one_line(err))
        return 2
    for r in results:
        sys.stdout.write(_estimate_line(r) + "\n")
    sys.stdout.write(f"written to {args.out}\n")
    if failed is not None:
        log.error("%s", failed)
        return 2
    return 0


def add_calibrate(cal: argparse.ArgumentParser) -> None:
    """``calibrate``'s options: a bag, or the env whose calibration run is recorded."""
    cal.add_argument("bag", nargs="?", default=None,
                     help="a bag of the robot moving, or a lab's ranges file (.csv, .npz: "
                     "columns t, node, anchor, range)")  # fmt: skip
    cal.add_argument("--ids", default=None,
                     help="the ranges file's id map (YAML: the lab's ids -> the "
                     "description's nodes and anchors)")  # fmt: skip
    cal.add_argument("--floor", default=None,
                     help="anchor heights above the floor (m), for a robot that never "
                     "rested on it: '0=4.7 1=4.5' or '0,1,2,3=4.6'; 'ccw=0,1,2': anchors "
                     "counter-clockwise seen from above (the handedness)")  # fmt: skip
    cal.add_argument(
        "--env", default=None, help=env_help("or record a calibration run of this env id")
    )
    cal.add_argument("--seconds", type=calibration_seconds, default=120.0,
                     help="length of that run (s)")  # fmt: skip
    cal.add_argument("--world-seed", type=count, default=0, help="the simulated lab's seed")
    add_engine(cal)
    cal.add_argument("--robot", default=None, help="robot preset or YAML, for a bare bag")
    add_lab_map(cal)
    cal.add_argument("--out", required=True, help="the calibration file to write (YAML)")


def run_calibrate(args: argparse.Namespace) -> int:
    """``calibrate``: fit the anchors and offsets; print what was written."""
    from agents.recordings.calibrate import calibrate_command
    from agents.recordings.importing import as_bag

    if args.lab_map is not None and args.bag is None:
        raise ValueError("calibrate: --lab-map reads the lab's recording given as BAG")
    with as_bag(args.bag, args.lab_map, args.robot) as bag:
        result = calibrate_command(
            bag=bag, env_id=args.env, seconds=args.seconds, world_seed=args.world_seed,
            robot=args.robot, out=Path(args.out), engine=args.engine, ids=args.ids,
            floor=args.floor,
        )  # fmt: skip
    sys.stdout.write(result + "\n")
    return 0


def add_import(imp: argparse.ArgumentParser) -> None:
    """``import``'s options: the lab's files, its map, its robot, the bag to write."""
    imp.add_argument("sources", nargs="+",
                     help="the lab's CSV logs and ranges files, or a folder of them")  # fmt: skip
    imp.add_argument("--map", default=None,
                     help="the lab map (YAML: each file's kind, columns, units; the UWB ids); "
                     "default: the folder's map.yaml")  # fmt: skip
    imp.add_argument("--robot", default=None, help="robot preset or YAML (default: the map's)")
    imp.add_argument("--calibration", default=None,
                     help="a UWB calibration file for the bag (default: nominal)")  # fmt: skip
    imp.add_argument("--control-period", type=positive_float, default=None,
                     help="s between commands (default: the commands log's, else 0.1)")  # fmt: skip
    imp.add_argument("--out", required=True, help="the bag folder to write (new)")


def run_import(args: argparse.Namespace) -> int:
    """``import``: write the lab's recording as a bag; print what was written."""
    from agents.recordings.importing import import_command

    line = import_command(args.sources, lab_map=args.map, robot=args.robot, out=args.out,
                          calibration=args.calibration,
                          control_period=args.control_period)  # fmt: skip
    sys.stdout.write(line + "\n")
    return 0


def add_view(v: argparse.ArgumentParser) -> None:
    """``view``'s options: the simulation (or the bag) streamed, the port, the pace."""
    from hardware.viewer import DEFAULT_PORT
    from tensegrity_gym.model.registry import ESTIMATORS

    v.add_argument("--env", default="tensegrity_gym/ThreeBarRoll-v0", help=env_help())
    v.add_argument("--policy", default="scripted",
                   help="scripted (the robot's face gait), random, or a training run "
                   "folder")  # fmt: skip
    v.add_argument("--bag", default=None, help="replay this bag instead (its commands drive it)")
    v.add_argument("--driver", default=None, help="a robot on the network: zenoh/tcp/HOST:PORT")
    v.add_argument("--port", type=port, default=DEFAULT_PORT,
                   help="WebSocket port (0: any free one)")  # fmt: skip
    v.add_argument("--speed", type=non_negative_float, default=1.0,
                   help="run time per wall-clock time; 0: as fast as it runs")  # fmt: skip
    v.add_argument("--episodes", type=count, default=0, help="episodes; 0: until Ctrl-C")
    v.add_argument("--steps", type=positive_int, default=None, help="control steps per episode")
    v.add_argument("--seed", type=count, default=0, help="episode k uses seed + k")
    v.add_argument("--estimator", default="ukf", choices=list(ESTIMATORS.names()),
                   help="the estimator run in the loop")  # fmt: skip


def run_view(args: argparse.Namespace) -> int:
    """``view``: stream to Foxglove until the episodes end (or Ctrl-C)."""
    from agents.recordings.view import view

    bag = Path(args.bag) if args.bag else None
    view(args.env, args.policy, bag=bag, driver=args.driver, port=args.port, speed=args.speed,
         episodes=args.episodes, steps=args.steps, seed=args.seed,
         estimator=args.estimator)  # fmt: skip
    return 0


COMMANDS = (
    Command("record", "run a policy and write each episode to a ROS 2 bag", add_record, run_record),
    Command(
        "estimate",
        "run an estimator over a bag; write its trajectory, metrics, plots",
        add_estimate,
        run_estimate,
    ),
    Command(
        "calibrate",
        "calibrate the UWB anchors and offsets from a recorded run of the robot moving",
        add_calibrate,
        run_calibrate,
    ),
    Command(
        "import",
        "write a lab's recording (CSV logs, ranges files; a lab map) as a bag",
        add_import,
        run_import,
    ),
    Command(
        "view",
        "stream a simulation or a replayed bag to Foxglove (ws://localhost:PORT)",
        add_view,
        run_view,
    ),
)
"""The subcommands of this module, in ``--help``'s order."""
