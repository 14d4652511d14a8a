"""The spring-mass net of papers/000 section IV-A, batched over sigma points.

Point masses at the nodes (half a rod each), members that exert linear stiffness and
damping along their axis (cables unilateral, rods as stiff bilateral members), flat
ground with a penalty contact and regularised Coulomb friction, gravity. The member
force density is q_k = K_k (1 - L0_k / L_k) + c_k / L_k dL_k/dt with tension positive,
and the force on node i of member (i, j) is q_k (N_j - N_i).

A state is (6 n,): node positions then node velocities, both (n, 3) flattened.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numba
import numpy as np

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription

__all__ = ["SpringMassModel", "SpringMassParams"]


@dataclass(frozen=True)
class SpringMassParams:
    """How the filter's model is built from a robot description.

    ``None`` picks a value from the description: the substep from the stiffest cable,
    the rod stiffness a multiple of the stiffest cable's, the substep short enough for
    the stiffest member to integrate stably.
    """

    substep: float | None = None
    """Integration step (s)."""
    rod_stiffness: float | None = None
    """Axial stiffness of the rods as members (N/m)."""
    rod_stiffness_factor: float = 5.0
    """Rod stiffness as a multiple of the stiffest cable's, when not given."""
    rod_damping_ratio: float = 0.5
    """Damping of the rod members as a share of critical."""
    ground_stiffness: float | None = None
    """Penalty stiffness of the ground per node (N/m); None: the robot's weight on one
    node sinks it by ``ground_sink`` rod lengths."""
    ground_sink: float = 0.01
    rod_contact_stiffness: float | None = None
    """Penalty stiffness between touching rods (N/m); None: 5 times the stiffest cable."""
    smoothing: float = 0.003
    """Length over which slack and contact switch on, in rod lengths."""
    slip_speed: float = 0.05
    """Friction grows linearly in the sliding speed below this (m/s)."""
    ground_damping_ratio: float = 1.0
    """Damping of the ground penalty as a share of critical (no bounce)."""
    friction: float | None = None
    """Coulomb friction coefficient; None takes the description's lateral friction."""
    max_substep: float = 0.004
    stability_margin: float = 1.0
    """Largest omega * substep allowed for any member (semi-implicit Euler: < 2)."""

    def __post_init__(self) -> None:
        for name in (
            "substep",
            "rod_stiffness",
            "ground_stiffness",
            "rod_contact_stiffness",
            "friction",
        ):
            value = getattr(self, name)
            if value is not None and not (np.isfinite(value) and value > 0):
                raise ValueError(f"SpringMassParams.{name} must be positive, got {value}")
        if not 0 < self.stability_margin < 2:
            raise ValueError(
                f"SpringMassParams.stability_margin must lie in (0, 2), got {self.stability_margin}"
            )


