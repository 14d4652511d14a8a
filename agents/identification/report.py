"""``tensegrity-gym identify``: a bag in, a fitted robot YAML and its report out."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from agents.evaluation.plots import pyplot
from agents.identification.identify import MAX_EVALUATIONS, MODELS, identify_run, parameter_values
from tensegrity_gym.model.checks import output_path_error
from tensegrity_gym.model.description import dump_robot, load_robot
from tensegrity_gym.model.kinematics import center_of_mass

if TYPE_CHECKING:
    from collections.abc import Sequence

    from agents.identification.identify import Identification
    from tensegrity_gym.model.description import RobotDescription

__all__ = ["identify_command", "write_report"]


def identify_command(
    bag: str,
    out: Path,
    *,
    params: Sequence[str],
    robot: str | None = None,
    model: str = "sim",
    segment_seconds: float = 2.0,
    max_evaluations: int = MAX_EVALUATIONS,
    workers: int | None = None,
    seed: int = 0,
    imu_windows: int = 300,
) -> str:
    """Fit ``params`` of ``robot`` (default: the bag's description) to the bag; write the
    fitted robot to ``out`` and the report beside it; what came out, for a person."""
    try:
        import cma  # noqa: F401
    except ImportError as error:
        raise ImportError(
            "identify needs the cma package: pip install 'tensegrity-gym[identify]'"
        ) from error
    from hardware.bag.reader import read_run

    unwritable = output_path_error(out, "--out")  # before the fit, not after its minutes
    if unwritable is not None:
        raise ValueError(unwritable)
    start = load_robot(robot) if robot else None
    run = read_run(Path(bag), description=start)
    result = identify_run(
        run, params, description=start or run.description, model=model,
        segment_seconds=segment_seconds, max_evaluations=max_evaluations, workers=workers,
        seed=seed, imu_windows_most=imu_windows,
    )  # fmt: skip
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(dump_robot(result.description))
    folder = out.parent / f"{out.stem}_identify"
    report = write_report(result, start or run.description, folder)
    lines = [f"{out}: {result.model} model fitted to the {result.trajectory} of {bag}"]
    for name, row in report["parameters"].items():
        lines.append(f"  {name}: {row['before']:.6g} -> {row['after']:.6g} (x{row['factor']:.3f})")
    c = report["open_loop_com_error_m"]
    lines.append(
        f"  open-loop CoM error over {segment_seconds:g} s segments: {1e3 * c['before']:.1f} mm "
        f"-> {1e3 * c['after']:.1f} mm (mean of {report['segments']})"
    )
    lines += [f"  note: {note}" for note in report["notes"]]
    lines.append(f"  report: {folder / 'report.md'}")
    return "\n".join(lines)


def fit_notes(result: Identification) -> list[str]:
    """What the report should warn of: factors that ended at a bound of the search, a
    damping fitted without the IMU's readings."""
    notes = [
        f"{name} ended at the bound of the search (factor {f:.3g}, searched {low:g}-{high:g}): "
        "the model could not explain the recording with it inside that range, which points "
        "at the model (a part of the description this fit does not move, another engine's "
        "physics) rather than at a value; do not take it as measured"
        for name, (low, high) in result.at_bound.items()
        for f in [float(result.factors[result.names.index(name)])]
    ]
    return notes + _damping_note(result)


def _damping_note(result: Identification) -> list[str]:
    """The note on a damping fitted without the IMU's readings, if it was."""
    if len(result.imu_before) or "damping" not in result.names:
        return []
    why = (
        "the UKF's model has no IMU"
        if result.model == "ukf"
        else "no IMU readings were fitted (the bag has none, or --imu-windows 0)"
    )
    return [
        f"{why}: fitted to the node positions over {len(result.segments)} segments at the "
        "control rate, in which the cables' damping shows little (on the 3-bar bench, 10 % "
        "more damping moved the replayed nodes by 0.8 mm RMS over 2 s): the damping factor "
        "is weakly determined wherever the recorded trajectory is noisier than that"
    ]


def _imu_figures(result: Identification) -> dict[str, Any] | None:
    """The IMU windows' scores before and after (mean squared error in units of the
    sensors' noise), or None without them."""
    if not len(result.imu_before):
        return None
    return {
        "windows": len(result.imu_before),
        "score_before": round(float(np.mean(result.imu_before)), 3),
        "score_after": round(float(np.mean(result.imu_after)), 3),
        "median_after": round(float(np.median(result.imu_after)), 3),
    }


def write_report(result: Identification, start: RobotDescription, folder: Path) -> dict[str, Any]:
    """``report.json``, ``report.md`` and ``paths.png`` in ``folder``; the report."""
    folder.mkdir(parents=True, exist_ok=True)
    report = {
        "model": result.model,
        "trajectory": result.trajectory,
        "segments": len(result.segments),
        "evaluations": result.evaluations,
        "seconds": round(result.seconds, 1),
        "parameters": {
            name: {
                "before": parameter_values(start, name),
                "after": parameter_values(result.description, name),
                "factor": round(float(f), 5),
            }
            for name, f in zip(result.names, result.factors, strict=True)
        },
        "open_loop_com_error_m": {
            "before": round(float(result.com_before.mean()), 5),
            "after": round(float(result.com_after.mean()), 5),
            "per_segment_before": np.round(result.com_before, 5).tolist(),
            "per_segment_after": np.round(result.com_after, 5).tolist(),
        },
        "node_rms_error_m": {
            "before": round(float(result.nodes_before.mean()), 5),
            "after": round(float(result.nodes_after.mean()), 5),
        },
        "fitted_to": "IMU readings" if len(result.imu_before) else "node positions",
        "imu_windows": _imu_figures(result),
        "at_bound": {name: list(searched) for name, searched in result.at_bound.items()},
        "notes": fit_notes(result),
    }
    (folder / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    (folder / "report.md").write_text(_markdown(report))
    _plot_paths(result, start, folder / "paths.png")
    return report


def _markdown(report: dict[str, Any]) -> str:
    imu = report["imu_windows"]
    fitted = (
        f"the IMU's readings over {imu['windows']} one-period windows, each replayed from "
        f"the recording's {report['trajectory']}"
        if imu
        else f"the recording's {report['trajectory']} over {report['segments']} segments"
    )
    lines = [
        "# System identification",
        "",
        f"The {report['model']} model fitted to {fitted} ({report['evaluations']} "
        f"evaluations, {report['seconds']} s).",
        "",
        *[line for note in report["notes"] for line in (f"**Note:** {note}.", "")],
        "| parameter | before | after | factor |",
        "|---|---|---|---|",
    ]
    for name, row in report["parameters"].items():
        lines.append(f"| {name} | {row['before']:.6g} | {row['after']:.6g} | {row['factor']:.4f} |")
    c = report["open_loop_com_error_m"]
    lines += [
        "",
        "| segment | open-loop CoM error before (mm) | after (mm) |",
        "|---|---|---|",
    ]
    for k, (b, a) in enumerate(zip(c["per_segment_before"], c["per_segment_after"], strict=True)):
        lines.append(f"| {k} | {1e3 * b:.1f} | {1e3 * a:.1f} |")
    lines += ["", f"Mean: {1e3 * c['before']:.1f} mm before, {1e3 * c['after']:.1f} mm after.", ""]
    if imu:
        lines += [
            f"IMU windows: mean squared difference from the recorded readings, in units of "
            f"the sensors' noise, {imu['score_before']:.4g} before, {imu['score_after']:.4g} "
            f"after (median {imu['median_after']:.4g}).",
            "",
        ]
    lines += ["![recorded and replayed CoM paths](paths.png)", ""]
    return "\n".join(lines)


def _plot_paths(result: Identification, start: RobotDescription, file: Path) -> None:
    """Each segment's CoM path from above: recorded, replayed before and after."""
    replay = MODELS[result.model]
    segments, dt, h = result.segments, result.control_period, result.time_step
    before = replay(start, segments, dt, h)
    after = replay(result.description, segments, dt, h)
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 5.2))
    masses = start.node_masses
    for k, seg in enumerate(segments):
        rec = center_of_mass(np.concatenate([seg.nodes[None], seg.recorded]), masses)
        label = k == 0
        ax.plot(rec[:, 0], rec[:, 1], "k-", lw=1.5, label="recorded" if label else None)
        for path, style, name in ((before[k], "r:", "before"), (after[k], "b--", "after")):
            com = center_of_mass(np.concatenate([seg.nodes[None], path]), masses)
            ax.plot(com[:, 0], com[:, 1], style, lw=1.0, label=name if label else None)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title("CoM per segment: recorded, replayed before and after the fit")
    ax.legend()
    fig.tight_layout()
    fig.savefig(file, dpi=120)
    plt.close(fig)
