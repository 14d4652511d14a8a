"""The robot as a URDF, for viewers (RViz's RobotModel, Foxglove's 3D panel).

A tensegrity has no joints between its rods that a URDF can state: the rods float,
held by cables. The URDF therefore has a root link ``world`` and one link per rod, each
attached to the root by a ``floating`` joint (which robot_state_publisher leaves alone:
the rods' poses come from ``/tf``, see :mod:`hardware.bag.scene`). A rod's link frame
is the rod's body frame: origin at the rod's centre, z along the rod. Its visuals are a
cylinder (the rod) and a sphere at each end (the endcaps), in the rod's colour.
Cables are not links; the markers draw them.

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


def _visual(link: ET.Element, geometry: str, size: dict[str, float], z: float, rod: Rod) -> None:
    """A visual of ``link``: a ``geometry`` (cylinder or sphere) of ``size`` (m) at
    height ``z`` (m) along the rod, in the rod's colour."""
    visual = ET.SubElement(link, "visual")
    ET.SubElement(visual, "origin", xyz=f"0 0 {_number(z)}", rpy="0 0 0")
    shape = ET.SubElement(ET.SubElement(visual, "geometry"), geometry)
    for key, value in size.items():
        shape.set(key, _number(value))
    material = ET.SubElement(visual, "material", name=f"{rod.name}_colour")
    ET.SubElement(material, "color", rgba=" ".join(_number(c) for c in rod.color))


def _rod_link(robot: ET.Element, rod: Rod) -> None:
    """The rod's link (a cylinder, an endcap sphere at each end) and its floating joint."""
    link = ET.SubElement(robot, "link", name=rod.name)
    _visual(link, "cylinder", {"radius": rod.radius, "length": rod.length}, 0.0, rod)
    for end in (-0.5, 0.5):
        _visual(link, "sphere", {"radius": rod.endcap_radius}, end * rod.length, rod)
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
