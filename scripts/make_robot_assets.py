"""Generate the robot description YAML assets from their design parameters.

Run once by a developer when a preset's design changes::

    python scripts/make_robot_assets.py

It computes the nominal node positions of each preset, the self-stress (force
densities that keep the net in equilibrium with no external load), the cable rest
lengths that give the chosen pretension, and turns the structure so that a face of
its convex hull lies on the ground. The YAML files are the only input the package
reads; this script is not imported by it. A file's ``gait`` section (found by
``scripts/find_gait.py``, not by this script) is kept as it is.
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy.linalg import null_space
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

ASSETS = Path(__file__).resolve().parents[1] / "tensegrity_gym" / "model" / "assets"


def prism_nodes(rod_length: float, height: float) -> np.ndarray:
    """Nodes of a 3-bar prism with the stable twist of 150 degrees, (6, 3)."""
    r = np.sqrt((rod_length**2 - height**2) / (2.0 - 2.0 * np.cos(np.radians(150.0))))
    bottom = [[r * np.cos(a), r * np.sin(a), 0.0] for a in np.radians([0.0, 120.0, 240.0])]
    top = [
        [r * np.cos(a + np.radians(150.0)), r * np.sin(a + np.radians(150.0)), height]
        for a in np.radians([0.0, 120.0, 240.0])
    ]
    # Node order: rod i joins node 2i (bottom) and 2i+1 (top).
    return np.array([p for i in range(3) for p in (bottom[i], top[i])])


def prism_topology() -> tuple[list[tuple[int, int]], list[tuple[int, int, bool]]]:
    rods = [(0, 1), (2, 3), (4, 5)]
    bottom, top = [0, 2, 4], [1, 3, 5]
    cables: list[tuple[int, int, bool]] = []
    for i in range(3):  # actuated "side" cables: the two end triangles
        cables.append((bottom[i], bottom[(i + 1) % 3], True))
    for i in range(3):
        cables.append((top[i], top[(i + 1) % 3], True))
    for i in range(3):  # passive cross cables: bottom i to top i-1
        cables.append((bottom[i], top[(i - 1) % 3], False))
    return rods, cables


def icosahedron_nodes(rod_length: float) -> np.ndarray:
    """The 6-bar tensegrity icosahedron, rods in parallel pairs, (12, 3)."""
    h, d = rod_length / 2.0, rod_length / 4.0
    nodes = []
    for s in (d, -d):  # rods along x at z = +-d
        nodes += [[-h, 0.0, s], [h, 0.0, s]]
    for s in (d, -d):  # rods along y at x = +-d
        nodes += [[s, -h, 0.0], [s, h, 0.0]]
    for s in (d, -d):  # rods along z at y = +-d
        nodes += [[0.0, s, -h], [0.0, s, h]]
    return np.array(nodes)


def icosahedron_topology(
    nodes: np.ndarray,
) -> tuple[list[tuple[int, int]], list[tuple[int, int, bool]]]:
    rods = [(2 * i, 2 * i + 1) for i in range(6)]
    rod_of = {n: i for i, (a, b) in enumerate(rods) for n in (a, b)}
    dist = {
        (i, j): float(np.linalg.norm(nodes[i] - nodes[j]))
        for i, j in itertools.combinations(range(12), 2)
        # Cables join rods of different axes; parallel rods are not joined.
        if rod_of[i] // 2 != rod_of[j] // 2
    }
    shortest = min(dist.values())
    pairs = sorted(p for p, v in dist.items() if abs(v - shortest) < 1e-9)
    assert len(pairs) == 24, len(pairs)
    # Closed faces: triangles of cables. Actuate the cables of four node-disjoint
    # closed faces, so every endcap drives exactly two actuated cables' ends, as on
    # SUPERball (one motor per endcap, 12 actuated cables).
    pair_set = set(pairs)
    triangles = [
        t
        for t in itertools.combinations(range(12), 3)
        if all(tuple(sorted(e)) in pair_set for e in itertools.combinations(t, 2))
    ]
    chosen: list[tuple[int, ...]] = []
    for combo in itertools.combinations(triangles, 4):
        if len({n for t in combo for n in t}) == 12:
            chosen = list(combo)
            break
    actuated = {tuple(sorted(e)) for t in chosen for e in itertools.combinations(t, 2)}
    cables = [(i, j, (i, j) in actuated) for i, j in pairs]
    return rods, cables


def self_stress(
    nodes: np.ndarray, rods: list[tuple[int, int]], cables: list[tuple[int, int, bool]]
) -> np.ndarray:
    """Force densities (cables first, then rods) of the self-stress state, cables > 0."""
    members = [(i, j) for i, j, _ in cables] + rods
    A = np.zeros((nodes.size, len(members)))
    for k, (i, j) in enumerate(members):
        u = nodes[j] - nodes[i]
        A[3 * i : 3 * i + 3, k] += u
        A[3 * j : 3 * j + 3, k] -= u
    basis = null_space(A)
    # The symmetric self-stress: least-squares fit to "all cables equal weight".
    target = np.r_[np.ones(len(cables)), np.zeros(len(rods))]
    coeffs, *_ = np.linalg.lstsq(basis[: len(cables)], target[: len(cables)], rcond=None)
    q = basis @ coeffs
    assert np.all(q[: len(cables)] > 0) and np.all(q[len(cables) :] < 0), q
    assert np.allclose(A @ q, 0.0, atol=1e-9)
    return q


def rest_on_face(nodes: np.ndarray, pick: str) -> np.ndarray:
    """Rotate so that one face of the convex hull lies on z = 0, centred at the origin."""
    hull = ConvexHull(nodes)
    centre = nodes.mean(axis=0)
    faces = []
    for simplex, eq in zip(hull.simplices, hull.equations, strict=True):
        normal = eq[:3]
        area = 0.5 * np.linalg.norm(np.cross(*(nodes[simplex[1:]] - nodes[simplex[0]])))
        faces.append((area, normal, simplex))
    if pick == "smallest":
        _, normal, _ = min(faces, key=lambda f: f[0])
    else:
        _, normal, _ = max(faces, key=lambda f: f[0])
    rot, _ = Rotation.align_vectors([[0.0, 0.0, -1.0]], [normal])
    out = rot.apply(nodes - centre)
    out[:, 2] -= out[:, 2].min()
    out[:, :2] -= out[:, :2].mean(axis=0)
    return out


def description(
    name: str,
    nodes: np.ndarray,
    rods: list[tuple[int, int]],
    cables: list[tuple[int, int, bool]],
    p: dict[str, Any],
) -> dict[str, Any]:
    q = self_stress(nodes, rods, cables)
    lengths = [float(np.linalg.norm(nodes[j] - nodes[i])) for i, j, _ in cables]
    tensions = q[: len(cables)] * np.array(lengths)
    tensions *= p["pretension"] / tensions.max()
    nodes = rest_on_face(nodes, p["face"])
    nodes[:, 2] += p["endcap_radius"]  # endcaps touch the ground, not sink into it
    node_names = [f"n{i}" for i in range(len(nodes))]
    out_cables = []
    for k, ((i, j, act), length, tension) in enumerate(zip(cables, lengths, tensions, strict=True)):
        kind = "actuated" if act else "passive"
        stiffness = p[f"{kind}_stiffness"]
        rest = length - tension / stiffness
        cable: dict[str, Any] = {
            "name": f"{'a' if act else 'p'}{k}",
            "nodes": [node_names[i], node_names[j]],
            "stiffness": stiffness,
            "damping": p[f"{kind}_damping"],
            "rest_length": round(float(rest), 5),
            "actuated": act,
        }
        if act:
            cable["motor"] = {
                "min_rest_length": round(float(rest * p["min_fraction"]), 5),
                "max_rest_length": round(float(rest * p["max_fraction"]), 5),
                "max_speed": p["motor_speed"],
            }
            if p.get("min_tension") is not None:  # the motor reels in slack
                cable["motor"]["min_tension"] = p["min_tension"]
        out_cables.append(cable)
    return {
        "name": name,
        # First: the package reads these three to register the env ids.
        "display_name": p["display_name"],
        "hardware": p["hardware"],
        "gravity": 9.81,
        # Some rolling and spinning resistance at the endcaps: with none, a rod rolls
        # about its own axis without loss and the resting robot never comes to rest.
        "ground": {
            "lateral_friction": p["friction"],
            "rolling_friction": round(0.005 * p["rod_length"], 5),
            "spinning_friction": round(0.005 * p["rod_length"], 5),
            "restitution": 0.0,
        },
        "nodes": [
            {"name": n, "position": [round(float(v), 6) for v in x]}
            for n, x in zip(node_names, nodes, strict=True)
        ],
        "rods": [
            {
                "name": color_name,
                "nodes": [node_names[i], node_names[j]],
                "length": p["rod_length"],
                "radius": p["rod_radius"],
                "endcap_radius": p["endcap_radius"],
                "mass": p["rod_mass"],
                "color": rgba,
            }
            for (i, j), (color_name, rgba) in zip(rods, p["colors"], strict=False)
        ],
        "cables": out_cables,
        "sensors": p["sensors"],
    }


COLORS = [
    ("red", [0.9, 0.1, 0.1, 1.0]),
    ("green", [0.1, 0.8, 0.1, 1.0]),
    ("blue", [0.1, 0.2, 0.9, 1.0]),
    ("yellow", [0.9, 0.85, 0.1, 1.0]),
    ("magenta", [0.85, 0.1, 0.85, 1.0]),
    ("cyan", [0.1, 0.85, 0.85, 1.0]),
]


def camera(position: list[float], target: list[float], near: float, far: float) -> dict[str, Any]:
    """An overhead RGB-D camera like Lu et al. 2022's, 320x240."""
    return {
        "position": position,
        "target": target,
        "up": [0.0, 0.0, 1.0],
        "width": 320,
        "height": 240,
        "vertical_fov": 58.0,
        "near": near,
        "far": far,
        "rate": 10.0,
        "depth_noise": 0.002,
        "depth_noise_quadratic": 0.0025,
    }