class SpringMassModel:
    """The robot as a spring-mass net; propagates batches of states.

    Members are the cables (first, in description order) followed by the rods.
    """

    def __init__(self, description: RobotDescription, params: SpringMassParams | None = None):
        p = params if params is not None else SpringMassParams()
        d = description
        self.description = d
        self.params = p
        self.n_nodes = d.n_nodes
        self.state_dim = 6 * d.n_nodes
        masses = d.node_masses
        self.node_masses = masses
        cable_k = np.array([c.stiffness for c in d.cables])
        cable_c = np.array([c.damping for c in d.cables])
        m_min = float(masses.min())
        rod_k = (
            p.rod_stiffness
            if p.rod_stiffness is not None
            else p.rod_stiffness_factor * float(cable_k.max())
        )
        # Two equal masses on a spring of stiffness k oscillate at sqrt(2 k / m).
        omega_max = float(np.sqrt(2.0 * max(rod_k, float(cable_k.max())) / m_min))
        if p.substep is None:
            substep = min(p.max_substep, p.stability_margin / omega_max)
        else:
            substep = p.substep
        self.substep = float(substep)
        rod_c = p.rod_damping_ratio * 2.0 * np.sqrt(rod_k * 0.5 * m_min)
        L = d.characteristic_length
        self.smoothing = float(p.smoothing * L)
        # A soft ground: with the state uncertain by centimetres, a stiff one would throw
        # sigma points that start below the surface far into the air.
        ground_k = (
            p.ground_stiffness
            if p.ground_stiffness is not None
            else d.total_mass * d.gravity / (p.ground_sink * L)
        )
        self.ground_stiffness = float(ground_k)
        self.ground_damping = float(p.ground_damping_ratio * 2.0 * np.sqrt(ground_k * m_min))
        self.friction = float(p.friction if p.friction is not None else d.ground.lateral_friction)
        # Rods touch (their collision shapes are capsules of the endcap radius): every
        # pair of rods can push on each other where their axes come within two radii.
        contact_k = (
            p.rod_contact_stiffness
            if p.rod_contact_stiffness is not None
            else 5.0 * float(cable_k.max())
        )
        self.rod_contact_stiffness = float(contact_k)
        self.rod_contact_damping = float(0.5 * 2.0 * np.sqrt(contact_k * 0.5 * m_min))
        pairs = [(a, b) for a in range(d.n_rods) for b in range(a + 1, d.n_rods)]
        self.rod_pairs = np.array(pairs, dtype=np.int64).reshape(-1, 2)
        self.rod_node_pairs = np.ascontiguousarray(d.rod_nodes, dtype=np.int64)
        self.contact_distance = np.array(
            [d.rods[a].endcap_radius + d.rods[b].endcap_radius for a, b in pairs]
        )
        # Squared centre distance beyond which a pair cannot touch (with 20 % slack for
        # rods stretched in a sigma point).
        reach = (
            np.array([0.6 * (d.rods[a].length + d.rods[b].length) for a, b in pairs])
            + self.contact_distance
            + self.smoothing
        )
        self._contact_bound = reach**2
        n_rods = d.n_rods
        self.member_nodes = np.ascontiguousarray(
            np.concatenate([d.cable_nodes, d.rod_nodes]), dtype=np.int64
        )
        self.stiffness = np.concatenate([cable_k, np.full(n_rods, rod_k)])
        self.damping = np.concatenate([cable_c, np.full(n_rods, rod_c)])
        self.unilateral = np.concatenate(
            [np.ones(d.n_cables, dtype=np.bool_), np.zeros(n_rods, dtype=np.bool_)]
        )
        self.base_rest_lengths = np.concatenate(
            [d.rest_lengths, np.array([r.length for r in d.rods])]
        )
        self.actuated_members = d.actuated.astype(np.int64)
        self.ground_height = np.array([d.rods[k].endcap_radius for k in d.node_rod], dtype=float)
        self.gravity = float(d.gravity)

    def rest_lengths(self, actuated: NDArray[np.float64]) -> NDArray[np.float64]:
        """Rest lengths of all members (m), (M,), with the actuated cables at ``actuated``."""
        out = self.base_rest_lengths.copy()
        out[self.actuated_members] = actuated
        return out

    def n_substeps(self, duration: float) -> int:
        return max(1, int(np.ceil(duration / self.substep - 1e-9)))

    def propagate(
        self,
        states: NDArray[np.float64],
        duration: float,
        rest_start: NDArray[np.float64],
        rest_end: NDArray[np.float64] | None = None,
        *,
        compiled: bool = True,
    ) -> NDArray[np.float64]:
        """Advance a batch of states by ``duration`` seconds.

        Args:
            states: (S, 6 n) or (6 n,).
            duration: seconds, split into equal substeps no longer than ``self.substep``.
            rest_start, rest_end: actuated cable rest lengths (m), (m,), at the start
                and end of the interval; linearly interpolated in between (the motors
                slew). ``rest_end`` None holds ``rest_start``.
            compiled: the numba kernel (default), or the same equations in plain
                numpy, vectorised over the batch: many times slower, kept as what a
                model written for filterpy would be, and to check the kernel against.

        Returns:
            The states after ``duration``, same shape as ``states`` (a new array).
        """
        x = np.asarray(states, dtype=np.float64)
        single = x.ndim == 1
        batch = np.ascontiguousarray(x.reshape(-1, self.state_dim)).copy()
        if duration <= 0.0:
            return batch[0] if single else batch
        r0 = self.rest_lengths(np.asarray(rest_start, dtype=np.float64))
        r1 = r0 if rest_end is None else self.rest_lengths(np.asarray(rest_end, dtype=np.float64))
        n = self.n_substeps(duration)
        step = _propagate if compiled else _propagate_numpy
        step(
            batch,
            n,
            duration / n,
            self.member_nodes,
            self.stiffness,
            self.damping,
            self.unilateral,
            r0,
            r1,
            1.0 / self.node_masses,
            self.gravity,
            self.ground_height,
            self.ground_stiffness,
            self.ground_damping,
            self.friction,
            self.params.slip_speed,
            self.smoothing,
            self.rod_node_pairs,
            self.rod_pairs,
            self.contact_distance,
            self._contact_bound,
            self.rod_contact_stiffness,
            self.rod_contact_damping,
        )
        return batch[0] if single else batch


