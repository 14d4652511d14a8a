"""The spring-mass net of Caluwaerts et al. 2016 section IV-A, batched over sigma points.

Point masses at the nodes (half a rod each), members that exert linear stiffness and
damping along their axis (cables unilateral, rods as stiff bilateral members), flat
ground with a penalty contact and regularised Coulomb friction, gravity. The member
force density is q_k = K_k (1 - L0_k / L_k) + c_k / L_k dL_k/dt with tension positive,
and the force on node i of member (i, j) is q_k (N_j - N_i).

A state is (6 n,): node positions then node velocities, both (n, 3) flattened.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple, Protocol

import numba
import numpy as np

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription

__all__ = ["Kernel", "KernelArrays", "SpringMassModel", "SpringMassParams"]


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


# Where each quantity sits in the kernel's arrays (see KernelArrays); numba reads these
# module-level ints as compile-time constants.
_NODE_I, _NODE_J, _IS_CABLE = 0, 1, 2  # members
_STIFFNESS, _DAMPING = 0, 1  # member_params
_INV_MASS, _GROUND_HEIGHT = 0, 1  # nodes
_GRAVITY, _GROUND_K, _GROUND_C, _FRICTION, _SLIP, _SMOOTHING, _CONTACT_K, _CONTACT_C = range(8)
_TUBES, _CAP_A, _CAP_B, _CAPS, _BOUND = range(5)  # pair_params


class KernelArrays(NamedTuple):
    """The model's parameters as the kernel takes them: built once per model, read by
    every propagation. M members (the cables in description order, then the rods), n
    nodes, P pairs of rods (a < b, in lexicographic order)."""

    members: NDArray[np.int64]
    """(M, 3): the member's two nodes i, j, then 1 for a cable (pulls only), 0 for a rod."""
    member_params: NDArray[np.float64]
    """(M, 2): axial stiffness (N/m), axial damping (N s/m)."""
    nodes: NDArray[np.float64]
    """(n, 2): inverse mass (1/kg), the height at which the node touches the ground (its
    endcap radius, m)."""
    constants: NDArray[np.float64]
    """(8,): gravity (m/s^2), ground stiffness (N/m), ground damping (N s/m), Coulomb
    friction coefficient (1), slip speed (m/s), smoothing width (m), rod contact
    stiffness (N/m), rod contact damping (N s/m)."""
    pairs: NDArray[np.int64]
    """(P, 4): nodes a0, a1 of rod a, then b0, b1 of rod b."""
    pair_params: NDArray[np.float64]
    """(P, 5): the distances (m) at which the pair touches: tube on tube (the sum of the
    rods' radii), rod a's endcap on rod b's tube, rod b's endcap on rod a's tube, endcap on
    endcap; then the squared centre distance beyond which the pair cannot touch (m^2)."""


class Kernel(Protocol):
    """Another implementation of the model's equations for :meth:`SpringMassModel.propagate`
    (the benchmark's plain numpy one): advances ``states`` in place."""

    def __call__(
        self,
        states: NDArray[np.float64],
        n_steps: int,
        h: float,
        rest: NDArray[np.float64],
        arrays: KernelArrays,
    ) -> None:
        """Advance ``states`` in place.

        Args:
            states: (S, 6 n), positions then velocities of each state.
            n_steps: substeps.
            h: the length of each substep (s).
            rest: (R, 2, M), every member's rest length (m) at the start and at the end
                of the interval, interpolated linearly at the middle of each substep;
                R = 1 (every state alike) or S (each state its own).
            arrays: the model's parameters.
        """


class _Constant:
    """A scalar of the model kept in ``arrays.constants``: what is written, the kernel
    uses."""

    def __init__(self, index: int) -> None:
        self.index = index

    def __get__(self, model: SpringMassModel, owner: object = None) -> float:
        return float(model.arrays.constants[self.index])

    def __set__(self, model: SpringMassModel, value: float) -> None:
        model.arrays.constants[self.index] = value


class _MemberColumn:
    """A per-member quantity kept in ``arrays.member_params`` (M,): reads give a view,
    and what is written, the kernel uses."""

    def __init__(self, column: int) -> None:
        self.column = column

    def __get__(self, model: SpringMassModel, owner: object = None) -> NDArray[np.float64]:
        return model.arrays.member_params[:, self.column]

    def __set__(self, model: SpringMassModel, value: NDArray[np.float64]) -> None:
        model.arrays.member_params[:, self.column] = value


