"""The robot as an MJCF model for MuJoCo, generated from the robot description alone.

No XML is written by hand for a robot: everything here is read from the
:class:`~tensegrity_gym.model.description.RobotDescription` (and the episode's terrain and
gravity), so MuJoCo and PyBullet simulate the same robot. The text imports nothing of
MuJoCo; :mod:`tensegrity_gym.sim.mujoco_world` compiles it.

- Each rod is a free body whose frame is the rod's (origin at its centre, z along it):
  a cylinder of the rod's radius between two endcap spheres, its mass at the centre with
  :attr:`Rod.inertia <tensegrity_gym.model.description.Rod.inertia>`, a site at each
  endcap (the nodes).
- Each cable is a spatial tendon between its two nodes' sites, pulled by a ``general``
  actuator whose force along the tendon is ``k * L0 - k * L - c * dL/dt`` (stiffness k,
  damping c, rest length L0), limited to pulling: ``forcerange`` ends at 0 (or at minus
  the motor's ``min_tension``, which holds the cable at that tension as the spool reels in
  slack). A passive cable's L0 is its control; an actuated cable's L0 is the actuator's
  activation, an integrator, its rate set each
  physics step so that it slews toward the command at the motor's speed limit (the
  world sets it). ``actearly`` has the force use the slewed rest length of the same step,
  as the PyBullet world's motors move before its cables pull.
- Contacts: every geom has the sliding, torsional (spinning) and rolling friction the
  PyBullet world's contacts have (:func:`contact_coefficients`; ``condim`` 6); that
  contact's restitution e sets its damping ratio ``-ln e / sqrt(pi^2 + ln^2 e)`` (a
  critically damped contact for e = 0).
- The ground is the plane z = 0, or a height field holding the terrain's heights: its
  ``nrow`` x ``ncol`` grid and size are in the text, the normalised heights are written
  into the compiled model (:func:`hfield_data`), as inline they would make a large map's
  text slow to parse.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from typing import TYPE_CHECKING

import numpy as np

from tensegrity_gym.model.kinematics import rod_quaternion_from_axis

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from tensegrity_gym.model.description import Ground, RobotDescription, Rod
    from tensegrity_gym.sim.terrain import Terrain

__all__ = [
    "HFIELD",
    "INTEGRATOR",
    "MIN_CONTACT_STEPS",
    "contact_coefficients",
    "hfield_data",
    "robot_mjcf",
    "site_name",
]

HFIELD = "terrain"
"""The name of the height field asset (and its geom) where the ground is a terrain."""
INTEGRATOR = "implicitfast"
"""MuJoCo's integrator for these models: the cables' damping is taken implicitly."""
_CONTACT_TIME_STEPS = 5.0
"""A contact's time constant in physics steps, by default."""
MIN_CONTACT_STEPS = 2.0
"""The shortest contact time constant, in physics steps, that MuJoCo integrates stably."""
_MIN_CONTACT_TIME = 0.005  # s: stiff enough that a resting robot sinks under a mm
_FLOOR_RGBA = "0.55 0.55 0.5 1"  # as the PyBullet world's floor
_ROD_RGBA = "0.3 0.3 0.3 1"
_MAX_FORCE = 1.0e9  # N: "no limit" on a cable's tension
_MIN_RELIEF = 1.0e-3  # m: the height field's elevation range where the map has none


def site_name(node: int) -> str:
    """The site at node ``node`` (an endcap), where cables attach."""
    return f"node{node}"


def _number(x: float) -> str:
    return repr(float(x))


def _vector(values: object) -> str:
    return " ".join(_number(v) for v in np.asarray(values, dtype=np.float64).ravel())


def _damping_ratio(restitution: float) -> float:
    """The contact damping ratio whose bounce keeps ``restitution`` of the speed."""
    if restitution <= 0.0:
        return 1.0
    log_e = math.log(min(restitution, 0.999))
    return -log_e / math.sqrt(math.pi * math.pi + log_e * log_e)