@numba.njit(cache=True, nogil=True, inline="always")
def _ramp(x: float, width: float) -> float:
    """max(0, x) with its corner replaced by a parabola over [-width, width].

    Continuous in value and slope, with a bounded second derivative 1 / (2 width);
    cheaper than a softplus, which costs an exp and a log per call.
    """
    if x >= width:
        return x
    if x <= -width:
        return 0.0
    u = x + width
    return u * u / (4.0 * width)


@numba.njit(cache=True, nogil=True, inline="always")
def _step(x: float, width: float) -> float:
    """The slope of :func:`_ramp`: 0 below -width, 1 above width, linear between."""
    if x >= width:
        return 1.0
    if x <= -width:
        return 0.0
    return (x + width) / (2.0 * width)


@numba.njit(cache=True, nogil=True, inline="always")
def _rod_contact(
    x: NDArray[np.float64],
    v: NDArray[np.float64],
    force: NDArray[np.float64],
    a0: int,
    a1: int,
    b0: int,
    b1: int,
    reach: float,
    k: float,
    c: float,
    smooth: float,
) -> None:
    """Penalty between rods (a0, a1) and (b0, b1) whose axes come closer than ``reach``.

    The closest points of the two segments (Ericson, Real-Time Collision Detection
    5.1.9) split the contact force between each rod's two nodes like a lever.
    """
    # Scalars throughout: small temporary arrays would be allocated on every call.
    d1x, d1y, d1z = x[a1, 0] - x[a0, 0], x[a1, 1] - x[a0, 1], x[a1, 2] - x[a0, 2]
    d2x, d2y, d2z = x[b1, 0] - x[b0, 0], x[b1, 1] - x[b0, 1], x[b1, 2] - x[b0, 2]
    rx, ry, rz = x[a0, 0] - x[b0, 0], x[a0, 1] - x[b0, 1], x[a0, 2] - x[b0, 2]
    aa = d1x * d1x + d1y * d1y + d1z * d1z
    ee = d2x * d2x + d2y * d2y + d2z * d2z
    f = d2x * rx + d2y * ry + d2z * rz
    cc = d1x * rx + d1y * ry + d1z * rz
    bb = d1x * d2x + d1y * d2y + d1z * d2z
    denom = aa * ee - bb * bb
    s = 0.0
    if denom > 1e-12 * aa * ee:
        s = min(max((bb * f - cc * ee) / denom, 0.0), 1.0)
    t = (bb * s + f) / ee
    if t < 0.0:
        t = 0.0
        s = min(max(-cc / aa, 0.0), 1.0)
    elif t > 1.0:
        t = 1.0
        s = min(max((bb - cc) / aa, 0.0), 1.0)
    gx = rx + s * d1x - t * d2x
    gy = ry + s * d1y - t * d2y
    gz = rz + s * d1z - t * d2z
    dist = np.sqrt(gx * gx + gy * gy + gz * gz)
    if dist < 1e-9 or dist >= reach + smooth:
        return
    nx, ny, nz = gx / dist, gy / dist, gz / dist  # from rod b toward rod a
    depth = reach - dist
    rel = 0.0
    for dim, nd in ((0, nx), (1, ny), (2, nz)):
        rel += nd * (
            (1.0 - s) * v[a0, dim] + s * v[a1, dim] - (1.0 - t) * v[b0, dim] - t * v[b1, dim]
        )
    fn = k * _ramp(depth, smooth) - c * rel * _step(depth, smooth)
    if fn <= 0.0:
        return  # separating faster than the spring pushes: no pull
    for dim, nd in ((0, nx), (1, ny), (2, nz)):
        push = fn * nd
        force[a0, dim] += (1.0 - s) * push
        force[a1, dim] += s * push
        force[b0, dim] -= (1.0 - t) * push
        force[b1, dim] -= t * push