def sensors(
    scale: float,
    anchors_half: float,
    uwb_offset: float,
    camera: dict[str, Any],
    heights: tuple[float, float],
) -> dict[str, Any]:
    a = anchors_half
    anchor_xy = [(a, a), (0.0, a), (-a, a), (-a, 0.0), (-a, -a), (0.0, -a), (a, -a), (a, 0.0)]
    return {
        "imu": {
            "rate": 200.0,
            "mount": "rod_centre",
            "accel_noise": 0.043,
            "gyro_noise": 0.002,
            "accel_bias": 0.001,
            "gyro_bias": 0.001,
            "mag_noise": 1.0e-6,
            "magnetic_field": [2.0e-5, 0.0, -4.5e-5],  # tesla
            "ahrs_gain": 0.5,
        },
        "encoder": {"rate": 100.0, "resolution": round(1e-4 * scale, 6)},
        "cable_length": {
            "rate": 10.0,
            "noise": round(0.004 * scale, 5),
            "slack_bias": round(0.01 * scale, 5),
        },
        "uwb": {
            "rate": 15.0,
            "packet_spacing": 0.001,
            "module_offset": uwb_offset,
            "timestamp_noise": 1.0e-10,
            "clock_drift_ppm": 10.0,
            "offset_mean": 0.3,
            "offset_std": 0.05,
            "reject_fraction": [0.3, 0.7],
            "anchors": [
                [round(x, 3), round(y, 3), heights[k % 2]] for k, (x, y) in enumerate(anchor_xy)
            ],
        },
        "contact": {"rate": 100.0, "threshold": 0.002},
        "camera": camera,
    }


