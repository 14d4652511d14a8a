"""The speed and accuracy of the shape reconstruction of Tong et al. 2024 section V (its C++
took 4.1 ms a solve, and its shapes' cable-connected endcap distances were 4.63 cm RMS
from the truth on its 1.45 m robot).

A run of the robot's scripted gait is recorded; at each control step the shape is
reconstructed from that step's encoder and cable-length samples, the true up vector in
the body frame and the contact sensors' flags, warm-started from the last shape as an
estimator does. Every solve is timed on its own; the first, which loads (or compiles)
the numba kernels, is left out. Times are medians (a shared machine's scheduler adds
long tails to a mean) with the means beside them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from agents.benchmarks.estimation import record_face_transition
from estimation.inekf.shape import ShapeConfig, ShapeReconstructor, ShapeSolution
from tensegrity_gym.model.kinematics import member_lengths
from tensegrity_gym.model.lie import quat_to_matrix
from tensegrity_gym.model.samples import CableLengthSample, ContactSample, EncoderSample

if TYPE_CHECKING:
    from collections.abc import Sequence

    from numpy.typing import NDArray

    from hardware.recording import RecordedRun
    from tensegrity_gym.model.description import RobotDescription

__all__ = ["ShapeFrame", "bench_shape", "reconstruct", "shape_frames", "shape_scores"]

_UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class ShapeFrame:
    """What one control step gives the shape reconstruction, and the truth to score it."""

    encoders: NDArray[np.float64]
    """Actuated rest lengths (m), (m,)."""
    cables: NDArray[np.float64]
    """Cable-length readings (m), (n_cables,)."""
    contacts: NDArray[np.bool_]
    """The contact sensors' flags, (n_nodes,)."""
    up: NDArray[np.float64]
    """True up in the body frame, (3,)."""
    rod_up: NDArray[np.float64]
    """True up in each rod's frame, (n_rods, 3)."""
    nodes: NDArray[np.float64]
    """True node positions in the body frame (m), (n_nodes, 3)."""
    taut: NDArray[np.bool_]
    """Cables truly taut (at least their rest length), (n_cables,)."""


def shape_frames(run: RecordedRun, base_rod: int = 0) -> list[ShapeFrame]:
    """One frame per recorded step that has encoder, cable-length and contact samples
    and the truth (the latest sample of each kind)."""
    frames = []
    for step in [run.start, *run.steps]:
        latest = {type(s): s for s in step.samples}
        enc, cab = latest.get(EncoderSample), latest.get(CableLengthSample)
        con, truth = latest.get(ContactSample), step.truth
        if truth is None or enc is None or cab is None or con is None:
            continue
        assert isinstance(enc, EncoderSample) and isinstance(cab, CableLengthSample)
        assert isinstance(con, ContactSample)
        R = quat_to_matrix(truth.rod_quaternions)
        nodes = (truth.node_positions - truth.rod_positions[base_rod]) @ R[base_rod]
        lengths = member_lengths(truth.node_positions, run.description.cable_nodes)
        frames.append(
            ShapeFrame(
                encoders=enc.rest_lengths,
                cables=cab.lengths,
                contacts=con.in_contact,
                up=R[base_rod].T @ _UP,
                rod_up=np.einsum("rji,j->ri", R, _UP),
                nodes=nodes,
                taut=lengths >= truth.rest_lengths,
            )
        )
    return frames


def reconstruct(
    reconstructor: ShapeReconstructor, frames: Sequence[ShapeFrame], rod_up: bool = False
) -> tuple[list[ShapeSolution], list[float]]:
    """Solve every frame warm-started from the last shape solved (a failed solve keeps
    it); with ``rod_up``, give each rod's up too. Returns the solutions and the seconds
    each solve took."""
    warm: NDArray[np.float64] | None = None
    solutions, seconds = [], []
    for f in frames:
        distances, weights = reconstructor.cable_distances(f.encoders, f.cables)
        t0 = time.perf_counter()
        solution = reconstructor.solve(
            distances, weights, up_body=f.up, contacts=f.contacts, warm=warm,
            rod_up=f.rod_up if rod_up else None,
        )  # fmt: skip
        seconds.append(time.perf_counter() - t0)
        solutions.append(solution)
        if solution.converged:
            warm = solution.positions
    return solutions, seconds


def shape_scores(
    description: RobotDescription, frames: Sequence[ShapeFrame], solutions: Sequence[ShapeSolution]
) -> dict[str, float]:
    """RMS errors (m) of the solved frames' cable-connected endcap distances (all
    cables, and those truly taut) and body-frame node positions; the failures' count."""
    pairs = description.cable_nodes
    ok = [(f, s) for f, s in zip(frames, solutions, strict=True) if s.converged]
    if not ok:
        return {"failures": float(len(solutions))}
    est = np.array([s.positions for _, s in ok])
    true = np.array([f.nodes for f, _ in ok])
    dist = member_lengths(est, pairs) - member_lengths(true, pairs)
    taut = np.array([f.taut for f, _ in ok])
    nodes = np.linalg.norm(est - true, axis=-1)
    return {
        "distance_rmse_m": round(float(np.sqrt(np.mean(dist**2))), 4),
        "taut_distance_rmse_m": round(float(np.sqrt(np.mean(dist[taut] ** 2))), 4),
        "node_rmse_m": round(float(np.sqrt(np.mean(nodes**2))), 4),
        "failures": float(len(solutions) - len(ok)),
    }


def bench_shape(
    n: int = 200, env_id: str = "tensegrity_gym/ThreeBarLargeRoll-v0", seed: int = 0
) -> dict[str, float]:
    """Microseconds per solve (median, mean, 95th percentile) and the errors of
    :func:`shape_scores` over ``n`` control steps of the gait, without and with each
    rod's up (``rod_up_`` figures)."""
    run = record_face_transition(env_id, seed, n)
    frames = shape_frames(run)
    reconstructor = ShapeReconstructor(run.description, ShapeConfig())
    out: dict[str, float] = {"frames": float(len(frames))}
    for prefix, rod_up in (("", False), ("rod_up_", True)):
        solutions, seconds = reconstruct(reconstructor, frames, rod_up=rod_up)
        us = 1e6 * np.asarray(seconds[1:])
        out[f"{prefix}solve_us"] = round(float(np.median(us)), 1)
        out[f"{prefix}solve_mean_us"] = round(float(np.mean(us)), 1)
        out[f"{prefix}solve_p95_us"] = round(float(np.percentile(us, 95)), 1)
        scores = shape_scores(run.description, frames, solutions)
        out.update({f"{prefix}{k}": v for k, v in scores.items()})
    return out