def contact_coefficients(ground: Ground) -> tuple[float, float, float, float]:
    """The sliding, spinning and rolling friction and the restitution of a contact as
    the PyBullet world makes them: it gives ground and rods alike the description's
    coefficients, and Bullet combines a pair's as ``mu_a mu_b`` (sliding),
    ``s_a mu_b + mu_a s_b`` (spinning, rolling) and ``e_a e_b`` (restitution). MuJoCo
    would take the larger of two geoms' instead, so each geom here gets the combined
    values: the two engines' contacts then pull and bounce alike."""
    mu = ground.lateral_friction
    return (
        mu * mu,
        2.0 * mu * ground.spinning_friction,
        2.0 * mu * ground.rolling_friction,
        ground.restitution * ground.restitution,
    )


def _contact(
    description: RobotDescription, time_step: float, contact_steps: float | None = None
) -> dict[str, str]:
    """The attributes every geom shares: friction, contact dimension, softness (the
    contact's time constant ``contact_steps`` physics steps; None: the default)."""
    sliding, spinning, rolling, restitution = contact_coefficients(description.ground)
    if contact_steps is None:
        time_constant = max(_CONTACT_TIME_STEPS * time_step, _MIN_CONTACT_TIME)
    else:
        time_constant = contact_steps * time_step
    return {
        "friction": _vector([sliding, spinning, rolling]),
        "condim": "6",
        "solref": _vector([time_constant, _damping_ratio(restitution)]),
    }


def _rod_body(
    world: ET.Element, description: RobotDescription, index: int, contact: dict[str, str]
) -> None:
    """One rod as a free body at its initial pose, its endcaps' sites named by node."""
    rod: Rod = description.rods[index]
    a, b = rod.nodes
    nodes = description.initial_positions
    axis = nodes[b] - nodes[a]
    x, y, z, w = rod_quaternion_from_axis(axis / np.linalg.norm(axis))
    body = ET.SubElement(
        world, "body", name=rod.name, pos=_vector(0.5 * (nodes[a] + nodes[b])),
        quat=_vector([w, x, y, z]),
    )  # fmt: skip
    ET.SubElement(body, "freejoint", name=f"{rod.name}_free")
    ET.SubElement(
        body, "inertial", pos="0 0 0", mass=_number(rod.mass), diaginertia=_vector(rod.inertia)
    )
    h = 0.5 * rod.length
    ET.SubElement(
        body, "geom", contact, type="cylinder", size=_vector([rod.radius, h]), rgba=_ROD_RGBA,
        mass="0",
    )  # fmt: skip
    for node, z_end in ((a, -h), (b, h)):
        ET.SubElement(
            body, "geom", contact, type="sphere", size=_number(rod.endcap_radius),
            pos=_vector([0.0, 0.0, z_end]), rgba=_vector(rod.color), mass="0",
        )  # fmt: skip
        ET.SubElement(body, "site", name=site_name(node), pos=_vector([0.0, 0.0, z_end]))


def _cables(root: ET.Element, description: RobotDescription) -> None:
    """The cables' tendons and the actuators that pull them."""
    tendons = ET.SubElement(root, "tendon")
    actuators = ET.SubElement(root, "actuator")
    least = np.zeros(description.n_cables)
    least[description.actuated] = np.nan_to_num(description.motor_min_stretch)
    for k, cable in enumerate(description.cables):
        width = "0.004" if cable.actuated else "0.002"
        tendon = ET.SubElement(tendons, "spatial", name=cable.name, width=width)
        for node in cable.nodes:
            ET.SubElement(tendon, "site", site=site_name(node))
        stiffness, damping = cable.stiffness, cable.damping
        attributes = {
            "name": cable.name,
            "tendon": cable.name,
            "gaintype": "fixed",
            "gainprm": _number(stiffness),
            "biastype": "affine",
            "biasprm": _vector([0.0, -stiffness, -damping]),
            "forcelimited": "true",
            "forcerange": _vector([-_MAX_FORCE, -stiffness * least[k]]),
        }
        if cable.actuated:
            attributes |= {"dyntype": "integrator", "actearly": "true"}
        ET.SubElement(actuators, "general", attributes)


