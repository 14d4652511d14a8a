"""Shape reconstruction of Tong et al. 2024 section V: the endcaps in the body frame from the
cable lengths, the rod lengths and gravity.

The body frame is the base rod's (its IMU's): origin at the rod's centre, z from its
first node to its second, x and y those of its rigid body. The base rod's nodes are
fixed at (0, 0, -L/2) and (0, 0, +L/2) (eq. 15b-c); every other rod is a centre and a
unit axis, so the rod lengths (15f) hold by construction. The unknowns (5 per free rod)
are fitted by Levenberg-Marquardt (compiled with numba) to

- the endcap-to-endcap distances the encoders and cable-length sensors imply (15a),
  each one-sided past a margin: a cable may be slack, shorter than its target
  (two-sided where the motor holds a minimum tension and so reels in any slack, as on
  Tong et al. 2024's robot: the description's ``motor.min_tension``);
- gravity: the endcaps in contact lie at one height along ``up`` (flat ground). The
  cable distances say nothing about the structure's rotation about body z (the base
  rod can spin about its own axis); the contacts fix it. Without two contacts, one of
  them off the body z axis, that rotation is held at the warm start's;
- optionally (not in the paper) each rod's tilt, u . up, from its own accelerometer;
- the inequalities, as penalties zero while they hold: each end triangle's centroid
  on its side of the body xy plane (15d-e, which the paper asks of every endcap: the
  presets' own rest shapes break that); the rod-centre triangle's normal along every
  rod's axis (15g-i, the rods do not cross); the prism's twist of the rest shape
  (15j-l, chirality); and, not in the paper, rods apart by their endcap radii (they
  touch in most of the gait) and no endcap below the ground plane of the contacts.

The cable distances alone admit the mirror image of the prism (reflected in a plane
through body z and ``up``, it keeps every distance and height): 15g-l tell the two
apart. Near the prestressed equilibrium a tensegrity's framework is also nearly
flexible, so distances that fit to a centimetre can leave endcaps a decimetre apart,
and a cable that goes slack frees the shape further. A solve therefore starts from the
warm start (the last shape) and, unless that fits well, also from its mirror image (if
it broke a constraint), the rest shape turned to fit gravity, and the warm result with
each cable let slack in turn; the feasible fit of least cost is kept.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numba
import numpy as np

from tensegrity_gym.model.checks import all_finite, check_number, check_optional_number
from tensegrity_gym.model.kinematics import member_lengths, rod_quaternion_from_axis
from tensegrity_gym.model.lie import quat_to_matrix

if TYPE_CHECKING:
    from typing import TypeAlias

    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription

    Geo: TypeAlias = tuple[
        NDArray[np.int64],
        NDArray[np.float64],
        NDArray[np.float64],
        NDArray[np.float64],
        NDArray[np.float64],
    ]
    """(node_rod, node_sign, half, E1, E2): what maps a node's gradient into J."""
    Problem: TypeAlias = tuple[
        NDArray[np.float64],
        NDArray[np.int64],
        NDArray[np.float64],
        NDArray[np.float64],
        NDArray[np.int64],
        NDArray[np.int64],
        NDArray[np.float64],
        NDArray[np.float64],
        NDArray[np.float64],
        NDArray[np.float64],
        NDArray[np.bool_],
        NDArray[np.float64],
        NDArray[np.float64],
        NDArray[np.float64],
        NDArray[np.int64],
        NDArray[np.int64],
        NDArray[np.float64],
        NDArray[np.float64],
        NDArray[np.float64],
        NDArray[np.float64],
        NDArray[np.int64],
    ]
    """See :meth:`ShapeReconstructor._problem`."""

__all__ = ["ShapeConfig", "ShapeReconstructor", "ShapeSolution", "structure_problem"]