class SpringMassModel:
    """The robot as a spring-mass net; propagates batches of states.

    Members are the cables (first, in description order) followed by the rods. The
    kernel's parameters live in :attr:`arrays`; the named attributes below read and
    write them.
    """

    stiffness = _MemberColumn(_STIFFNESS)
    """Axial stiffness of each member (N/m), (M,)."""
    damping = _MemberColumn(_DAMPING)
    """Axial damping of each member (N s/m), (M,)."""
    gravity = _Constant(_GRAVITY)
    """Gravitational acceleration (m/s^2)."""
    ground_stiffness = _Constant(_GROUND_K)
    """Penalty stiffness of the ground per node (N/m)."""
    ground_damping = _Constant(_GROUND_C)
    """Damping of the ground penalty per node (N s/m)."""
    friction = _Constant(_FRICTION)
    """Coulomb friction coefficient."""
    smoothing = _Constant(_SMOOTHING)
    """Width over which slack and contact switch on (m)."""
    rod_contact_stiffness = _Constant(_CONTACT_K)
    """Penalty stiffness between touching rods (N/m)."""
    rod_contact_damping = _Constant(_CONTACT_C)
    """Damping of the rod contact penalty (N s/m)."""

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
        smoothing = float(p.smoothing * L)
        pairs = [(a, b) for a in range(d.n_rods) for b in range(a + 1, d.n_rods)]
        self.rod_pairs = np.array(pairs, dtype=np.int64).reshape(-1, 2)
        self.rod_node_pairs = np.ascontiguousarray(d.rod_nodes, dtype=np.int64)
        self.member_nodes = np.ascontiguousarray(
            np.concatenate([d.cable_nodes, d.rod_nodes]), dtype=np.int64
        )
        self.base_rest_lengths = np.concatenate(
            [d.rest_lengths, np.array([r.length for r in d.rods])]
        )
        self.actuated_members = d.actuated.astype(np.int64)
        self._base_rest_interval = np.stack([self.base_rest_lengths, self.base_rest_lengths])
        self.arrays = KernelArrays(
            members=np.column_stack(
                [
                    self.member_nodes,
                    (np.arange(len(self.member_nodes)) < d.n_cables).astype(np.int64),
                ]
            ),
            member_params=_member_params(d, cable_k, rod_k, float(rod_c)),
            nodes=np.column_stack(
                [1.0 / masses, np.array([d.rods[k].endcap_radius for k in d.node_rod])]
            ),
            constants=_constants(d, p, smoothing, cable_k, m_min),
            pairs=self.rod_node_pairs[self.rod_pairs].reshape(-1, 4),
            pair_params=_pair_params(d, pairs, smoothing),
        )

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
        offsets: NDArray[np.float64] | None = None,
        kernel: Kernel | None = None,
    ) -> NDArray[np.float64]:
        """Advance a batch of states by ``duration`` seconds.

        Args:
            states: (S, 6 n) or (6 n,).
            duration: seconds, split into equal substeps no longer than ``self.substep``.
            rest_start, rest_end: actuated cable rest lengths (m), (m,), at the start
                and end of the interval; linearly interpolated in between (the motors
                slew). ``rest_end`` None holds ``rest_start``.
            offsets: (S, M) or (M,), m added to each member's rest length, per state
                (the description's error as the filter estimates it); None: none.
            kernel: another implementation of the same equations to run instead (the
                benchmark's plain numpy one).

        Returns:
            The states after ``duration``, same shape as ``states`` (a new array).
        """
        x = np.asarray(states, dtype=np.float64)
        single = x.ndim == 1
        batch = np.ascontiguousarray(x.reshape(-1, self.state_dim)).copy()
        if duration <= 0.0:
            return batch[0] if single else batch
        rest = self._base_rest_interval.copy()  # one copy: filterpy calls this per point
        rest[0][self.actuated_members] = rest_start
        rest[1][self.actuated_members] = rest_start if rest_end is None else rest_end
        if offsets is None:
            rest = rest[None]
        else:
            shift = np.asarray(offsets, dtype=np.float64).reshape(-1, 1, rest.shape[-1])
            if shift.shape[0] not in (1, batch.shape[0]):
                raise ValueError(
                    f"offsets for {shift.shape[0]} states; propagating {batch.shape[0]}"
                )
            rest = np.ascontiguousarray(rest[None] + shift)
        n = self.n_substeps(duration)
        if kernel is not None:
            kernel(batch, n, duration / n, rest, self.arrays)
        else:
            _propagate(batch, n, duration / n, rest, *self.arrays)
        return batch[0] if single else batch


