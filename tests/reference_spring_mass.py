"""A plain, slow reference of the UKF's spring-mass model: one state, a loop per member.

Written from the model's stated equations (estimation/ukf/spring_mass.py), not from its
code: it reads the robot's geometry, masses, cables and rest lengths from the
description itself, and takes from the model only the constants the model chooses
(substep, rod stiffness and damping, ground and contact penalties, smoothing width,
friction), so that a wrong member order or a wrong actuated-cable index in the model
shows up as a mismatch too.

Semi-implicit Euler per substep, all forces from the state at the start of it:

- member k between nodes (i, j): L = |x_j - x_i|, dL/dt = (x_j - x_i).(v_j - v_i) / L,
  tension T = max(0, K ramp(L - L0) + c dL/dt step(L - L0)) for a cable (it never
  pushes) and T = K (L - L0) + c dL/dt for a rod; node i gets (T / L)(x_j - x_i), node j
  the opposite;
  the actuated rest lengths are interpolated linearly at the middle of the substep;
- rod-rod contact: each rod is a tube of its radius between two endcap spheres; of every
  part of rod a against every part of rod b, the one that overlaps most (largest
  R - d) gives the closest points p(s) on rod a and q(t) on rod b, d = |p - q|, and the
  sum R of the two parts' radii; within R (plus the smoothing width) the normal force
  f = kc ramp(R - d) - cc (n.(v_p - v_q)) step(R - d), n = (p - q) / d, is applied only
  if positive, split between each rod's two nodes like a lever (1 - s, s and 1 - t, t);
- ground: penetration e = r - z, normal force fn = max(0, kg ramp(e) - cg v_z step(e));
- v += h (F / m + fn / m e_z - g e_z); then the horizontal velocity is scaled by
  1 / (1 + h mu fn / (m sqrt(|v_xy|^2 + slip^2))) (implicit regularised Coulomb);
  then x += h v.

ramp(u) is max(0, u) with its corner replaced by the parabola (u + w)^2 / (4 w) over
[-w, w]; step(u) is its slope.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from estimation.ukf.spring_mass import SpringMassModel
    from tensegrity_gym.model.description import RobotDescription, Rod


def ramp(u: float, w: float) -> float:
    if u <= -w:
        return 0.0
    if u >= w:
        return u
    return (u + w) ** 2 / (4.0 * w)


def step(u: float, w: float) -> float:
    if u <= -w:
        return 0.0
    if u >= w:
        return 1.0
    return (u + w) / (2.0 * w)


def closest_parameters(
    p0: NDArray[np.float64],
    p1: NDArray[np.float64],
    q0: NDArray[np.float64],
    q1: NDArray[np.float64],
) -> tuple[float, float, float]:
    """(s, t, distance) of the closest points p0 + s (p1 - p0) and q0 + t (q1 - q0).

    The obvious way: the interior stationary point of the squared distance if it lies in
    the unit square, else the best of the four edges, each a clamped 1-D minimum.
    Non-parallel segments only (the minimiser is then unique).
    """
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0

    def dist(s: float, t: float) -> float:
        return float(np.linalg.norm(r + s * d1 - t * d2))

    a, b, e = d1 @ d1, d1 @ d2, d2 @ d2
    c, f = d1 @ r, d2 @ r
    # Stationary point: [a -b; -b e] [s; t] = [-c; f].
    det = a * e - b * b
    candidates: list[tuple[float, float]] = []
    if det > 0.0:
        s = (b * f - c * e) / det
        t = (a * f - b * c) / det
        if 0.0 <= s <= 1.0 and 0.0 <= t <= 1.0:
            candidates.append((s, t))
    if not candidates:
        for t in (0.0, 1.0):  # edges t fixed: minimise over s
            candidates.append((min(max((t * b - c) / a, 0.0), 1.0), t))
        for s in (0.0, 1.0):  # edges s fixed: minimise over t
            candidates.append((s, min(max((s * b + f) / e, 0.0), 1.0)))
    s, t = min(candidates, key=lambda st: dist(*st))
    return s, t, dist(s, t)


def segment_parameter(
    p: NDArray[np.float64], q0: NDArray[np.float64], q1: NDArray[np.float64]
) -> float:
    """t of the point q0 + t (q1 - q0) closest to the point p."""
    d = q1 - q0
    return min(max(float((p - q0) @ d) / float(d @ d), 0.0), 1.0)


def deepest_touch(
    x: NDArray[np.float64], rod_a: Rod, rod_b: Rod
) -> tuple[float, float, float, float]:
    """(s, t, reach, distance) of the parts of two rods that overlap most: every pair of
    parts (tube or either endcap of rod a, the same of rod b), reach the sum of their
    radii, distance that of their closest points p(s) on rod a's axis, q(t) on rod b's."""
    a0, a1 = (x[i] for i in rod_a.nodes)
    b0, b1 = (x[i] for i in rod_b.nodes)
    best: tuple[float, float, float, float] | None = None
    for part_a in ("tube", 0.0, 1.0):
        for part_b in ("tube", 0.0, 1.0):
            if part_a == "tube" and part_b == "tube":
                s, t, _ = closest_parameters(a0, a1, b0, b1)
            elif part_b == "tube":
                s = float(part_a)
                t = segment_parameter(a0 + s * (a1 - a0), b0, b1)
            elif part_a == "tube":
                t = float(part_b)
                s = segment_parameter(b0 + t * (b1 - b0), a0, a1)
            else:
                s, t = float(part_a), float(part_b)
            reach = (rod_a.radius if part_a == "tube" else rod_a.endcap_radius) + (
                rod_b.radius if part_b == "tube" else rod_b.endcap_radius
            )
            dist = float(np.linalg.norm(a0 + s * (a1 - a0) - b0 - t * (b1 - b0)))
            if best is None or reach - dist > best[2] - best[3]:
                best = (s, t, reach, dist)
    assert best is not None
    return best


@dataclass
class Events:
    """What the reference met along the way, so a test can check it exercised each case."""

    slack_cable_steps: int = 0
    smoothed_cable_steps: int = 0
    clamped_cable_steps: int = 0
    """A taut cable shortening so fast that its damping would have pushed."""
    ground_contact_steps: int = 0
    rod_contact_steps: int = 0
    friction_steps: int = 0
    pairs_touching: set[tuple[int, int]] = field(default_factory=set)


def propagate_reference(
    model: SpringMassModel,
    state: NDArray[np.float64],
    duration: float,
    rest_start: NDArray[np.float64],
    rest_end: NDArray[np.float64] | None = None,
    events: Events | None = None,
) -> NDArray[np.float64]:
    """One state (6 n,) advanced by ``duration`` seconds; see the module docstring."""
    d = model.description
    ev = events if events is not None else Events()
    n = d.n_nodes
    state = np.array(state, dtype=np.float64)
    x = state[: 3 * n].reshape(n, 3).copy()
    v = state[3 * n :].reshape(n, 3).copy()
    if duration <= 0.0:
        return state
    mass = np.zeros(n)
    radius = np.zeros(n)
    for rod in d.rods:
        for node in rod.nodes:
            mass[node] += 0.5 * rod.mass
            radius[node] = rod.endcap_radius
    r_start = np.asarray(rest_start, dtype=np.float64)
    r_end = r_start if rest_end is None else np.asarray(rest_end, dtype=np.float64)
    actuated = [k for k, cable in enumerate(d.cables) if cable.actuated]
    n_cables = len(d.cables)
    rod_k = float(model.stiffness[n_cables])  # the model's choice for the rods
    rod_c = float(model.damping[n_cables])
    w = model.smoothing
    g = d.gravity
    kg, cg = model.ground_stiffness, model.ground_damping
    kc, cc = model.rod_contact_stiffness, model.rod_contact_damping
    mu, slip = model.friction, model.params.slip_speed

    n_steps = max(1, math.ceil(duration / model.substep - 1e-9))
    h = duration / n_steps
    for k_step in range(n_steps):
        frac = (k_step + 0.5) / n_steps
        force = np.zeros((n, 3))
        # Cables.
        for k, cable in enumerate(d.cables):
            i, j = cable.nodes
            rest = cable.rest_length
            if cable.actuated:
                a = actuated.index(k)
                rest = r_start[a] + frac * (r_end[a] - r_start[a])
            u = x[j] - x[i]
            length = float(np.linalg.norm(u))
            rate = float(u @ (v[j] - v[i])) / length
            stretch = length - rest
            ev.slack_cable_steps += stretch < 0.0
            ev.smoothed_cable_steps += abs(stretch) < w
            tension = cable.stiffness * ramp(stretch, w) + cable.damping * rate * step(stretch, w)
            ev.clamped_cable_steps += tension < 0.0
            tension = max(tension, 0.0)
            force[i] += tension / length * u
            force[j] -= tension / length * u
        # Rods as stiff bilateral members.
        for rod in d.rods:
            i, j = rod.nodes
            u = x[j] - x[i]
            length = float(np.linalg.norm(u))
            rate = float(u @ (v[j] - v[i])) / length
            tension = rod_k * (length - rod.length) + rod_c * rate
            force[i] += tension / length * u
            force[j] -= tension / length * u
        # Rod-rod contact where tubes or endcaps overlap most.
        for ra in range(d.n_rods):
            for rb in range(ra + 1, d.n_rods):
                a0, a1 = d.rods[ra].nodes
                b0, b1 = d.rods[rb].nodes
                s, t, reach, dist = deepest_touch(x, d.rods[ra], d.rods[rb])
                if dist >= reach + w:
                    continue
                normal = ((x[a0] + s * (x[a1] - x[a0])) - (x[b0] + t * (x[b1] - x[b0]))) / dist
                v_p = (1.0 - s) * v[a0] + s * v[a1]
                v_q = (1.0 - t) * v[b0] + t * v[b1]
                closing = float(normal @ (v_p - v_q))
                fn = kc * ramp(reach - dist, w) - cc * closing * step(reach - dist, w)
                if fn <= 0.0:
                    continue
                ev.rod_contact_steps += 1
                ev.pairs_touching.add((ra, rb))
                force[a0] += (1.0 - s) * fn * normal
                force[a1] += s * fn * normal
                force[b0] -= (1.0 - t) * fn * normal
                force[b1] -= t * fn * normal
        # Ground, gravity, friction; then the positions with the new velocities.
        for i in range(n):
            depth = radius[i] - x[i, 2]
            fn = max(kg * ramp(depth, w) - cg * v[i, 2] * step(depth, w), 0.0)
            ev.ground_contact_steps += fn > 0.0
            v[i] += h * force[i] / mass[i]
            v[i, 2] += h * (fn / mass[i] - g)
            sliding = math.sqrt(v[i, 0] ** 2 + v[i, 1] ** 2 + slip**2)
            shrink = 1.0 / (1.0 + h * mu * fn / (mass[i] * sliding))
            ev.friction_steps += shrink < 1.0
            v[i, :2] *= shrink
            x[i] += h * v[i]
    return np.concatenate([x.ravel(), v.ravel()])


def awkward_states(d: RobotDescription, rng: np.random.Generator) -> NDArray[np.float64]:
    """Six states (6, 6 n) near the resting shape, perturbed by 3 % of a rod length, at
    rest: in the first a node is pushed 2 cm under the ground, in the second the robot
    is shrunk by 10 % (its cables slack), in the third rod 1's centre is moved onto rod
    0's, half an endcap radius above it (the rods pressed together)."""
    x0 = np.concatenate([d.initial_positions.ravel(), np.zeros(3 * d.n_nodes)])
    states = x0 + 0.03 * d.characteristic_length * rng.standard_normal((6, x0.size))
    states[0, 2] -= 0.02
    states[1, : 3 * d.n_nodes] *= 0.9
    nodes = states[2, : 3 * d.n_nodes].reshape(-1, 3)
    (a0, a1), (b0, b1) = d.rod_nodes[0], d.rod_nodes[1]
    shift = 0.5 * (nodes[a0] + nodes[a1]) - 0.5 * (nodes[b0] + nodes[b1])
    nodes[[b0, b1]] += shift + np.array([0.0, 0.0, 0.5 * d.rods[0].endcap_radius])
    return np.asarray(states)