def _ground(
    world: ET.Element, asset: ET.Element, terrain: Terrain | None, contact: dict[str, str]
) -> None:
    """The plane z = 0, or the terrain's height field placed over its map."""
    if terrain is None or terrain.is_flat:
        ET.SubElement(
            world, "geom", contact, name="floor", type="plane", size="0 0 1", material="floor"
        )
        return
    rows, cols = terrain.heights.shape
    x0, x1, y0, y1 = terrain.extent
    low, high = float(terrain.heights.min()), float(terrain.heights.max())
    relief = max(high - low, _MIN_RELIEF)  # a level map off z = 0 has none: MuJoCo wants some
    ET.SubElement(
        asset, "hfield", name=HFIELD, nrow=str(rows), ncol=str(cols),
        size=_vector([0.5 * (x1 - x0), 0.5 * (y1 - y0), relief, 0.1 * relief + 0.01]),
    )  # fmt: skip
    ET.SubElement(
        world, "geom", contact, name=HFIELD, type="hfield", hfield=HFIELD, material="floor",
        pos=_vector([0.5 * (x0 + x1), 0.5 * (y0 + y1), low]),
    )  # fmt: skip


def hfield_data(terrain: Terrain) -> NDArray[np.float32]:
    """The terrain's heights as MuJoCo's height field holds them: row-major with rows
    along y and columns along x (as :class:`Terrain` has them), scaled to [0, 1] of the
    field's elevation (``rows * cols``,)."""
    h = np.asarray(terrain.heights, dtype=np.float64)
    span = max(float(h.max() - h.min()), _MIN_RELIEF)
    scaled: NDArray[np.float32] = ((h - h.min()) / span).astype(np.float32).ravel()
    return scaled


def robot_mjcf(
    description: RobotDescription,
    *,
    time_step: float,
    gravity: NDArray[np.float64] | None = None,
    terrain: Terrain | None = None,
    contact_steps: float | None = None,
) -> str:
    """The MJCF text of ``description`` on ``terrain`` (None or flat: the plane z = 0)
    under ``gravity`` (3,) m/s^2 (default: the description's, straight down), stepped at
    ``time_step`` seconds. Rods start at the description's initial pose. The contacts'
    time constant is ``contact_steps`` physics steps, at least
    :data:`MIN_CONTACT_STEPS` (None: 5 steps and at least 5 ms)."""
    if contact_steps is not None and not contact_steps >= MIN_CONTACT_STEPS:
        raise ValueError(
            f"contact_steps must be at least {MIN_CONTACT_STEPS} (MuJoCo's stable minimum), "
            f"got {contact_steps!r}"
        )
    g = np.array([0.0, 0.0, -description.gravity]) if gravity is None else gravity
    root = ET.Element("mujoco", model=description.name)
    ET.SubElement(root, "compiler", angle="radian", autolimits="true")
    ET.SubElement(root, "option", timestep=_number(time_step), gravity=_vector(g),
                  integrator=INTEGRATOR)  # fmt: skip
    # extent 1: the visual's near and far planes are then in metres.
    ET.SubElement(root, "statistic", extent="1", center="0 0 0")
    asset = ET.SubElement(root, "asset")
    ET.SubElement(asset, "texture", name="grid", type="2d", builtin="checker",
                  rgb1="0.55 0.55 0.5", rgb2="0.5 0.5 0.45", width="64", height="64")  # fmt: skip
    length = description.characteristic_length
    ET.SubElement(asset, "material", name="floor", texture="grid",
                  texrepeat=_vector([1.0 / length, 1.0 / length]), texuniform="true",
                  rgba=_FLOOR_RGBA)  # fmt: skip
    world = ET.SubElement(root, "worldbody")
    ET.SubElement(world, "light", pos="0 0 10", dir="0 0 -1", directional="true")
    contact = _contact(description, time_step, contact_steps)
    _ground(world, asset, terrain, contact)
    for index in range(description.n_rods):
        _rod_body(world, description, index, contact)
    _cables(root, description)
    return ET.tostring(root, encoding="unicode")