def _member_params(
    d: RobotDescription, cable_k: NDArray[np.float64], rod_k: float, rod_c: float
) -> NDArray[np.float64]:
    """:attr:`KernelArrays.member_params`: the cables' own, then the rods' chosen ones."""
    n_rods = d.n_rods
    cable_c = np.array([c.damping for c in d.cables])
    stiffness = np.concatenate([cable_k, np.full(n_rods, rod_k)])
    damping = np.concatenate([cable_c, np.full(n_rods, rod_c)])
    return np.column_stack([stiffness, damping])


def _constants(
    d: RobotDescription,
    p: SpringMassParams,
    smoothing: float,
    cable_k: NDArray[np.float64],
    m_min: float,
) -> NDArray[np.float64]:
    """:attr:`KernelArrays.constants`, each chosen from ``p`` or the description."""
    out = np.empty(8)
    L = d.characteristic_length
    # A soft ground: with the state uncertain by centimetres, a stiff one would throw
    # sigma points that start below the surface far into the air.
    ground_k = (
        p.ground_stiffness
        if p.ground_stiffness is not None
        else d.total_mass * d.gravity / (p.ground_sink * L)
    )
    out[_GROUND_K] = ground_k
    out[_GROUND_C] = p.ground_damping_ratio * 2.0 * np.sqrt(ground_k * m_min)
    out[_FRICTION] = p.friction if p.friction is not None else d.ground.lateral_friction
    # Rods touch (each a tube between two wider endcaps): every pair of rods can push on
    # each other where their tubes or endcaps meet.
    contact_k = (
        p.rod_contact_stiffness
        if p.rod_contact_stiffness is not None
        else 5.0 * float(cable_k.max())
    )
    out[_CONTACT_K] = contact_k
    out[_CONTACT_C] = 0.5 * 2.0 * np.sqrt(contact_k * 0.5 * m_min)
    out[_GRAVITY] = d.gravity
    out[_SLIP] = p.slip_speed
    out[_SMOOTHING] = smoothing
    return out


def _pair_params(
    d: RobotDescription, pairs: list[tuple[int, int]], smoothing: float
) -> NDArray[np.float64]:
    """:attr:`KernelArrays.pair_params` of the rod pairs ``pairs``."""
    out = np.empty((len(pairs), 5))
    for row, (a, b) in zip(out, pairs, strict=True):
        ra, rb = d.rods[a], d.rods[b]
        row[:4] = (
            ra.radius + rb.radius,
            ra.endcap_radius + rb.radius,
            ra.radius + rb.endcap_radius,
            ra.endcap_radius + rb.endcap_radius,
        )
        # Squared centre distance beyond which a pair cannot touch (with 20 % slack for
        # rods stretched in a sigma point).
        row[_BOUND] = (0.6 * (ra.length + rb.length) + row[_CAPS] + smoothing) ** 2
    return out


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
def _segments_closest(
    x: NDArray[np.float64], a0: int, a1: int, b0: int, b1: int
) -> tuple[float, float, float]:
    """(s, t, distance (m)) of the closest points x[a0] + s (x[a1] - x[a0]) and x[b0] +
    t (x[b1] - x[b0]) of two segments (Ericson, Real-Time Collision Detection 5.1.9)."""
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
    return s, t, np.sqrt(gx * gx + gy * gy + gz * gz)


@numba.njit(cache=True, nogil=True, inline="always")
def _gap(
    x: NDArray[np.float64], a0: int, a1: int, b0: int, b1: int, s: float, t: float
) -> tuple[float, float, float, float]:
    """The vector from x[b0] + t (x[b1] - x[b0]) to x[a0] + s (x[a1] - x[a0]), and its
    length (m)."""
    gx = x[a0, 0] + s * (x[a1, 0] - x[a0, 0]) - x[b0, 0] - t * (x[b1, 0] - x[b0, 0])
    gy = x[a0, 1] + s * (x[a1, 1] - x[a0, 1]) - x[b0, 1] - t * (x[b1, 1] - x[b0, 1])
    gz = x[a0, 2] + s * (x[a1, 2] - x[a0, 2]) - x[b0, 2] - t * (x[b1, 2] - x[b0, 2])
    return gx, gy, gz, np.sqrt(gx * gx + gy * gy + gz * gz)