@numba.njit(cache=True, nogil=True)
def _propagate(
    states: NDArray[np.float64],
    n_steps: int,
    h: float,
    members: NDArray[np.int64],
    stiffness: NDArray[np.float64],
    damping: NDArray[np.float64],
    unilateral: NDArray[np.bool_],
    rest_start: NDArray[np.float64],
    rest_end: NDArray[np.float64],
    inv_mass: NDArray[np.float64],
    gravity: float,
    ground_height: NDArray[np.float64],
    ground_k: float,
    ground_c: float,
    mu: float,
    slip: float,
    smooth: float,
    rod_nodes: NDArray[np.int64],
    rod_pairs: NDArray[np.int64],
    contact_distance: NDArray[np.float64],
    contact_bound: NDArray[np.float64],
    contact_k: float,
    contact_c: float,
) -> None:
    """Semi-implicit Euler on each state of ``states`` (S, 6 n), in place.

    Every switch of the hybrid dynamics (a cable going slack, a node touching the
    ground, friction changing direction) is rounded over a small length or speed:
    sigma points lie a fraction of a standard deviation apart, and the unscented
    transform turns a kink between them into a large error in the mean.
    """
    S = states.shape[0]
    n = inv_mass.shape[0]
    M = members.shape[0]
    force = np.empty((n, 3))
    for s in range(S):
        x = states[s, : 3 * n].reshape(n, 3)
        v = states[s, 3 * n :].reshape(n, 3)
        for step in range(n_steps):
            # Rest lengths at the middle of the substep: the motors slew linearly.
            frac = (step + 0.5) / n_steps
            force[:, :] = 0.0
            for k in range(M):
                i = members[k, 0]
                j = members[k, 1]
                ux = x[j, 0] - x[i, 0]
                uy = x[j, 1] - x[i, 1]
                uz = x[j, 2] - x[i, 2]
                length = np.sqrt(ux * ux + uy * uy + uz * uz)
                if length < 1e-9:
                    continue
                rest = rest_start[k] + frac * (rest_end[k] - rest_start[k])
                rate = (
                    ux * (v[j, 0] - v[i, 0]) + uy * (v[j, 1] - v[i, 1]) + uz * (v[j, 2] - v[i, 2])
                ) / length
                if unilateral[k]:
                    # A cable pulls, never pushes: stretch rounded at zero, its damping
                    # fading out as it goes slack.
                    stretch = length - rest
                    tension = max(
                        stiffness[k] * _ramp(stretch, smooth)
                        + damping[k] * rate * _step(stretch, smooth),
                        0.0,
                    )  # damping may slow a shortening cable to slack, never push
                else:
                    tension = stiffness[k] * (length - rest) + damping[k] * rate
                q = tension / length
                force[i, 0] += q * ux
                force[i, 1] += q * uy
                force[i, 2] += q * uz
                force[j, 0] -= q * ux
                force[j, 1] -= q * uy
                force[j, 2] -= q * uz
            for k in range(rod_pairs.shape[0]):
                a0, a1 = rod_nodes[rod_pairs[k, 0], 0], rod_nodes[rod_pairs[k, 0], 1]
                b0, b1 = rod_nodes[rod_pairs[k, 1], 0], rod_nodes[rod_pairs[k, 1], 1]
                # Broad phase: rods whose centres lie further apart than their half
                # lengths and the reach cannot touch.
                cx = 0.5 * (x[a0, 0] + x[a1, 0] - x[b0, 0] - x[b1, 0])
                cy = 0.5 * (x[a0, 1] + x[a1, 1] - x[b0, 1] - x[b1, 1])
                cz = 0.5 * (x[a0, 2] + x[a1, 2] - x[b0, 2] - x[b1, 2])
                if cx * cx + cy * cy + cz * cz > contact_bound[k]:
                    continue
                _rod_contact(
                    x, v, force, a0, a1, b0, b1,
                    contact_distance[k], contact_k, contact_c, smooth,
                )  # fmt: skip
            for i in range(n):
                w = inv_mass[i]
                depth = ground_height[i] - x[i, 2]
                # Penalty contact, rounded at the surface; never pulls a node down.
                fn = ground_k * _ramp(depth, smooth) - ground_c * v[i, 2] * _step(depth, smooth)
                fn = max(fn, 0.0)
                v[i, 0] += h * w * force[i, 0]
                v[i, 1] += h * w * force[i, 1]
                v[i, 2] += h * (w * (force[i, 2] + fn) - gravity)
                # Coulomb friction regularised below the slip speed, applied implicitly
                # (v / (1 + h c / m)) so that it slows a node but can never reverse it.
                speed = np.sqrt(v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + slip * slip)
                scale = 1.0 / (1.0 + h * w * mu * fn / speed)
                v[i, 0] *= scale
                v[i, 1] *= scale
                x[i, 0] += h * v[i, 0]
                x[i, 1] += h * v[i, 1]
                x[i, 2] += h * v[i, 2]


