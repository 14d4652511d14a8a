"""The ``tensegrity-gym`` command line."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

__all__ = ["main"]

log = logging.getLogger("tensegrity_gym")


def _demo(args: argparse.Namespace) -> int:
    from agents.demo import run_gait

    summary = run_gait(
        args.env, steps=args.steps, seed=args.seed, estimator=args.estimator, out=Path(args.out)
    )
    s, e = summary["com_start"], summary["com_end"]
    sys.stdout.write(
        f"{summary['env']}: scripted gait, {summary['seconds']:.1f} s simulated, "
        f"{summary['face_changes']} support-face changes\n"
        f"  true CoM went from ({s[0]:+.3f}, {s[1]:+.3f}) to ({e[0]:+.3f}, {e[1]:+.3f}) m: "
        f"{summary['distance']:.3f} m in a straight line, {summary['path_length']:.3f} m of path\n"
        f"  {summary['estimator']} estimate of the CoM: "
        f"{100 * summary['estimation_error_rms']:.1f} cm RMS error, "
        f"{100 * summary['estimation_error_max']:.1f} cm at worst\n"
        f"  plot: {summary['plot']}\n"
    )
    return 1 if summary["diverged"] else 0


def _bench(args: argparse.Namespace) -> int:
    from agents.bench import run_benchmarks

    results = run_benchmarks(
        speed_steps=args.steps, memory_steps=args.memory_steps, estimation=args.estimation
    )
    text = json.dumps(results, indent=2)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text + "\n")
    sys.stdout.write(text + "\n")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tensegrity-gym", description="Tensegrity robots with estimated-state observations."
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log at debug level")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="roll the 3-bar robot with its scripted gait; plot the CoM")
    demo.add_argument("--env", default="tensegrity_gym/ThreeBarRoll-v0")
    demo.add_argument("--steps", type=int, default=300, help="control steps (10 Hz)")
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--estimator", default="ukf", choices=["ukf", "oracle"])
    demo.add_argument("--out", default="demo_out", help="folder for the plot and summary")
    demo.set_defaults(func=_demo)

    bench = sub.add_parser("bench", help="measure env speed and memory; print JSON")
    bench.add_argument("--steps", type=int, default=2000, help="env steps timed per env")
    bench.add_argument(
        "--memory-steps", type=int, default=100_000, help="env steps of the memory test (0: skip)"
    )
    bench.add_argument(
        "--estimation",
        action="store_true",
        help="also run the estimation study (papers/000 on SUPERball) and the UKF's "
        "speed against filterpy's",
    )
    bench.add_argument("--out", default=None, help="also write the JSON to this file")
    bench.set_defaults(func=_bench)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    return int(args.func(args))


if __name__ == "__main__":
    raise SystemExit(main())
