"""The UKF's measurement models, and the vector of what arrived in one update.

Five kinds of row, each a function of the node positions alone:

- rod axis: the unit vector from a rod's first node to its second, as the AHRS
  orientation of that rod gives it (its body z axis in the AHRS's frame: the world's
  turned by the frames' alignment where the state carries it), three rows a rod;
- UWB range: the distance between two modules plus the pair's offset o_ij
  (Caluwaerts et al. 2016 eq. 6-7); a robot module sits ``module_offset`` from its endcap toward
  the rod centre, an anchor at its surveyed position;
- cable length: an on-board stretch sensor's endcap-to-endcap distance;
- rod length: a pseudo-measurement that the rod keeps its length (the description's,
  plus its error where the state carries it);
- contact height: a pseudo-measurement that an endcap in contact rests on the ground.

The vector changes size with every update: dropped packets are simply absent.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import TYPE_CHECKING

import numpy as np

from tensegrity_gym.model.lie import quat_rotate

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription

__all__ = ["MeasurementBatch", "MeasurementModel", "RowKind", "ahrs_axis", "turn_back"]


class RowKind(IntEnum):
    ROD_AXIS = 0
    RANGE = 1
    CABLE_LENGTH = 2
    ROD_LENGTH = 3
    CONTACT_HEIGHT = 4


@dataclass(frozen=True)
class MeasurementBatch:
    """The measurements of one update, stacked: k rows."""

    z: NDArray[np.float64]
    """(k,) measured values."""
    variance: NDArray[np.float64]
    """(k,) noise variances."""
    kind: NDArray[np.int8]
    """(k,) :class:`RowKind` of each row."""
    groups: NDArray[np.intp]
    """(k,) rows that are gated together share an id (the 3 rows of a rod axis)."""
    axis_rods: NDArray[np.intp]
    """(a,) rods with an axis measurement, rows 3 a."""
    range_pairs: NDArray[np.intp]
    """(r, 2) module ids of the ranges."""
    range_offsets: NDArray[np.float64]
    """(r,) the offset o_ij the model adds to each range (m)."""
    cables: NDArray[np.intp]
    """(c,) cables with a length measurement."""
    rods: NDArray[np.intp]
    """(p,) rods with a length pseudo-measurement."""
    contact_nodes: NDArray[np.intp]
    """(q,) nodes held to the ground."""

    @property
    def size(self) -> int:
        return int(self.z.shape[0])


class MeasurementModel:
    """Predicts a :class:`MeasurementBatch` for a batch of states (S, 6 n), or (S, 6 n + 3)
    where the state carries the alignment of the AHRS's frame.

    Args:
        description: the robot (its rods, cables, endcaps).
        anchors: (a, 3) the anchors' positions (m).
        module_offset: how far a robot's UWB module sits from its endcap (m).
        alignment: where the state's rotation vector (3,) from the AHRS's frame to the
            world's starts; None: the two frames are one.
        rod_offsets: (r,) where the state's error of each rod's length (m) lies, by rod;
            None: the description's lengths are exact.
    """

    def __init__(
        self,
        description: RobotDescription,
        anchors: NDArray[np.float64],
        module_offset: float,
        alignment: int | None = None,
        rod_offsets: NDArray[np.intp] | None = None,
    ) -> None:
        d = description
        self.alignment = alignment
        self.rod_offsets = rod_offsets
        self.n_nodes = d.n_nodes
        self.rod_nodes = d.rod_nodes
        self.cable_nodes = d.cable_nodes
        self.node_rod = d.node_rod
        self.rod_lengths = np.array([r.length for r in d.rods])
        self.ground_height = np.array([d.rods[k].endcap_radius for k in d.node_rod])
        self.anchors = np.asarray(anchors, dtype=np.float64).reshape(-1, 3)
        self.module_offset = float(module_offset)
        # The other end of each node's rod: a module sits on the line toward it.
        other = np.empty(d.n_nodes, dtype=np.intp)
        for a, b in d.rod_nodes:
            other[a], other[b] = b, a
        self.other_end = other

    def module_positions(self, nodes: NDArray[np.float64]) -> NDArray[np.float64]:
        """Module positions (S, n + n_anchors, 3) for node positions (S, n, 3)."""
        robot = nodes
        if self.module_offset != 0.0:
            toward = nodes[:, self.other_end] - nodes
            toward /= np.linalg.norm(toward, axis=-1, keepdims=True)
            robot = nodes + self.module_offset * toward
        anchors = np.broadcast_to(self.anchors, (nodes.shape[0], *self.anchors.shape))
        return np.concatenate([robot, anchors], axis=1)

    def predict(self, batch: MeasurementBatch, states: NDArray[np.float64]) -> NDArray[np.float64]:
        """Predicted measurements (S, k) of states (S, d), rows in ``batch`` order."""
        S = states.shape[0]
        nodes = states[:, : 3 * self.n_nodes].reshape(S, self.n_nodes, 3)
        parts = []
        if batch.axis_rods.size:
            rn = self.rod_nodes[batch.axis_rods]
            u = nodes[:, rn[:, 1]] - nodes[:, rn[:, 0]]
            u = u / np.linalg.norm(u, axis=-1, keepdims=True)
            if self.alignment is not None:
                # The AHRS reads the world's axis turned back into its own frame.
                u = turn_back(states[:, self.alignment : self.alignment + 3], u)
            parts.append(u.reshape(S, -1))
        if batch.range_pairs.size:
            modules = self.module_positions(nodes)
            p = batch.range_pairs
            diff = modules[:, p[:, 1]] - modules[:, p[:, 0]]
            parts.append(np.sqrt(np.einsum("sri,sri->sr", diff, diff)) + batch.range_offsets)
        if batch.cables.size:
            cn = self.cable_nodes[batch.cables]
            diff = nodes[:, cn[:, 1]] - nodes[:, cn[:, 0]]
            parts.append(np.sqrt(np.einsum("sri,sri->sr", diff, diff)))
        if batch.rods.size:
            rn = self.rod_nodes[batch.rods]
            diff = nodes[:, rn[:, 1]] - nodes[:, rn[:, 0]]
            length = np.sqrt(np.einsum("sri,sri->sr", diff, diff))
            if self.rod_offsets is not None:  # the rod as built: its error taken off
                length = length - states[:, self.rod_offsets[batch.rods]]
            parts.append(length)
        if batch.contact_nodes.size:
            parts.append(nodes[:, batch.contact_nodes, 2])
        if not parts:
            return np.zeros((S, 0))
        return np.concatenate(parts, axis=1)

    def batch(
        self,
        *,
        axes: dict[int, NDArray[np.float64]] | None = None,
        axis_variance: float = 0.0,
        range_pairs: NDArray[np.intp] | None = None,
        ranges: NDArray[np.float64] | None = None,
        range_offsets: NDArray[np.float64] | None = None,
        range_variance: float = 0.0,
        cable_lengths: NDArray[np.float64] | None = None,
        cable_variance: float = 0.0,
        rod_variance: float | None = None,
        contact_nodes: NDArray[np.intp] | None = None,
        contact_variance: float = 0.0,
    ) -> MeasurementBatch:
        """Stack what arrived into one batch; the order of rows is the order of kinds.

        Args:
            axes: rod index -> measured unit axis (3,).
            range_pairs, ranges, range_offsets: (r, 2) module ids, (r,) metres, (r,)
                offsets to add in the model.
            cable_lengths: (n_cables,) measured lengths, NaN where none.
            rod_variance: include rod-length pseudo-measurements with this variance.
            contact_nodes: nodes that touch the ground.
        """
        z: list[NDArray[np.float64]] = []
        var: list[NDArray[np.float64]] = []
        kind: list[NDArray[np.int8]] = []
        empty = np.zeros(0, dtype=np.intp)
        axis_rods = empty
        if axes:
            axis_rods = np.array(sorted(axes), dtype=np.intp)
            z.append(np.concatenate([axes[int(r)] for r in axis_rods]))
            var.append(np.full(3 * len(axis_rods), axis_variance))
            kind.append(np.full(3 * len(axis_rods), RowKind.ROD_AXIS, dtype=np.int8))
        pairs = np.zeros((0, 2), dtype=np.intp)
        offsets = np.zeros(0)
        if range_pairs is not None and ranges is not None and len(ranges):
            pairs = np.asarray(range_pairs, dtype=np.intp).reshape(-1, 2)
            offsets = (
                np.zeros(len(pairs))
                if range_offsets is None
                else np.asarray(range_offsets, dtype=np.float64)
            )
            z.append(np.asarray(ranges, dtype=np.float64))
            var.append(np.full(len(pairs), range_variance))
            kind.append(np.full(len(pairs), RowKind.RANGE, dtype=np.int8))
        cables = empty
        if cable_lengths is not None:
            lengths = np.asarray(cable_lengths, dtype=np.float64)
            cables = np.flatnonzero(np.isfinite(lengths)).astype(np.intp)
            z.append(lengths[cables])
            var.append(np.full(len(cables), cable_variance))
            kind.append(np.full(len(cables), RowKind.CABLE_LENGTH, dtype=np.int8))
        rods = empty
        if rod_variance is not None:
            rods = np.arange(len(self.rod_lengths), dtype=np.intp)
            z.append(self.rod_lengths.copy())
            var.append(np.full(len(rods), rod_variance))
            kind.append(np.full(len(rods), RowKind.ROD_LENGTH, dtype=np.int8))
        contacts = empty
        if contact_nodes is not None and len(contact_nodes):
            contacts = np.asarray(contact_nodes, dtype=np.intp)
            z.append(self.ground_height[contacts])
            var.append(np.full(len(contacts), contact_variance))
            kind.append(np.full(len(contacts), RowKind.CONTACT_HEIGHT, dtype=np.int8))
        if z:
            zz, vv, kk = np.concatenate(z), np.concatenate(var), np.concatenate(kind)
        else:
            zz, vv, kk = np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int8)
        # Axis rows gate per rod (3 rows share an id); every other row alone.
        groups = np.arange(len(zz), dtype=np.intp)
        groups[: 3 * len(axis_rods)] = np.repeat(np.arange(len(axis_rods)), 3)
        return MeasurementBatch(
            zz, vv, kk, groups, axis_rods, pairs, offsets, cables, rods, contacts
        )


def _cross(p: NDArray[np.float64], u: NDArray[np.float64]) -> NDArray[np.float64]:
    """p x u for p (S, 1, 3) and u (S, a, 3), component by component: np.cross is
    three times slower on arrays this small."""
    out = np.empty_like(u)
    out[..., 0] = p[..., 1] * u[..., 2] - p[..., 2] * u[..., 1]
    out[..., 1] = p[..., 2] * u[..., 0] - p[..., 0] * u[..., 2]
    out[..., 2] = p[..., 0] * u[..., 1] - p[..., 1] * u[..., 0]
    return out


def turn_back(phi: NDArray[np.float64], u: NDArray[np.float64]) -> NDArray[np.float64]:
    """R(phi)^T u: vectors u (S, a, 3) turned back by the rotations of rotation vectors
    phi (S, 3), rad. Rodrigues: R^T u = u - a phi x u + b phi x (phi x u), a = sin(t)/t,
    b = (1 - cos t)/t^2 (t = |phi|), both through np.sinc, which is smooth at 0."""
    theta = np.sqrt(np.einsum("si,si->s", phi, phi))[:, None, None]
    a = np.sinc(theta / np.pi)
    b = 0.5 * np.sinc(theta / (2.0 * np.pi)) ** 2
    p = phi[:, None, :]
    once = _cross(p, u)
    return np.asarray(u - a * once + b * _cross(p, once))


def ahrs_axis(quaternion: NDArray[np.float64]) -> NDArray[np.float64]:
    """A rod's axis in the world (its body z axis) from its AHRS quaternion (x, y, z, w)."""
    return quat_rotate(np.asarray(quaternion, dtype=np.float64), np.array([0.0, 0.0, 1.0]))