def main() -> None:
    small = {
        "rod_length": 0.325,
        "rod_radius": 0.01,
        "endcap_radius": 0.0175,
        "rod_mass": 0.16,
        "actuated_stiffness": 2000.0,
        "actuated_damping": 5.0,
        "passive_stiffness": 400.0,
        "passive_damping": 2.0,
        "pretension": 12.0,
        "min_fraction": 0.55,
        "max_fraction": 1.05,
        "motor_speed": 0.15,
        "friction": 0.8,
        "face": "largest",
        "display_name": "ThreeBar",
        "hardware": True,
        "colors": COLORS[:3],
        "sensors": sensors(
            1.0,
            1.5,
            0.0,
            camera([0.3, -1.1, 1.2], [0.3, 0.0, 0.0], 0.1, 5.0),
            (1.0, 0.2),
        ),
    }
    large = dict(small)
    k = 1.45 / 0.325
    large.update(
        {
            "display_name": "ThreeBarLarge",
            "hardware": False,
            "rod_length": 1.45,
            "rod_radius": 0.038,
            "endcap_radius": 0.06,
            "rod_mass": 4.0,
            "actuated_stiffness": 5000.0,
            "actuated_damping": 50.0,
            "passive_stiffness": 1000.0,
            "passive_damping": 20.0,
            "pretension": 120.0,
            "motor_speed": 0.3,
            # Tong et al. 2024 VI: "the motors are controlled to apply a minimum torque,
            # ensuring cables remain under tension and preventing slackness".
            "min_tension": 10.0,
            "sensors": sensors(
                k,
                5.0,
                0.0,
                camera([1.5, -4.5, 4.5], [1.5, 0.0, 0.0], 0.3, 15.0),
                (2.0, 0.3),
            ),
        }
    )
    # Tong et al. 2024 VI: "An IMU (VN-100) is attached at the center of the bar with red
    # endcaps"; the other rods carry none.
    large["sensors"]["imu"] = {**large["sensors"]["imu"], "rods": ["red"]}
    superball = {
        "rod_length": 1.5,
        "rod_radius": 0.025,
        "endcap_radius": 0.06,
        "rod_mass": 3.6,
        "actuated_stiffness": 3150.0,
        "actuated_damping": 50.0,
        "passive_stiffness": 1000.0,
        "passive_damping": 20.0,
        "pretension": 90.0,
        "min_fraction": 0.6,
        "max_fraction": 1.05,
        "motor_speed": 0.3,
        "friction": 0.8,
        "face": "largest",
        "display_name": "SuperBall",
        "hardware": True,
        "colors": COLORS,
        "sensors": sensors(
            4.0,
            4.75,
            0.1,
            camera([1.5, -5.0, 5.0], [1.5, 0.0, 0.0], 0.3, 15.0),
            (2.0, 0.3),
        ),
    }
    rods, cables = prism_topology()
    presets = {
        "three_bar": description("three_bar", prism_nodes(0.325, 0.2), rods, cables, small),
        "three_bar_large": description(
            "three_bar_large", prism_nodes(1.45, 0.2 * k), rods, cables, large
        ),
    }
    ico = icosahedron_nodes(1.5)
    rods6, cables6 = icosahedron_topology(ico)
    presets["superball"] = description("superball", ico, rods6, cables6, superball)
    for name, desc in presets.items():
        path = ASSETS / f"{name}.yaml"
        text = yaml.safe_dump(desc, sort_keys=False, default_flow_style=None, width=100)
        header = f"# {name}: generated by scripts/make_robot_assets.py; SI units (m, kg, s, N).\n"
        path.write_text(header + text + kept_gait(path))


def kept_gait(path: Path) -> str:
    """The ``gait`` section of the file at ``path`` (with its comment), or ""."""
    if not path.exists():
        return ""
    lines = path.read_text().splitlines(keepends=True)
    starts = [k for k, line in enumerate(lines) if line.startswith("gait:")]
    if not starts:
        return ""
    k = starts[0]
    while k > 0 and lines[k - 1].startswith("#"):
        k -= 1
    return "".join(lines[k:])


if __name__ == "__main__":
    main()
