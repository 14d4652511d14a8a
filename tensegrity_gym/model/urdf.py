"""The robot as a URDF, for viewers (RViz's RobotModel, Foxglove's 3D panel).

A tensegrity has no joints between its rods that a URDF can state: the rods float,
held by cables. The URDF therefore has a root link ``world`` and one link per rod, each
attached to the root by a ``floating`` joint (which robot_state_publisher leaves alone:
the rods' poses come from ``/tf``, see :mod:`hardware.bag.scene`). A rod's link frame
is the rod's body frame: origin at the rod's centre, z along the rod. Its visuals are a
cylinder (the rod) and a sphere at each end (the endcaps), in the rod's colour; its
collisions are the same shapes (as the simulator builds the rod). Its ``<inertial>``
holds the rod's mass (kg) at its centre with a solid cylinder's inertia (kg m^2) of the
rod's radius and length, so that a physics engine loading it (PyBullet: a test checks)
gets the rods' masses instead of its defaults. Cables are not links; the markers draw them.
The root link ``world`` has no inertial: it is the fixed frame, not a body.

Built from the :class:`~tensegrity_gym.model.description.RobotDescription` alone.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from tensegrity_gym.model.description import RobotDescription, Rod

__all__ = ["ROOT_LINK", "robot_urdf"]

ROOT_LINK = "world"
"""The URDF's root link, the frame the rods' ``/tf`` transforms hang from."""


def _number(x: float) -> str:
    return f"{x:.6g}"


def _exact(x: float) -> str:
    """``x`` as the shortest text that reads back as the same float: a mass or an
    inertia is given as the description has it, not rounded for the eye."""
    return repr(float(x))


def _shape(
    link: ET.Element, kind: str, geometry: str, size: dict[str, float], z: float
) -> ET.Element:
    """A ``kind`` (``visual`` or ``collision``) element of ``link``: a ``geometry``
    (cylinder or sphere) of ``size`` (m) at height ``z`` (m) along the rod."""
    element = ET.SubElement(link, kind)
    ET.SubElement(element, "origin", xyz=f"0 0 {_number(z)}", rpy="0 0 0")
    shape = ET.SubElement(ET.SubElement(element, "geometry"), geometry)
    for key, value in size.items():
        shape.set(key, _number(value))
    return element


def _inertial(link: ET.Element, rod: Rod) -> None:
    """The rod's mass (kg) at its centre and its inertia tensor (kg m^2) about it
    (:attr:`Rod.inertia <tensegrity_gym.model.description.Rod.inertia>`)."""
    m = rod.mass
    across, _, along = rod.inertia
    inertial = ET.SubElement(link, "inertial")
    ET.SubElement(inertial, "origin", xyz="0 0 0", rpy="0 0 0")
    ET.SubElement(inertial, "mass", value=_exact(m))
    ET.SubElement(inertial, "inertia", ixx=_exact(across), ixy="0", ixz="0",
                  iyy=_exact(across), iyz="0", izz=_exact(along))  # fmt: skip


def _rod_link(robot: ET.Element, rod: Rod) -> None:
    """The rod's link (inertial; a cylinder and an endcap sphere at each end, seen and
    colliding) and its floating joint."""
    link = ET.SubElement(robot, "link", name=rod.name)
    _inertial(link, rod)
    shapes = [("cylinder", {"radius": rod.radius, "length": rod.length}, 0.0)]
    shapes += [("sphere", {"radius": rod.endcap_radius}, end * rod.length) for end in (-0.5, 0.5)]
    rgba = " ".join(_number(c) for c in rod.color)
    for geometry, size, z in shapes:
        visual = _shape(link, "visual", geometry, size, z)
        material = ET.SubElement(visual, "material", name=f"{rod.name}_colour")
        ET.SubElement(material, "color", rgba=rgba)
    for geometry, size, z in shapes:
        _shape(link, "collision", geometry, size, z)
    joint = ET.SubElement(robot, "joint", name=f"{ROOT_LINK}_to_{rod.name}", type="floating")
    ET.SubElement(joint, "parent", link=ROOT_LINK)
    ET.SubElement(joint, "child", link=rod.name)
    ET.SubElement(joint, "origin", xyz="0 0 0", rpy="0 0 0")


def robot_urdf(description: RobotDescription) -> str:
    """The URDF of ``description`` (see the module docstring), as XML text; ValueError
    for a rod named like the root link."""
    if any(rod.name == ROOT_LINK for rod in description.rods):
        raise ValueError(f"a rod named {ROOT_LINK!r} clashes with the URDF's root link")
    robot = ET.Element("robot", name=description.name)
    ET.SubElement(robot, "link", name=ROOT_LINK)
    for rod in description.rods:
        _rod_link(robot, rod)
    ET.indent(robot)
    return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"