@numba.njit(cache=True, nogil=True, inline="always")
def _on_segment(x: NDArray[np.float64], p: int, p1: int, end: float, q0: int, q1: int) -> float:
    """Parameter in [0, 1] of the point of segment (q0, q1) closest to the end ``end``
    (0 or 1) of segment (p, p1)."""
    px = x[p, 0] + end * (x[p1, 0] - x[p, 0]) - x[q0, 0]
    py = x[p, 1] + end * (x[p1, 1] - x[p, 1]) - x[q0, 1]
    pz = x[p, 2] + end * (x[p1, 2] - x[p, 2]) - x[q0, 2]
    dx, dy, dz = x[q1, 0] - x[q0, 0], x[q1, 1] - x[q0, 1], x[q1, 2] - x[q0, 2]
    t: float = (px * dx + py * dy + pz * dz) / (dx * dx + dy * dy + dz * dz)
    return min(max(t, 0.0), 1.0)


@numba.njit(cache=True, nogil=True, inline="always")
def _deepest_touch(
    x: NDArray[np.float64],
    a0: int,
    a1: int,
    b0: int,
    b1: int,
    pair_params: NDArray[np.float64],
    pair: int,
    axes: tuple[float, float, float],
) -> tuple[float, float, float]:
    """(depth (m), s, t) of the deepest overlap of rods (a0, a1) and (b0, b1), each a tube
    between two endcap spheres: tube on tube (their axes' closest points ``axes``, as
    :func:`_segments_closest` gives them), an endcap of rod a on rod b's tube and
    endcaps, then an endcap of rod b on rod a's tube, at the distances of row ``pair`` of
    :attr:`KernelArrays.pair_params`. The first of equal depths wins."""
    s, t, dist = axes
    best, bs, bt = pair_params[pair, _TUBES] - dist, s, t
    for end in (0.0, 1.0):
        t = _on_segment(x, a0, a1, end, b0, b1)
        depth = pair_params[pair, _CAP_A] - _gap(x, a0, a1, b0, b1, end, t)[3]
        if depth > best:
            best, bs, bt = depth, end, t
        for other in (0.0, 1.0):
            depth = pair_params[pair, _CAPS] - _gap(x, a0, a1, b0, b1, end, other)[3]
            if depth > best:
                best, bs, bt = depth, end, other
    for end in (0.0, 1.0):
        s = _on_segment(x, b0, b1, end, a0, a1)
        depth = pair_params[pair, _CAP_B] - _gap(x, a0, a1, b0, b1, s, end)[3]
        if depth > best:
            best, bs, bt = depth, s, end
    return best, bs, bt


# Not inlined, and reached only by rods that may touch: inlined, its nine tries slowed
# the whole kernel 1.5-2x, even where no rods touched.
@numba.njit(cache=True, nogil=True)
def _rod_contact(
    x: NDArray[np.float64],
    v: NDArray[np.float64],
    force: NDArray[np.float64],
    a0: int,
    a1: int,
    b0: int,
    b1: int,
    pair_params: NDArray[np.float64],
    pair: int,
    axes: tuple[float, float, float],
    k: float,
    c: float,
    smooth: float,
) -> None:
    """Penalty between rods (a0, a1) and (b0, b1) where their tubes or endcaps overlap.

    The deepest overlap's two points split the contact force between each rod's two
    nodes like a lever.
    """
    depth, s, t = _deepest_touch(x, a0, a1, b0, b1, pair_params, pair, axes)
    gx, gy, gz, dist = _gap(x, a0, a1, b0, b1, s, t)
    if dist < 1e-9 or depth <= -smooth:
        return
    nx, ny, nz = gx / dist, gy / dist, gz / dist  # from rod b toward rod a
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


@numba.njit(cache=True, nogil=True, inline="always")
def _member_forces(
    x: NDArray[np.float64],
    v: NDArray[np.float64],
    force: NDArray[np.float64],
    members: NDArray[np.int64],
    member_params: NDArray[np.float64],
    rest: NDArray[np.float64],
    frac: float,
    smooth: float,
) -> None:
    """Adds every member's axial force to ``force`` (n, 3), rest lengths at ``frac`` of
    the interval from ``rest[0]`` to ``rest[1]``."""
    for k in range(members.shape[0]):
        i = members[k, _NODE_I]
        j = members[k, _NODE_J]
        ux = x[j, 0] - x[i, 0]
        uy = x[j, 1] - x[i, 1]
        uz = x[j, 2] - x[i, 2]
        length = np.sqrt(ux * ux + uy * uy + uz * uz)
        if length < 1e-9:
            continue
        length_rest = rest[0, k] + frac * (rest[1, k] - rest[0, k])
        rate = (
            ux * (v[j, 0] - v[i, 0]) + uy * (v[j, 1] - v[i, 1]) + uz * (v[j, 2] - v[i, 2])
        ) / length
        stiffness = member_params[k, _STIFFNESS]
        damping = member_params[k, _DAMPING]
        if members[k, _IS_CABLE] != 0:
            # A cable pulls, never pushes: stretch rounded at zero, its damping fading
            # out as it goes slack.
            stretch = length - length_rest
            tension = max(
                stiffness * _ramp(stretch, smooth) + damping * rate * _step(stretch, smooth),
                0.0,
            )  # damping may slow a shortening cable to slack, never push
        else:
            tension = stiffness * (length - length_rest) + damping * rate
        q = tension / length
        force[i, 0] += q * ux
        force[i, 1] += q * uy
        force[i, 2] += q * uz
        force[j, 0] -= q * ux
        force[j, 1] -= q * uy
        force[j, 2] -= q * uz