def _ramp_np(x: NDArray[np.float64], width: float) -> NDArray[np.float64]:
    u = np.clip(x + width, 0.0, 2.0 * width)
    return np.where(x >= width, x, u * u / (4.0 * width))


def _step_np(x: NDArray[np.float64], width: float) -> NDArray[np.float64]:
    return np.clip((x + width) / (2.0 * width), 0.0, 1.0)


def _propagate_numpy(
    states: NDArray[np.float64],
    n_steps: int,
    h: float,
    members: NDArray[np.int64],
    stiffness: NDArray[np.float64],
    damping: NDArray[np.float64],
    unilateral: NDArray[np.bool_],
    rest_start: NDArray[np.float64],
    rest_end: NDArray[np.float64],
    inv_mass: NDArray[np.float64],
    gravity: float,
    ground_height: NDArray[np.float64],
    ground_k: float,
    ground_c: float,
    mu: float,
    slip: float,
    smooth: float,
    rod_nodes: NDArray[np.int64],
    rod_pairs: NDArray[np.int64],
    contact_distance: NDArray[np.float64],
    contact_bound: NDArray[np.float64],
    contact_k: float,
    contact_c: float,
) -> None:
    """:func:`_propagate` in numpy, vectorised over states, members and rod pairs."""
    S = states.shape[0]
    n = inv_mass.shape[0]
    x = states[:, : 3 * n].reshape(S, n, 3)
    v = states[:, 3 * n :].reshape(S, n, 3)
    i, j = members[:, 0], members[:, 1]
    a0, a1 = rod_nodes[rod_pairs[:, 0], 0], rod_nodes[rod_pairs[:, 0], 1]
    b0, b1 = rod_nodes[rod_pairs[:, 1], 0], rod_nodes[rod_pairs[:, 1], 1]
    for step in range(n_steps):
        rest = rest_start + (step + 0.5) / n_steps * (rest_end - rest_start)
        u = x[:, j] - x[:, i]
        length = np.linalg.norm(u, axis=-1)
        rate = np.einsum("smi,smi->sm", u, v[:, j] - v[:, i]) / length
        stretch = length - rest
        tension = np.where(
            unilateral,
            np.maximum(
                stiffness * _ramp_np(stretch, smooth) + damping * rate * _step_np(stretch, smooth),
                0.0,
            ),
            stiffness * stretch + damping * rate,
        )
        pull = (tension / length)[..., None] * u
        force = np.zeros_like(x)
        by_node = force.transpose(1, 0, 2)  # a view, (n, S, 3): np.add.at on the node axis
        np.add.at(by_node, i, pull.transpose(1, 0, 2))
        np.add.at(by_node, j, -pull.transpose(1, 0, 2))
        if len(rod_pairs):
            d1, d2 = x[:, a1] - x[:, a0], x[:, b1] - x[:, b0]
            r = x[:, a0] - x[:, b0]
            aa = np.einsum("spi,spi->sp", d1, d1)
            ee = np.einsum("spi,spi->sp", d2, d2)
            f = np.einsum("spi,spi->sp", d2, r)
            cc = np.einsum("spi,spi->sp", d1, r)
            bb = np.einsum("spi,spi->sp", d1, d2)
            denom = aa * ee - bb * bb
            s = np.where(
                denom > 1e-12 * aa * ee,
                np.clip((bb * f - cc * ee) / np.where(denom > 0, denom, 1.0), 0.0, 1.0),
                0.0,
            )
            t = (bb * s + f) / ee
            s = np.where(
                t < 0.0,
                np.clip(-cc / aa, 0.0, 1.0),
                np.where(t > 1.0, np.clip((bb - cc) / aa, 0.0, 1.0), s),
            )
            t = np.clip(t, 0.0, 1.0)
            gap = r + s[..., None] * d1 - t[..., None] * d2
            dist = np.linalg.norm(gap, axis=-1)
            centre = 0.5 * (x[:, a0] + x[:, a1] - x[:, b0] - x[:, b1])
            near = (
                (np.einsum("spi,spi->sp", centre, centre) <= contact_bound)
                & (dist >= 1e-9)
                & (dist < contact_distance + smooth)
            )
            normal = gap / np.where(dist > 0, dist, 1.0)[..., None]
            depth = contact_distance - dist
            sv, tv = s[..., None], t[..., None]
            rel = np.einsum(
                "spi,spi->sp",
                (1 - sv) * v[:, a0] + sv * v[:, a1] - (1 - tv) * v[:, b0] - tv * v[:, b1],
                normal,
            )
            fn = contact_k * _ramp_np(depth, smooth) - contact_c * rel * _step_np(depth, smooth)
            fn = np.where(near & (fn > 0.0), fn, 0.0)
            push = fn[..., None] * normal
            for nodes, share in ((a0, (1 - sv) * push), (a1, sv * push)):
                np.add.at(by_node, nodes, share.transpose(1, 0, 2))
            for nodes, share in ((b0, (1 - tv) * push), (b1, tv * push)):
                np.add.at(by_node, nodes, -share.transpose(1, 0, 2))
        depth = ground_height - x[..., 2]
        fn = ground_k * _ramp_np(depth, smooth) - ground_c * v[..., 2] * _step_np(depth, smooth)
        fn = np.maximum(fn, 0.0)
        v += h * inv_mass[:, None] * force
        v[..., 2] += h * (inv_mass * fn - gravity)
        speed = np.sqrt(v[..., 0] ** 2 + v[..., 1] ** 2 + slip * slip)
        scale = 1.0 / (1.0 + h * inv_mass * mu * fn / speed)
        v[..., 0] *= scale
        v[..., 1] *= scale
        x += h * v