@dataclass(frozen=True)
class ShapeConfig:
    """How shapes are reconstructed. Lengths in metres; a ``*_sigma`` is a standard
    deviation, weighted as its inverse square."""

    geometric: bool = True
    """15g-i: the rods do not cross (the rod-centre triangle's normal along each rod)."""
    chirality: bool = True
    """15j-l: the prism keeps the twist direction of the rest shape."""
    non_penetration: bool = True
    """Rods stay apart by their endcap radii; no endcap sinks below the contacts' plane."""
    gravity_sigma: float = 0.005
    """Spread of the in-contact endcaps' heights along up."""
    encoder_sigma: float = 0.02
    """Error of an actuated cable's distance taken as its rest length plus the rest
    shape's pre-stretch (the tension, and so the stretch, varies with the gait)."""
    sensor_sigma: float | None = None
    """Error of a cable-length sensor reading; None: the description's sensor noise."""
    rest_shape_sigma: float = 0.1
    """Error of a passive cable's distance taken from the rest shape (no sensor)."""
    slack_sigmas: float = 3.0
    """A cable shorter than its target by more than this many of its sigmas counts as
    slack: its residual stops growing (cables only pull)."""
    constraint_tolerance: float = 1e-3
    """Scale of the inequality penalties: metres for penetration and the z signs,
    a share of the rest shape's value for 15g-l."""
    spin_sigma: float = 1e-3
    """rad: how firmly the rotation about body z is held when gravity cannot fix it."""
    tilt_sigma: float = 0.03
    """Error of a rod's measured u . up (``rod_up``), dimensionless (~ rad)."""
    slack_search: bool = True
    """Also try the warm result with each cable let slack in turn: a cable going slack
    frees a shape that a warm start tracking the taut one does not reach."""
    search_cost: float = 8.0
    """The warm start's solution is kept without trying the others when its cost (as
    ``switch_margin``'s) is at most this; 0: always search."""
    switch_margin: float = 1.0
    """Another start's solution replaces the warm start's only if its cost (half the
    sum of squared residuals, each over its sigma) is lower by this much."""
    max_iterations: int = 100
    """Levenberg-Marquardt iterations per start."""
    xtol: float = 1e-5
    """Converged when a step moves no coordinate by more than this (m, rad)..."""
    ftol: float = 1e-6
    """... or lowers the cost by less than this share."""
    max_residual: float | None = None
    """RMS cable-distance residual (m) above which a solve is reported failed; None:
    4 cable-length sensor sigmas (7 cm on three_bar_large, 1.6 cm on three_bar)."""
    max_slack: int = 3
    """More cables slack than this is no shape of a tensegrity under prestress: failed."""

    def __post_init__(self) -> None:
        for name in ("geometric", "chirality", "non_penetration", "slack_search"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(
                    f"ShapeConfig: {name}={getattr(self, name)!r} must be True or False"
                )
        positive = (
            "gravity_sigma", "encoder_sigma", "rest_shape_sigma", "slack_sigmas",
            "constraint_tolerance", "spin_sigma", "tilt_sigma", "xtol", "ftol",
        )  # fmt: skip
        for name in positive:
            check_number(name, getattr(self, name), positive=True, where="ShapeConfig")
        for name in ("switch_margin", "search_cost"):
            check_number(name, getattr(self, name), non_negative=True, where="ShapeConfig")
        for name in ("sensor_sigma", "max_residual"):
            check_optional_number(name, getattr(self, name), positive=True, where="ShapeConfig")
        for name, low in (("max_iterations", 1), ("max_slack", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ValueError(f"ShapeConfig: {name}={v!r} must be an integer >= {low}")


@dataclass(frozen=True)
class ShapeSolution:
    """The result of one :meth:`ShapeReconstructor.solve`."""

    positions: NDArray[np.float64]
    """(n_nodes, 3) body frame, m; all NaN when the solve failed."""
    converged: bool
    residual_rms: float
    """RMS of the weighted cables' distance residuals (m), a slack cable's counted at
    its slack margin."""
    iterations: int
    """Levenberg-Marquardt iterations, all starts together."""
    why: str | None
    """Why it failed, one line; None when it converged."""
    slack: tuple[int, ...] = ()
    """Cables found slack: shorter than their target by more than the slack margin."""


# ----------------------------------------------------------------------------- kernels
#
# The unknowns: for each free rod f a centre C[f] (3) and a unit axis U[f] (3); a node
# is C[f] + sign * half[f] * U[f]. A step has 5 entries per free rod: the centre's move
# and the axis' move along its tangents E1[f], E2[f] (then renormalised). The kernels
# fill the residual vector r (each row a length over its sigma, or a constraint's
# violation over its tolerance) and its Jacobian J in those 5 F steps. They work on
# scalars where they can: at this size numba's small-array allocations cost more than
# the arithmetic.

# Scalars, in one float array (numba takes arrays more cheaply than many arguments).
_SW_GRAVITY = 0  # 1 / gravity_sigma
_SW_SPIN = 1  # 1 / spin_sigma
_SW_CONSTRAINT = 2  # 1 / constraint_tolerance
_GROUND_TOL = 3  # m an endcap may sit below the contacts' plane before it counts
_SW_TILT = 4  # 1 / tilt_sigma
_N_FLOATS = 5
# Switches, in one int array.
_GRAVITY = 0  # the contacts at one height along up (else: hold the spin about z)
_PENETRATION = 1
_PRISM = 2  # a 3-bar prism: 15d-e apply
_GEOMETRIC = 3
_CHIRALITY = 4
_N_FLAGS = 5

# What _verdict finds; the constraint codes follow the order of their row blocks.
_OK, _NOT_FINITE, _NO_CONVERGENCE, _RESIDUAL, _SLACK = 0, 1, 2, 3, 4
_VIOLATED = (
    "an endcap below the ground",
    "an end triangle's centroid on the wrong side of the body xy plane (15d-e)",
    "rods interpenetrating",
    "rods crossing (15g-i)",
    "the prism's twist reversed (15j-l)",
)


@numba.njit(cache=True, nogil=True)
def _blocks(n_cables: int, n_nodes: int, n_rods: int) -> tuple[int, ...]:
    """Where each block of residual rows starts: gravity (a row per node), ground (per
    node), the spin (1), the ends' z signs (2), rod pairs, geometric (per rod),
    chirality (per rod), tilt (per rod); the last entry is the number of rows. The
    cables' rows come first, from 0."""
    gravity = n_cables
    ground = gravity + n_nodes
    spin = ground + n_nodes
    zsign = spin + 1
    clearance = zsign + 2
    geometric = clearance + n_rods * (n_rods - 1) // 2
    chirality = geometric + n_rods
    tilt = chirality + n_rods
    return gravity, ground, spin, zsign, clearance, geometric, chirality, tilt, tilt + n_rods


@numba.njit(cache=True, nogil=True)
def _node_positions(
    C: NDArray[np.float64],
    U: NDArray[np.float64],
    base: NDArray[np.float64],
    node_rod: NDArray[np.int64],
    node_sign: NDArray[np.float64],
    half: NDArray[np.float64],
) -> NDArray[np.float64]:
    """(n, 3): base nodes from ``base``, the others from their rod's centre and axis."""
    p = np.empty((node_rod.shape[0], 3))
    for k in range(node_rod.shape[0]):
        f = node_rod[k]
        for i in range(3):
            p[k, i] = base[k, i] if f < 0 else C[f, i] + node_sign[k] * half[f] * U[f, i]
    return p


@numba.njit(cache=True, nogil=True)
def _tangents(U: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Orthonormal E1, E2 (F, 3), both perpendicular to each unit axis of U (F, 3)."""
    E1 = np.empty_like(U)
    E2 = np.empty_like(U)
    for f in range(U.shape[0]):
        x, y, z = U[f, 0], U[f, 1], U[f, 2]
        # cross U with the coordinate axis least along it
        ax, ay, az = abs(x), abs(y), abs(z)
        if ax <= ay and ax <= az:
            v0, v1, v2 = 0.0, z, -y
        elif ay <= az:
            v0, v1, v2 = -z, 0.0, x
        else:
            v0, v1, v2 = y, -x, 0.0
        norm = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        v0, v1, v2 = v0 / norm, v1 / norm, v2 / norm
        E1[f, 0], E1[f, 1], E1[f, 2] = v0, v1, v2
        E2[f, 0], E2[f, 1], E2[f, 2] = y * v2 - z * v1, z * v0 - x * v2, x * v1 - y * v0
    return E1, E2


@numba.njit(cache=True, nogil=True, inline="always")
def _grad(
    J: NDArray[np.float64], row: int, k: int, g: NDArray[np.float64], scale: float, geo: Geo
) -> None:
    """Add ``scale * g``, row ``row``'s gradient (3,) in node ``k``'s position, to J."""
    node_rod, node_sign, half, E1, E2 = geo
    f = node_rod[k]
    if f < 0:
        return  # a base node: fixed
    gx, gy, gz = scale * g[0], scale * g[1], scale * g[2]
    J[row, 5 * f] += gx
    J[row, 5 * f + 1] += gy
    J[row, 5 * f + 2] += gz
    arm = node_sign[k] * half[f]
    J[row, 5 * f + 3] += arm * (gx * E1[f, 0] + gy * E1[f, 1] + gz * E1[f, 2])
    J[row, 5 * f + 4] += arm * (gx * E2[f, 0] + gy * E2[f, 1] + gz * E2[f, 2])


@numba.njit(cache=True, nogil=True)
def _cable_rows(
    p: NDArray[np.float64],
    pairs: NDArray[np.int64],
    target: NDArray[np.float64],
    sw: NDArray[np.float64],
    slack: NDArray[np.float64],
    r: NDArray[np.float64],
    J: NDArray[np.float64],
    jac: bool,
    geo: Geo,
) -> None:
    """sw (l - d) per cable; shorter than its target by over ``slack`` (m), a cable is
    slack and costs a constant: cables only pull, and a slack reading bounds it above."""
    g = np.empty(3)
    for c in range(pairs.shape[0]):
        i, j = pairs[c, 0], pairs[c, 1]
        dx, dy, dz = p[j, 0] - p[i, 0], p[j, 1] - p[i, 1], p[j, 2] - p[i, 2]
        length = np.sqrt(dx * dx + dy * dy + dz * dz)
        e = length - target[c]
        if e < -slack[c]:
            r[c] = -slack[c] * sw[c]
            continue
        r[c] = sw[c] * e
        if jac and sw[c] > 0.0:
            g[0], g[1], g[2] = dx / length, dy / length, dz / length
            _grad(J, c, j, g, sw[c], geo)
            _grad(J, c, i, g, -sw[c], geo)


@numba.njit(cache=True, nogil=True)
def _gravity_rows(
    p: NDArray[np.float64],
    up: NDArray[np.float64],
    contact: NDArray[np.bool_],
    fl: NDArray[np.float64],
    ground: bool,
    row0: int,
    r: NDArray[np.float64],
    J: NDArray[np.float64],
    jac: bool,
    geo: Geo,
) -> None:
    """Rows row0 + i: contact i's height along up less the contacts' mean height; with
    ``ground``, rows row0 + n + i: how far endcap i (not in contact) sinks below it."""
    n = p.shape[0]
    h = np.empty(n)
    k = 0
    mean = 0.0
    for i in range(n):
        h[i] = p[i, 0] * up[0] + p[i, 1] * up[1] + p[i, 2] * up[2]
        if contact[i]:
            mean += h[i]
            k += 1
    mean /= k
    sw, sc = fl[_SW_GRAVITY], fl[_SW_CONSTRAINT]
    for i in range(n):
        if contact[i]:
            r[row0 + i] = sw * (h[i] - mean)
            for m in range(n):
                if jac and contact[m]:
                    _grad(J, row0 + i, m, up, sw * ((1.0 if m == i else 0.0) - 1.0 / k), geo)
            continue
        depth = mean - h[i] - fl[_GROUND_TOL]
        if ground and depth > 0.0:
            r[row0 + n + i] = sc * depth
            if jac:
                _grad(J, row0 + n + i, i, up, -sc, geo)
                for m in range(n):
                    if contact[m]:
                        _grad(J, row0 + n + i, m, up, sc / k, geo)


@numba.njit(cache=True, nogil=True)
def _spin_row(
    C: NDArray[np.float64],
    spin_ref: NDArray[np.float64],
    sw: float,
    row: int,
    r: NDArray[np.float64],
    J: NDArray[np.float64],
    jac: bool,
) -> None:
    """The free rods' centres' mean rotation about body z away from ``spin_ref`` (F, 3),
    linearised (rad): holds the one direction the cables leave free."""
    norm = 0.0
    for f in range(C.shape[0]):
        norm += spin_ref[f, 0] ** 2 + spin_ref[f, 1] ** 2
    if norm < 1e-12:
        return
    acc = 0.0
    for f in range(C.shape[0]):
        tx, ty = -spin_ref[f, 1] / norm, spin_ref[f, 0] / norm
        acc += tx * (C[f, 0] - spin_ref[f, 0]) + ty * (C[f, 1] - spin_ref[f, 1])
        if jac:
            J[row, 5 * f] += sw * tx
            J[row, 5 * f + 1] += sw * ty
    r[row] = sw * acc


@numba.njit(cache=True, nogil=True)
def _zsign_rows(
    p: NDArray[np.float64],
    zsign: NDArray[np.float64],
    sw: float,
    row0: int,
    r: NDArray[np.float64],
    J: NDArray[np.float64],
    jac: bool,
    geo: Geo,
) -> None:
    """15d-e, relaxed: the centroid of the end triangle of the nodes with zsign -1 has
    z < 0 (row row0), that of those with +1 z > 0 (row0 + 1). The paper asks it of every
    node, which the presets' rest shapes themselves do not satisfy."""
    for side in range(2):
        want = 2.0 * side - 1.0
        z, m = 0.0, 0
        for k in range(p.shape[0]):
            if zsign[k] == want:
                z += p[k, 2]
                m += 1
        v = -want * z / max(m, 1)
        if m == 0 or v <= 0.0:
            continue
        r[row0 + side] = sw * v
        ez = np.array([0.0, 0.0, 1.0])
        for k in range(p.shape[0]):
            if jac and zsign[k] == want:
                _grad(J, row0 + side, k, ez, -sw * want / m, geo)


@numba.njit(cache=True, nogil=True)
def _closest(
    p: NDArray[np.float64], a1: int, b1: int, a2: int, b2: int
) -> tuple[float, float, float, float, float, float]:
    """Closest points of segments p[a1]-p[b1] and p[a2]-p[b2] (Ericson, Real-Time
    Collision Detection, 5.1.9): their parameters s, t in [0, 1], the distance, and the
    unit vector from the second segment's point to the first's."""
    d1 = (p[b1, 0] - p[a1, 0], p[b1, 1] - p[a1, 1], p[b1, 2] - p[a1, 2])
    d2 = (p[b2, 0] - p[a2, 0], p[b2, 1] - p[a2, 1], p[b2, 2] - p[a2, 2])
    w = (p[a1, 0] - p[a2, 0], p[a1, 1] - p[a2, 1], p[a1, 2] - p[a2, 2])
    a = d1[0] * d1[0] + d1[1] * d1[1] + d1[2] * d1[2]
    e = d2[0] * d2[0] + d2[1] * d2[1] + d2[2] * d2[2]
    f = d2[0] * w[0] + d2[1] * w[1] + d2[2] * w[2]
    c = d1[0] * w[0] + d1[1] * w[1] + d1[2] * w[2]
    b = d1[0] * d2[0] + d1[1] * d2[1] + d1[2] * d2[2]
    den = a * e - b * b
    s = min(max((b * f - c * e) / den, 0.0), 1.0) if den > 1e-12 * a * e else 0.0
    t = (b * s + f) / e
    if t < 0.0:
        t, s = 0.0, min(max(-c / a, 0.0), 1.0)
    elif t > 1.0:
        t, s = 1.0, min(max((b - c) / a, 0.0), 1.0)
    vx, vy, vz = (
        w[0] + s * d1[0] - t * d2[0],
        w[1] + s * d1[1] - t * d2[1],
        w[2] + s * d1[2] - t * d2[2],
    )
    dist = np.sqrt(vx * vx + vy * vy + vz * vz)
    inv = 1.0 / dist if dist > 1e-12 else 0.0
    return s, t, dist, vx * inv, vy * inv, vz * inv


@numba.njit(cache=True, nogil=True)
def _clearance_rows(
    p: NDArray[np.float64],
    rod_nodes: NDArray[np.int64],
    clearance: NDArray[np.float64],
    sw: float,
    row0: int,
    r: NDArray[np.float64],
    J: NDArray[np.float64],
    jac: bool,
    geo: Geo,
) -> None:
    """One row per rod pair: how far the rods' axes come closer than ``clearance``."""
    row = row0
    for q1 in range(rod_nodes.shape[0]):
        for q2 in range(q1 + 1, rod_nodes.shape[0]):
            a1, b1, a2, b2 = rod_nodes[q1, 0], rod_nodes[q1, 1], rod_nodes[q2, 0], rod_nodes[q2, 1]
            s, t, gap, nx, ny, nz = _closest(p, a1, b1, a2, b2)
            depth = clearance[q1, q2] - gap
            if depth > 0.0:
                r[row] = sw * depth
                if jac:
                    nrm = np.array([nx, ny, nz])
                    _grad(J, row, a1, nrm, -sw * (1.0 - s), geo)
                    _grad(J, row, b1, nrm, -sw * s, geo)
                    _grad(J, row, a2, nrm, sw * (1.0 - t), geo)
                    _grad(J, row, b2, nrm, sw * t, geo)
            row += 1


@numba.njit(cache=True, nogil=True, inline="always")
def _cross(
    ax: float, ay: float, az: float, bx: float, by: float, bz: float
) -> tuple[float, float, float]:
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


@numba.njit(cache=True, nogil=True)
def _centroid(p: NDArray[np.float64], nodes: NDArray[np.int64]) -> NDArray[np.float64]:
    out = np.zeros(3)
    for k in nodes:
        out += p[k] / nodes.shape[0]
    return out


@numba.njit(cache=True, nogil=True)
def _geometric_values(
    p: NDArray[np.float64], end_a: NDArray[np.int64], end_b: NDArray[np.int64]
) -> NDArray[np.float64]:
    """15g-i of a 3-bar prism, (3,): g_i = ((c1 - c0) x (c2 - c1)) . u_i, the rod-centre
    triangle's normal along rod i's axis u_i (from end A to end B)."""
    c = np.empty((3, 3))
    for m in range(3):
        for i in range(3):
            c[m, i] = 0.5 * (p[end_a[m], i] + p[end_b[m], i])
    nx, ny, nz = _cross(
        c[1, 0] - c[0, 0], c[1, 1] - c[0, 1], c[1, 2] - c[0, 2],
        c[2, 0] - c[1, 0], c[2, 1] - c[1, 1], c[2, 2] - c[1, 2],
    )  # fmt: skip
    out = np.empty(3)
    for m in range(3):
        a, b = end_a[m], end_b[m]
        out[m] = (p[b, 0] - p[a, 0]) * nx + (p[b, 1] - p[a, 1]) * ny + (p[b, 2] - p[a, 2]) * nz
    return out


@numba.njit(cache=True, nogil=True)
def _chirality_values(
    p: NDArray[np.float64], end_a: NDArray[np.int64], end_b: NDArray[np.int64]
) -> NDArray[np.float64]:
    """15j-l, (r,): rod i's twist about the prism's axis n = cB - cA (the end triangles'
    centroids), h_i = n . ((a_i - cA) x (b_i - cB)); the mirror image negates each."""
    m = end_a.shape[0]
    ca = np.zeros(3)
    cb = np.zeros(3)
    for k in range(m):
        for i in range(3):
            ca[i] += p[end_a[k], i] / m
            cb[i] += p[end_b[k], i] / m
    out = np.empty(m)
    for k in range(m):
        a, b = end_a[k], end_b[k]
        x, y, z = _cross(
            p[a, 0] - ca[0], p[a, 1] - ca[1], p[a, 2] - ca[2],
            p[b, 0] - cb[0], p[b, 1] - cb[1], p[b, 2] - cb[2],
        )  # fmt: skip
        out[k] = (cb[0] - ca[0]) * x + (cb[1] - ca[1]) * y + (cb[2] - ca[2]) * z
    return out


@numba.njit(cache=True, nogil=True)
def _geometric_grad(
    p: NDArray[np.float64],
    end_a: NDArray[np.int64],
    end_b: NDArray[np.int64],
    i: int,
    scale: float,
    row: int,
    J: NDArray[np.float64],
    geo: Geo,
) -> None:
    """Add ``scale`` times the gradient of g_i (:func:`_geometric_values`) to J's row."""
    c = np.empty((3, 3))
    for m in range(3):
        c[m] = 0.5 * (p[end_a[m]] + p[end_b[m]])
    e1, e2, u = c[1] - c[0], c[2] - c[1], p[end_b[i]] - p[end_a[i]]
    g1, g2 = np.cross(e2, u), np.cross(u, e1)  # d g_i / d e1, d g_i / d e2
    gc = (-g1, g1 - g2, g2)  # d g_i / d c0, c1, c2; each centre the mean of two nodes
    for m in range(3):
        _grad(J, row, end_a[m], gc[m], 0.5 * scale, geo)
        _grad(J, row, end_b[m], gc[m], 0.5 * scale, geo)
    normal = np.cross(e1, e2)
    _grad(J, row, end_b[i], normal, scale, geo)
    _grad(J, row, end_a[i], normal, -scale, geo)


@numba.njit(cache=True, nogil=True)
def _chirality_grad(
    p: NDArray[np.float64],
    end_a: NDArray[np.int64],
    end_b: NDArray[np.int64],
    i: int,
    scale: float,
    row: int,
    J: NDArray[np.float64],
    geo: Geo,
) -> None:
    """Add ``scale`` times the gradient of h_i (:func:`_chirality_values`) to J's row."""
    m = end_a.shape[0]
    ca, cb = _centroid(p, end_a), _centroid(p, end_b)
    n, va, vb = cb - ca, p[end_a[i]] - ca, p[end_b[i]] - cb
    gn, ga, gb = np.cross(va, vb), np.cross(vb, n), np.cross(n, va)
    for k in range(m):  # through the centroids, each the mean of m nodes
        _grad(J, row, end_a[k], -(gn + ga) / m, scale, geo)
        _grad(J, row, end_b[k], (gn - gb) / m, scale, geo)
    _grad(J, row, end_a[i], ga, scale, geo)
    _grad(J, row, end_b[i], gb, scale, geo)


@numba.njit(cache=True, nogil=True)
def _sign_rows(
    p: NDArray[np.float64],
    ends: tuple[NDArray[np.int64], NDArray[np.int64]],
    sign: NDArray[np.float64],
    twist: bool,
    sw: float,
    row0: int,
    r: NDArray[np.float64],
    J: NDArray[np.float64],
    jac: bool,
    geo: Geo,
) -> None:
    """Row row0 + i: how far rod i's g_i (15g-i) or, with ``twist``, h_i (15j-l) has
    crossed to the other sign than the rest shape's; ``sign`` is that sign over the
    rest shape's magnitude, so the rows are shares of the rest value."""
    end_a, end_b = ends
    values = _chirality_values(p, end_a, end_b) if twist else _geometric_values(p, end_a, end_b)
    for i in range(values.shape[0]):
        v = -sign[i] * values[i]
        if v <= 0.0:
            continue
        r[row0 + i] = sw * v
        if jac and twist:
            _chirality_grad(p, end_a, end_b, i, -sw * sign[i], row0 + i, J, geo)
        elif jac:
            _geometric_grad(p, end_a, end_b, i, -sw * sign[i], row0 + i, J, geo)


@numba.njit(cache=True, nogil=True)
def _tilt_rows(
    U: NDArray[np.float64],
    up: NDArray[np.float64],
    tilt: NDArray[np.float64],
    sw: float,
    row0: int,
    r: NDArray[np.float64],
    J: NDArray[np.float64],
    jac: bool,
    E1: NDArray[np.float64],
    E2: NDArray[np.float64],
) -> None:
    """Row row0 + f: free rod f's axis along up, u_f . up, against ``tilt[f]`` (what its
    own accelerometer reads of up along its axis); NaN: not measured."""
    for f in range(U.shape[0]):
        if np.isnan(tilt[f]):
            continue
        r[row0 + f] = sw * (U[f] @ up - tilt[f])
        if jac:
            J[row0 + f, 5 * f + 3] = sw * (E1[f] @ up)
            J[row0 + f, 5 * f + 4] = sw * (E2[f] @ up)


@numba.njit(cache=True, nogil=True)
def _evaluate(
    C: NDArray[np.float64],
    U: NDArray[np.float64],
    E1: NDArray[np.float64],
    E2: NDArray[np.float64],
    prob: Problem,
    r: NDArray[np.float64],
    J: NDArray[np.float64],
    jac: bool,
) -> None:
    """Fill r (rows,) and, if ``jac``, J (rows, 5 F) at the rods' centres C and axes U
    (F, 3) with tangents E1, E2 (F, 3), for the arrays of ``prob``
    (:meth:`ShapeReconstructor._problem`)."""
    (base, node_rod, node_sign, half, rod_nodes, pairs, target, sw, slack, up, contact,
     zsign, clearance, spin_ref, end_a, end_b, sign_geo, sign_chi, tilt, fl, flags,
     ) = prob  # fmt: skip
    r[:] = 0.0
    if jac:
        J[:] = 0.0
    p = _node_positions(C, U, base, node_rod, node_sign, half)
    geo = (node_rod, node_sign, half, E1, E2)
    rows = _blocks(pairs.shape[0], p.shape[0], rod_nodes.shape[0])
    sc = fl[_SW_CONSTRAINT]
    _cable_rows(p, pairs, target, sw, slack, r, J, jac, geo)
    if flags[_GRAVITY]:
        _gravity_rows(p, up, contact, fl, flags[_PENETRATION] != 0, rows[0], r, J, jac, geo)
    else:
        _spin_row(C, spin_ref, fl[_SW_SPIN], rows[2], r, J, jac)
    if flags[_PRISM]:
        _zsign_rows(p, zsign, sc, rows[3], r, J, jac, geo)
    if flags[_PENETRATION]:
        _clearance_rows(p, rod_nodes, clearance, sc, rows[4], r, J, jac, geo)
    if flags[_GEOMETRIC]:
        _sign_rows(p, (end_a, end_b), sign_geo, False, sc, rows[5], r, J, jac, geo)
    if flags[_CHIRALITY]:
        _sign_rows(p, (end_a, end_b), sign_chi, True, sc, rows[6], r, J, jac, geo)
    if up @ up > 0.0:
        _tilt_rows(U, up, tilt, fl[_SW_TILT], rows[7], r, J, jac, E1, E2)


@numba.njit(cache=True, nogil=True)
def _retract(
    C: NDArray[np.float64],
    U: NDArray[np.float64],
    E1: NDArray[np.float64],
    E2: NDArray[np.float64],
    step: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Centres moved by the step, axes turned along their tangents and renormalised."""
    C2 = np.empty_like(C)
    U2 = np.empty_like(U)
    for f in range(C.shape[0]):
        C2[f] = C[f] + step[5 * f : 5 * f + 3]
        u = U[f] + step[5 * f + 3] * E1[f] + step[5 * f + 4] * E2[f]
        U2[f] = u / np.sqrt(u @ u)
    return C2, U2


@numba.njit(cache=True, nogil=True)
def _n_rows(prob: Problem) -> int:
    return _blocks(prob[5].shape[0], prob[0].shape[0], prob[4].shape[0])[-1]


@numba.njit(cache=True, nogil=True)
def _normal_equations(
    J: NDArray[np.float64], r: NDArray[np.float64], H: NDArray[np.float64], g: NDArray[np.float64]
) -> None:
    """H = J^T J and g = J^T r, in place, row by row skipping zeros (most constraint
    rows are zero; by hand, as at 10 columns BLAS's call costs more than the sums)."""
    n = J.shape[1]
    H[:] = 0.0
    g[:] = 0.0
    for i in range(J.shape[0]):
        for a in range(n):
            x = J[i, a]
            if x == 0.0:
                continue
            g[a] += x * r[i]
            for b in range(a, n):
                H[a, b] += x * J[i, b]
    for a in range(n):
        for b in range(a):
            H[a, b] = H[b, a]


@numba.njit(cache=True, nogil=True)
def _damped_step(
    H: NDArray[np.float64],
    g: NDArray[np.float64],
    lam: float,
    scale: NDArray[np.float64],
    L: NDArray[np.float64],
    step: NDArray[np.float64],
) -> bool:
    """step = -(H + lam diag(scale))^-1 g by Cholesky, in place; False if not positive
    definite (it is for lam > 0 unless H holds NaN)."""
    n = H.shape[0]
    for i in range(n):
        for j in range(i + 1):
            acc = H[i, j] + (lam * scale[i] if i == j else 0.0)
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            if i == j:
                if not acc > 0.0:
                    return False
                L[i, i] = np.sqrt(acc)
            else:
                L[i, j] = acc / L[j, j]
    for i in range(n):  # L y = -g
        acc = -g[i]
        for k in range(i):
            acc -= L[i, k] * step[k]
        step[i] = acc / L[i, i]
    for i in range(n - 1, -1, -1):  # L^T x = y
        acc = step[i]
        for k in range(i + 1, n):
            acc -= L[k, i] * step[k]
        step[i] = acc / L[i, i]
    return True


@numba.njit(cache=True, nogil=True)
def _lm(
    C: NDArray[np.float64],
    U: NDArray[np.float64],
    prob: Problem,
    max_iterations: int,
    xtol: float,
    ftol: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], int, bool]:
    """Levenberg-Marquardt (Marquardt's scaling) from C, U (F, 3). Returns the centres,
    axes, residuals there, iterations and whether it converged: a step or a gain below
    tolerance, or no step that lowers the cost (a minimum to precision)."""
    n_rows, n = _n_rows(prob), 5 * C.shape[0]
    r, r2 = np.zeros(n_rows), np.zeros(n_rows)
    J = np.zeros((n_rows, n))
    H, L = np.zeros((n, n)), np.zeros((n, n))
    g, step, scale = np.zeros(n), np.zeros(n), np.zeros(n)
    E1, E2 = _tangents(U)
    _evaluate(C, U, E1, E2, prob, r, J, True)
    cost, lam = 0.5 * (r @ r), 1e-2
    for it in range(1, max_iterations + 1):
        _normal_equations(J, r, H, g)
        top = 0.0
        for i in range(n):
            top = max(top, H[i, i])
        for i in range(n):
            scale[i] = max(H[i, i], 1e-9 * top + 1e-300)
        while lam < 1e10:
            if not _damped_step(H, g, lam, scale, L, step):
                return C, U, r, it, False
            C2, U2 = _retract(C, U, E1, E2, step)
            _evaluate(C2, U2, E1, E2, prob, r2, J, False)
            cost2 = 0.5 * (r2 @ r2)
            if cost2 < cost:
                break
            lam *= 4.0
        else:
            return C, U, r, it, True  # no step lowers the cost
        lam = max(0.25 * lam, 1e-10)
        gain = cost - cost2
        C, U, cost = C2, U2, cost2
        r, r2 = r2, r  # the residuals at the new C, U (they do not depend on the tangents)
        if np.max(np.abs(step)) < xtol or gain <= ftol * (cost + gain):
            return C, U, r, it, True
        E1, E2 = _tangents(U)
        _evaluate(C, U, E1, E2, prob, r, J, True)  # the Jacobian only where it is needed
    return C, U, r, max_iterations, False


@numba.njit(cache=True, nogil=True)
def _verdict(
    r: NDArray[np.float64],
    prob: Problem,
    converged: bool,
    max_residual: float,
    max_slack: int,
) -> tuple[int, float]:
    """What a solve's residuals ``r`` say (``_OK``, ``_NOT_FINITE``, ...; from 5 on, the
    constraint of ``_VIOLATED[code - 5]`` is broken by over 3 tolerances) and the RMS
    cable residual (m), a slack cable's counted at its slack margin."""
    sw, slack = prob[7], prob[8]
    acc, k, n_slack = 0.0, 0, 0
    for c in range(sw.shape[0]):
        if sw[c] > 0.0:
            acc += (r[c] / sw[c]) ** 2
            k += 1
            n_slack += r[c] <= -slack[c] * sw[c]
    rms = np.sqrt(acc / k) if k else 0.0
    if not np.all(np.isfinite(r)):
        return _NOT_FINITE, rms
    if not converged:
        return _NO_CONVERGENCE, rms
    if rms > max_residual:
        return _RESIDUAL, rms
    if n_slack > max_slack:
        return _SLACK, rms
    rows = _blocks(sw.shape[0], prob[0].shape[0], prob[4].shape[0])
    starts = (rows[1], rows[3], rows[4], rows[5], rows[6])
    ends = (rows[2], rows[4], rows[5], rows[6], rows[7])
    for b in range(5):
        # the penalties hold a feasible shape within a tolerance or so of its bounds
        if ends[b] > starts[b] and np.max(r[starts[b] : ends[b]]) > 3.0:
            return 5 + b, rms
    return _OK, rms


@numba.njit(cache=True, nogil=True)
def _best_spin(
    C: NDArray[np.float64], U: NDArray[np.float64], prob: Problem, n_angles: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """C, U turned about body z by the one of ``n_angles`` even angles of least cost."""
    r = np.zeros(_n_rows(prob))
    J = np.zeros((1, 1))
    best, best_C, best_U = np.inf, C, U
    for k in range(n_angles):
        a = 2.0 * np.pi * k / n_angles
        R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
        C2, U2 = C @ R.T, U @ R.T
        _evaluate(C2, U2, U2, U2, prob, r, J, False)  # tangents unused without a Jacobian
        cost = float(r @ r)
        if cost < best:
            best, best_C, best_U = cost, C2, U2
    return best_C, best_U


@numba.njit(cache=True, nogil=True)
def _search(
    warm: tuple[NDArray[np.float64], NDArray[np.float64]],
    rest: tuple[NDArray[np.float64], NDArray[np.float64]],
    normal: NDArray[np.float64],
    prob: Problem,
    slack_search: bool,
    settings: NDArray[np.float64],
) -> tuple[int, float, NDArray[np.float64], NDArray[np.float64], int]:
    """Solve from the warm start. Unless that is feasible at a cost of at most
    ``enough``, also from: its result's mirror image in the plane of ``normal`` (if it
    is infeasible: a mirrored warm start), the rest shape turned to fit gravity, and
    (``slack_search``) the warm result with each of its taut cables freed, then
    refitted. The feasible solution of least cost is kept, the warm one's cost lowered
    by ``margin`` (the shape moves little between solves).

    ``settings``: max iterations, xtol, ftol, max_residual, margin, enough, max_slack.
    Returns the verdict (the warm start's if none is feasible), RMS, C, U and the
    iterations of all starts."""
    max_it, xtol, ftol, max_residual, margin, enough = (
        int(settings[0]), settings[1], settings[2], settings[3], settings[4], settings[5],
    )  # fmt: skip
    max_slack = int(settings[6])
    sw, slack = prob[7], prob[8]
    wC, wU, r, iterations, ok = _lm(warm[0], warm[1], prob, max_it, xtol, ftol)
    first, first_rms = _verdict(r, prob, ok, max_residual, max_slack)
    if first == _OK and 0.5 * (r @ r) <= enough:
        return first, first_rms, wC, wU, iterations
    best = 0.5 * (r @ r) - margin if first == _OK else np.inf
    best_rms, best_C, best_U = first_rms, wC, wU
    taut = r[: sw.shape[0]] > -slack * sw + 1e-12  # in the warm result
    for k in range(-2, sw.shape[0] if slack_search else 0):
        if k == -2:
            if first == _OK:
                continue
            reflect = np.eye(3) - 2.0 * np.outer(normal, normal)
            C0, U0 = wC @ reflect, wU @ reflect
        elif k == -1:
            C0, U0 = _best_spin(rest[0], rest[1], prob, 24)
        elif sw[k] == 0.0 or not taut[k] or slack[k] == np.inf:
            continue  # unknown, slack already, or held taut by its motor
        else:
            keep, sw[k] = sw[k], 0.0
            C0, U0, _, it, _ = _lm(wC, wU, prob, max_it, xtol, ftol)
            sw[k] = keep
            iterations += it
        C, U, r, it, ok = _lm(C0, U0, prob, max_it, xtol, ftol)
        iterations += it
        code, rms = _verdict(r, prob, ok, max_residual, max_slack)
        if code == _OK and 0.5 * (r @ r) < best:
            best, best_rms, best_C, best_U = 0.5 * (r @ r), rms, C, U
    if best == np.inf:
        return first, first_rms, wC, wU, iterations
    return _OK, best_rms, best_C, best_U, iterations


@numba.njit(cache=True, nogil=True)
def _triangle_violation(
    n_nodes: int,
    rod_nodes: NDArray[np.int64],
    rod_lengths: NDArray[np.float64],
    pairs: NDArray[np.int64],
    target: NDArray[np.float64],
    margin: NDArray[np.float64],
    used: NDArray[np.bool_],
) -> tuple[int, float]:
    """A used cable that no shape can make as long as its target less its margin: the
    shortest path between its nodes along the rods and the other used cables (each as
    long as its target plus margin) is shorter. Returns (cable, that length) or (-1, 0)."""
    for c in range(pairs.shape[0]):
        if not used[c]:
            continue
        D = np.full((n_nodes, n_nodes), np.inf)
        for i in range(n_nodes):
            D[i, i] = 0.0
        for q in range(rod_nodes.shape[0]):
            a, b = rod_nodes[q, 0], rod_nodes[q, 1]
            D[a, b] = D[b, a] = min(D[a, b], rod_lengths[q])
        for k in range(pairs.shape[0]):
            if used[k] and k != c:
                a, b = pairs[k, 0], pairs[k, 1]
                D[a, b] = D[b, a] = min(D[a, b], target[k] + margin[k])
        for m in range(n_nodes):  # Floyd-Warshall
            for i in range(n_nodes):
                for j in range(n_nodes):
                    D[i, j] = min(D[i, j], D[i, m] + D[m, j])
        i, j = pairs[c, 0], pairs[c, 1]
        if target[c] - margin[c] > D[i, j]:
            return c, D[i, j]
    return -1, 0.0


@numba.njit(cache=True, nogil=True)
def _short_cables(
    p: NDArray[np.float64],
    pairs: NDArray[np.int64],
    target: NDArray[np.float64],
    margin: NDArray[np.float64],
    candidates: NDArray[np.bool_],
) -> NDArray[np.int64]:
    """The ``candidates`` cables shorter in ``p`` (n, 3) than their target less their
    margin, (k,) indices in order."""
    out = np.empty(pairs.shape[0], dtype=np.int64)
    n = 0
    for k in range(pairs.shape[0]):
        if candidates[k]:
            a, b = pairs[k, 0], pairs[k, 1]
            d0, d1, d2 = p[b, 0] - p[a, 0], p[b, 1] - p[a, 1], p[b, 2] - p[a, 2]
            if math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) < target[k] - margin[k]:
                out[n] = k
                n += 1
    return out[:n]


# ------------------------------------------------------------------------ the solver


def structure_problem(description: RobotDescription) -> str | None:
    """Why the shape solver, and so the invariant EKF, cannot serve ``description``, or
    None where it can: it needs a 3-bar prism (three rods whose actuated cables join
    their ends in two triangles, 15d-l), of any name, size and handedness."""
    d = description
    if d.n_rods != 3:
        return f"it needs a 3-bar prism (three rods); this robot has {d.n_rods} rods"
    if _prism_ends(d, 0) is None:
        return (
            "it needs a 3-bar prism whose actuated cables join the rods' ends in two "
            "triangles; this robot's actuated cables do not"
        )
    return None


def _prism_ends(
    d: RobotDescription, base_rod: int
) -> tuple[NDArray[np.int64], NDArray[np.int64]] | None:
    """Each rod's node on end A (the actuated triangle of the base rod's first node) and
    on end B, (3,) each; None unless the robot is a 3-bar prism of two such triangles."""
    if d.n_rods != 3 or d.n_nodes != 6:
        return None
    label = list(range(d.n_nodes))  # union-find over the actuated cables

    def root(i: int) -> int:
        while label[i] != i:
            i = label[i]
        return i

    for k in d.actuated:
        i, j = d.cable_nodes[k]
        label[root(int(i))] = root(int(j))
    end = root(int(d.rod_nodes[base_rod, 0]))
    in_a = np.array([root(i) == end for i in range(d.n_nodes)])
    rn = d.rod_nodes
    if not np.all(in_a[rn[:, 0]] != in_a[rn[:, 1]]) or in_a.sum() != 3:
        return None
    if len({root(i) for i in range(d.n_nodes)}) != 2:
        return None
    end_a = np.where(in_a[rn[:, 0]], rn[:, 0], rn[:, 1]).astype(np.int64)
    end_b = np.where(in_a[rn[:, 0]], rn[:, 1], rn[:, 0]).astype(np.int64)
    return end_a, end_b


def _body_frame(
    positions: NDArray[np.float64], base_nodes: NDArray[np.intp]
) -> NDArray[np.float64]:
    """World node positions (n, 3) in the frame of the rod ``base_nodes`` (2,) as the
    simulator builds it: origin at its centre, z along it (kinematics'
    ``rod_quaternion_from_axis``)."""
    a, b = positions[base_nodes[0]], positions[base_nodes[1]]
    axis = (b - a) / np.linalg.norm(b - a)
    R = quat_to_matrix(rod_quaternion_from_axis(axis))
    return np.asarray((positions - 0.5 * (a + b)) @ R)


class ShapeReconstructor:
    """Endcap positions in the body frame from cable distances and gravity (module doc).

    Args:
        description: the robot; 15d-l need a 3-bar prism (two actuated end triangles).
        config: see :class:`ShapeConfig`.
        base_rod: the rod whose frame (its IMU's) is the body frame.
    """

    def __init__(
        self, description: RobotDescription, config: ShapeConfig | None = None, base_rod: int = 0
    ) -> None:
        d = description
        config = ShapeConfig() if config is None else config
        if isinstance(base_rod, bool) or not isinstance(base_rod, (int, np.integer)):
            raise ValueError(f"base_rod must be a rod index, got {base_rod!r}")
        if not 0 <= base_rod < d.n_rods:
            raise ValueError(f"base_rod {base_rod} is not a rod of {d.name!r} ({d.n_rods} rods)")
        self.description, self.config, self.base_rod = d, config, int(base_rod)
        self._ends = _prism_ends(d, self.base_rod)
        if self._ends is None and (config.geometric or config.chirality):
            raise ValueError(
                f"{d.name!r} is not a 3-bar prism: ShapeConfig.geometric and .chirality "
                "(Tong et al. 2024 eq. 15g-l) do not apply to it; set them False"
            )
        self._layout()
        # The resting pose with every rod at its length exactly, as the solver builds shapes
        # (the YAML's positions are rounded to a micrometre).
        resting = _body_frame(d.initial_positions, d.rod_nodes[self.base_rod])
        self._rest = self._positions(*self._params(resting))
        rest_distances = member_lengths(d.initial_positions, d.cable_nodes)
        self._prestretch = rest_distances - d.rest_lengths
        sensors = d.sensors.cable_length
        sigma = sensors.noise if config.sensor_sigma is None else config.sensor_sigma
        self._sensor_sigma = max(sigma, 1e-6)  # a noiseless simulated sensor
        self._max_residual = (
            4.0 * self._sensor_sigma if config.max_residual is None else config.max_residual
        )
        self._bias = sensors.slack_bias
        # Where a slack reading (rest + bias) and a taut one (rest + the rest shape's
        # stretch) lie over 4 sigma apart a reading can be told slack, and is debiased.
        self._debias = np.abs(self._prestretch - self._bias) > 4.0 * self._sensor_sigma
        self._signs = self._rest_signs()
        self._rest_params = self._params(self._rest)
        # Cables whose motor keeps a minimum tension (reeling in slack): their distance is
        # the encoder's reading plus a stretch, never shorter (two-sided residuals).
        self._reeled = np.zeros(d.n_cables, dtype=bool)
        self._reeled[d.actuated] = np.isfinite(d.motor_min_stretch)
        self._constants()

    def _constants(self) -> None:
        """What every solve passes on unchanged, built once (a solve's setup in Python
        cost as much as the compiled search)."""
        c, d = self.config, self.description
        self._rod_nodes64 = d.rod_nodes.astype(np.int64)
        self._cable_nodes64 = d.cable_nodes.astype(np.int64)
        sigma = np.full(d.n_cables, c.rest_shape_sigma)
        sigma[d.actuated] = c.encoder_sigma
        self._model_weights = sigma**-2.0
        self._settings = np.array(
            [c.max_iterations, c.xtol, c.ftol, self._max_residual, c.switch_margin,
             c.search_cost, c.max_slack],
            dtype=np.float64,
        )  # fmt: skip
        fl = np.zeros(_N_FLOATS)
        fl[_SW_GRAVITY], fl[_SW_SPIN] = 1.0 / c.gravity_sigma, 1.0 / c.spin_sigma
        fl[_SW_CONSTRAINT], fl[_GROUND_TOL] = 1.0 / c.constraint_tolerance, 2.0 * c.gravity_sigma
        fl[_SW_TILT] = 1.0 / c.tilt_sigma
        self._floats = fl
        flags = np.zeros(_N_FLAGS, dtype=np.int64)
        flags[_PENETRATION] = c.non_penetration
        flags[_PRISM] = self._ends is not None
        flags[_GEOMETRIC], flags[_CHIRALITY] = c.geometric, c.chirality
        self._flags = flags
        self._end_nodes = self._ends or (np.zeros(0, np.int64), np.zeros(0, np.int64))

    def _layout(self) -> None:
        """Which free rod (-1: the base rod) and end (-1 first, +1 second) each node is."""
        d = self.description
        self._free = [q for q in range(d.n_rods) if q != self.base_rod]
        self._free_nodes = d.rod_nodes[self._free]
        self._free_rods = np.array(self._free, dtype=np.intp)
        self._node_rod = np.full(d.n_nodes, -1, dtype=np.int64)
        self._node_sign = np.zeros(d.n_nodes)
        self._half = np.array([0.5 * d.rods[q].length for q in self._free])
        self._base = np.zeros((d.n_nodes, 3))
        for f, q in enumerate(self._free):
            self._node_rod[d.rod_nodes[q]] = f
        for q in range(d.n_rods):
            self._node_sign[d.rod_nodes[q]] = (-1.0, 1.0)
        a, b = d.rod_nodes[self.base_rod]
        half = 0.5 * d.rods[self.base_rod].length
        self._base[a, 2], self._base[b, 2] = -half, half
        # Rods cross nowhere closer than their tubes let them (15g-i): the endcaps,
        # wider, are left to the cables that keep them apart.
        radius = np.array([r.radius for r in d.rods])
        self._clearance = radius[:, None] + radius[None, :]
        self._rod_lengths = np.array([r.length for r in d.rods])

    def _rest_signs(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Each node's end (-1: A, +1: B; 15d-e) and the rest shape's signs over
        magnitudes of 15g-i and 15j-l."""
        n = self.description.n_nodes
        if self._ends is None:
            return np.zeros(n), np.zeros(3), np.zeros(3)
        end_a, end_b = self._ends
        zsign = np.zeros(n)
        zsign[end_a], zsign[end_b] = -1.0, 1.0
        g = _geometric_values(self._rest, end_a, end_b)
        h = _chirality_values(self._rest, end_a, end_b)
        if np.any(np.abs(g) < 1e-9) or np.any(np.abs(h) < 1e-9):
            raise ValueError(f"{self.description.name!r}: the rest shape is no twisted prism")
        return zsign, 1.0 / g, 1.0 / h

    def rest_shape(self) -> NDArray[np.float64]:
        """The description's resting pose in the body frame (n_nodes, 3), m."""
        return self._rest.copy()

    # ------------------------------------------------------------------ measurements

    def cable_distances(
        self, rest_lengths: NDArray[np.float64], cable_lengths: NDArray[np.float64] | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The endcap-to-endcap distances (m) the measurements imply and their weights
        (1 / m^2), each (n_cables,).

        Cables attach at the endcap centres (the nodes), so a taut cable's distance is
        its rest length plus its stretch, tension / stiffness. The encoders give the
        actuated cables' rest lengths (m,); the stretch is taken as the rest shape's
        (its pre-stretch), with ``encoder_sigma`` for how the tension varies. A passive
        cable without a sensor has its rest-shape distance (``rest_shape_sigma``).

        ``cable_lengths`` (n_cables,), the stretch sensors, are fused with those by
        inverse variance. A slack cable's sensor reads its rest length plus the slack
        bias; where that reading lies over 4 sigma from a taut one at the rest shape's
        stretch (the passive cables of the presets), a reading nearer the slack one is
        debiased to the rest length. Elsewhere (the actuated cables, whose working
        stretch is about the bias) it is kept: the solver treats every distance as an
        upper bound a slack cable may fall short of. A reading that is not finite is
        left out.
        """
        d = self.description
        act = d.actuated
        enc = np.asarray(rest_lengths, dtype=np.float64)
        if enc.shape != (d.n_actuated,):
            raise ValueError(f"rest_lengths must be ({d.n_actuated},), got {enc.shape}")
        rest = d.rest_lengths.copy()
        rest[act] = enc
        model = rest + self._prestretch
        w_model = self._model_weights
        if cable_lengths is None:
            return model, w_model.copy()
        s = np.array(cable_lengths, dtype=np.float64)
        if s.shape != (d.n_cables,):
            raise ValueError(f"cable_lengths must be ({d.n_cables},), got {s.shape}")
        slack = self._debias & (np.abs(s - rest - self._bias) < np.abs(s - model))
        s[slack] -= self._bias
        # A reading that is not finite (a sensor missing) leaves its cable to the model.
        read = np.isfinite(s)
        w_sensor = np.where(read, self._sensor_sigma**-2.0, 0.0)
        weights = w_model + w_sensor
        return (w_model * model + w_sensor * np.where(read, s, 0.0)) / weights, weights

    # ------------------------------------------------------------------ solving

    def solve(
        self,
        distances: NDArray[np.float64],
        weights: NDArray[np.float64],
        up_body: NDArray[np.float64] | None = None,
        contacts: NDArray[np.bool_] | None = None,
        warm: NDArray[np.float64] | None = None,
        rod_up: NDArray[np.float64] | None = None,
    ) -> ShapeSolution:
        """The shape that best explains the cable ``distances`` (n_cables,) m with
        ``weights`` (n_cables,) 1/m^2 (0: unknown), under the constraints.

        Args:
            up_body: unit up vector (3,) in the body frame (e.g. the normalised
                low-passed accelerometer); None: the rotation about z is the warm start's.
            contacts: (n_nodes,) bool, the endcaps on the ground; None: the three lowest
                along ``up_body`` (a prism at rest stands on three endcaps).
            warm: (n_nodes, 3) body frame start, e.g. the last shape; None: the rest shape.
            rod_up: (n_rods, 3), each rod's up direction in its own frame (its own
                accelerometer's, like ``up_body``; any length but 0), rows of NaN where
                unknown; not in the paper. Only the component along the rod is used
                (u . up, how far the rod tilts), which pins what the cables leave loose;
                needs ``up_body``.

        Where the warm start's fit is infeasible or costs more than ``search_cost``,
        the mirror image of its result (if infeasible), the rest shape turned to fit
        gravity and (``slack_search``) each cable let slack in turn are tried too; the
        feasible fit of least cost is kept. A failed solution has NaN positions and
        says why.
        """
        n = self.description.n_nodes
        target, w = self._checked(distances, weights)
        up = None if up_body is None else self._unit(up_body)
        start = self._rest if warm is None else np.asarray(warm, dtype=np.float64)
        if start.shape != (n, 3):
            raise ValueError(f"warm must be ({n}, 3), got {start.shape}")
        tilt = self._tilts(rod_up, up)
        margin = self._margin(w)
        why = self._implausible(target, w, start, margin)
        if why is not None:
            return self._failed(why, 0)
        if contacts is not None:
            mask = np.asarray(contacts, dtype=bool)
            if mask.shape != (n,):
                raise ValueError(f"contacts must be ({n},) bool, got {mask.shape}")
            return self._solve_from(start, target, w, margin, up, mask, tilt)
        mask = self._lowest(start, up)
        solution = self._solve_from(start, target, w, margin, up, mask, tilt)
        if not solution.converged or up is None:
            return solution
        lowest = self._lowest(solution.positions, up)
        if np.array_equal(lowest, mask):
            return solution
        # its own feet
        again = self._solve_from(solution.positions, target, w, margin, up, lowest, tilt)
        return again if again.converged else solution

    def _margin(self, w: NDArray[np.float64]) -> NDArray[np.float64]:
        """(n_cables,) m: how much shorter than its distance a cable may be before it is
        slack (``slack_sigmas`` of its noise); 0 where unknown (weight 0)."""
        used = w > 0.0
        return np.where(used, self.config.slack_sigmas / np.sqrt(np.where(used, w, 1.0)), 0.0)

    def _tilts(
        self, rod_up: NDArray[np.float64] | None, up: NDArray[np.float64] | None
    ) -> NDArray[np.float64]:
        """The free rods' measured u . up, (F,), NaN where not measured."""
        tilt = np.full(len(self._free), np.nan)
        if rod_up is None:
            return tilt
        v = np.asarray(rod_up, dtype=np.float64)
        if v.shape != (self.description.n_rods, 3):
            raise ValueError(f"rod_up must be ({self.description.n_rods}, 3), got {v.shape}")
        if up is None:
            raise ValueError("rod_up needs up_body: a rod's tilt is measured against up")
        free = v[self._free_rods]
        norm = np.sqrt((free * free).sum(axis=1))
        np.divide(free[:, 2], norm, out=tilt, where=norm > 0.0)  # NaN stays where not
        return tilt

    def _checked(
        self, distances: NDArray[np.float64], weights: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        m = self.description.n_cables
        target = np.asarray(distances, dtype=np.float64)
        w = np.asarray(weights, dtype=np.float64)
        if target.shape != (m,) or w.shape != (m,):
            raise ValueError(f"distances and weights must be ({m},), got {target.shape}, {w.shape}")
        return target, w

    @staticmethod
    def _unit(v: NDArray[np.float64]) -> NDArray[np.float64]:
        up = np.asarray(v, dtype=np.float64)
        norm = float(np.linalg.norm(up)) if up.shape == (3,) else 0.0
        if not (math.isfinite(norm) and norm > 0.0):
            raise ValueError(f"up_body must be a finite non-zero (3,) vector, got {v!r}")
        return up / norm

    def _implausible(
        self,
        target: NDArray[np.float64],
        w: NDArray[np.float64],
        start: NDArray[np.float64],
        margin: NDArray[np.float64],
    ) -> str | None:
        """Why no shape can be solved for, before trying; None if one may be. ``margin``:
        :meth:`_margin` of ``w``."""
        if not (all_finite(target, w) and float(w.min()) >= 0.0):
            return "distances or weights not finite, or a weight negative"
        if not all_finite(start):
            return "warm start not finite"
        used = w > 0.0
        d = self.description
        cable, bound = _triangle_violation(
            d.n_nodes, self._rod_nodes64, self._rod_lengths, self._cable_nodes64, target,
            margin, used,
        )  # fmt: skip
        if cable < 0:
            return None
        return (
            f"cable {d.cables[cable].name}'s distance {target[cable]:.3f} m is longer than "
            f"the rods and the other cables allow between its endcaps ({bound:.3f} m)"
        )

    def _lowest(
        self, positions: NDArray[np.float64], up: NDArray[np.float64] | None
    ) -> NDArray[np.bool_]:
        """The three endcaps lowest along ``up`` (none without it), (n_nodes,) bool."""
        mask = np.zeros(self.description.n_nodes, dtype=bool)
        if up is not None:
            mask[np.argsort(positions @ up, kind="stable")[:3]] = True
        return mask

    def _failed(self, why: str, iterations: int, rms: float = math.nan) -> ShapeSolution:
        nan = np.full((self.description.n_nodes, 3), np.nan)
        return ShapeSolution(nan, False, rms, iterations, why)

    def _solve_from(
        self,
        start: NDArray[np.float64],
        target: NDArray[np.float64],
        w: NDArray[np.float64],
        margin: NDArray[np.float64],
        up: NDArray[np.float64] | None,
        contacts: NDArray[np.bool_],
        tilt: NDArray[np.float64],
    ) -> ShapeSolution:
        """Search from ``start`` (:func:`_search`) and report what it found."""
        warm = self._params(start)
        prob = self._problem(target, w, margin, up, contacts, warm[0], tilt)
        code, rms, C, U, iterations = _search(
            warm, self._rest_params, self._mirror_normal(up), prob, self.config.slack_search,
            self._settings,
        )  # fmt: skip
        if code != _OK:
            return self._failed(self._why(code, rms), iterations, rms)
        positions = self._positions(C, U)
        return ShapeSolution(
            positions, True, rms, iterations, None, self._slack(positions, target, w, margin)
        )

    def _why(self, code: int, rms: float) -> str:
        c = self.config
        if code == _NOT_FINITE:
            return "the solve diverged (not finite)"
        if code == _NO_CONVERGENCE:
            return f"no convergence in {c.max_iterations} iterations"
        if code == _RESIDUAL:
            return f"cable residual {rms:.3f} m RMS exceeds max_residual {self._max_residual:.3g} m"
        if code == _SLACK:
            return f"more than max_slack={c.max_slack} cables slack: the distances do not fit"
        return f"constraint violated: {_VIOLATED[code - 5]}"

    def _problem(
        self,
        target: NDArray[np.float64],
        w: NDArray[np.float64],
        margin: NDArray[np.float64],
        up: NDArray[np.float64] | None,
        contacts: NDArray[np.bool_],
        spin_ref: NDArray[np.float64],
        tilt: NDArray[np.float64],
    ) -> Problem:
        """The kernels' arrays. Gravity fixes the spin about z when two endcaps touch,
        one off the z axis (a base-rod endcap's height pins the others' just as well);
        otherwise the free rods' centres keep ``spin_ref``'s (F, 3) rotation about z."""
        off_axis = contacts & (self._node_rod >= 0)
        gravity = up is not None and contacts.sum() >= 2 and bool(off_axis.any())
        sw = np.sqrt(w)
        slack = np.where(w > 0.0, margin, np.inf)
        slack[self._reeled] = np.inf  # a motor holding its cable taut: never slack
        flags = self._flags.copy()
        flags[_GRAVITY] = gravity
        ends = self._end_nodes
        zsign, sign_geo, sign_chi = self._signs
        return (
            self._base, self._node_rod, self._node_sign, self._half,
            self._rod_nodes64, self._cable_nodes64, target, sw, slack,
            np.zeros(3) if up is None else up, contacts, zsign, self._clearance,
            np.ascontiguousarray(spin_ref), ends[0], ends[1], sign_geo, sign_chi, tilt,
            self._floats, flags,
        )  # fmt: skip

    def _params(
        self, positions: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Free rods' centres and unit axes (F, 3) of node positions (n, 3)."""
        rn = self._free_nodes
        a, b = positions[rn[:, 0]], positions[rn[:, 1]]
        axis = b - a
        return 0.5 * (a + b), axis / np.linalg.norm(axis, axis=1, keepdims=True)

    def _positions(self, C: NDArray[np.float64], U: NDArray[np.float64]) -> NDArray[np.float64]:
        return _node_positions(C, U, self._base, self._node_rod, self._node_sign, self._half)

    @staticmethod
    def _mirror_normal(up: NDArray[np.float64] | None) -> NDArray[np.float64]:
        """The normal of the mirror plane through body z and ``up`` (x = 0 without it):
        the mirror image keeps every distance, the base rod and every height along up."""
        # z x up, written out (np.cross costs more than the rest of the solve's setup)
        normal = np.array([1.0, 0.0, 0.0]) if up is None else np.array([-up[1], up[0], 0.0])
        norm = float(np.linalg.norm(normal))
        return normal / norm if norm > 1e-9 else np.array([1.0, 0.0, 0.0])

    def _slack(
        self,
        positions: NDArray[np.float64],
        target: NDArray[np.float64],
        w: NDArray[np.float64],
        margin: NDArray[np.float64],
    ) -> tuple[int, ...]:
        candidates = (w > 0.0) & ~self._reeled
        short = _short_cables(positions, self._cable_nodes64, target, margin, candidates)
        return tuple(short.tolist())