@numba.njit(cache=True, nogil=True, inline="always")
def _advance_nodes(
    x: NDArray[np.float64],
    v: NDArray[np.float64],
    force: NDArray[np.float64],
    nodes: NDArray[np.float64],
    constants: NDArray[np.float64],
    h: float,
) -> None:
    """One semi-implicit Euler substep of ``h`` seconds for every node: ``force`` (n, 3)
    plus ground, gravity and friction change the velocities ``v``, which then move the
    positions ``x`` (both (n, 3), in place)."""
    gravity = constants[_GRAVITY]
    ground_k = constants[_GROUND_K]
    ground_c = constants[_GROUND_C]
    mu = constants[_FRICTION]
    slip = constants[_SLIP]
    smooth = constants[_SMOOTHING]
    for i in range(nodes.shape[0]):
        w = nodes[i, _INV_MASS]
        depth = nodes[i, _GROUND_HEIGHT] - x[i, 2]
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


@numba.njit(cache=True, nogil=True)
def _propagate(
    states: NDArray[np.float64],
    n_steps: int,
    h: float,
    rest: NDArray[np.float64],
    members: NDArray[np.int64],
    member_params: NDArray[np.float64],
    nodes: NDArray[np.float64],
    constants: NDArray[np.float64],
    pairs: NDArray[np.int64],
    pair_params: NDArray[np.float64],
) -> None:
    """Semi-implicit Euler on each state of ``states`` (S, 6 n), in place, with the rest
    lengths ``rest`` (R, 2, M) of every state (R = 1) or of each (R = S): a
    :class:`Kernel` compiled, taking the fields of ``arrays`` one by one.

    Every switch of the hybrid dynamics (a cable going slack, a node touching the
    ground, friction changing direction) is rounded over a small length or speed:
    sigma points lie a fraction of a standard deviation apart, and the unscented
    transform turns a kink between them into a large error in the mean.
    """
    n = nodes.shape[0]
    smooth = constants[_SMOOTHING]
    contact_k = constants[_CONTACT_K]
    contact_c = constants[_CONTACT_C]
    force = np.empty((n, 3))
    shared = rest.shape[0] == 1
    for s in range(states.shape[0]):
        x = states[s, : 3 * n].reshape(n, 3)
        v = states[s, 3 * n :].reshape(n, 3)
        own = rest[0] if shared else rest[s]
        for step in range(n_steps):
            force[:, :] = 0.0
            # Rest lengths at the middle of the substep: the motors slew linearly.
            frac = (step + 0.5) / n_steps
            _member_forces(x, v, force, members, member_params, own, frac, smooth)
            # The rod pairs here, not in a helper of their own: with that one inlined
            # too, the kernel ran some 7 % slower.
            for k in range(pairs.shape[0]):
                a0, a1, b0, b1 = pairs[k, 0], pairs[k, 1], pairs[k, 2], pairs[k, 3]
                # Broad phase: rods whose centres lie further apart than their half
                # lengths and the reach cannot touch.
                cx = 0.5 * (x[a0, 0] + x[a1, 0] - x[b0, 0] - x[b1, 0])
                cy = 0.5 * (x[a0, 1] + x[a1, 1] - x[b0, 1] - x[b1, 1])
                cz = 0.5 * (x[a0, 2] + x[a1, 2] - x[b0, 2] - x[b1, 2])
                if cx * cx + cy * cy + cz * cz > pair_params[k, _BOUND]:
                    continue
                # The axes' distance bounds every other: rods this far apart cannot touch.
                axes = _segments_closest(x, a0, a1, b0, b1)
                if axes[2] >= pair_params[k, _CAPS] + smooth:
                    continue
                _rod_contact(
                    x, v, force, a0, a1, b0, b1,
                    pair_params, k, axes, contact_k, contact_c, smooth,
                )  # fmt: skip
            _advance_nodes(x, v, force, nodes, constants, h)
