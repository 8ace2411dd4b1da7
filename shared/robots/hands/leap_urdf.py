"""The project's LEAP hand (right) model: published kinematics + primitive collision shapes -> URDF.

No package on a registry carries a usable LEAP model, so the project writes its own. Sources:
- kinematics (joint origins, axes, limits, effort, velocity, link masses): LEAP_Hand_Sim
  `assets/leap_hand/robot.urdf` (MIT). Joint names are the published ones, "0".."15", which are also the
  Dynamixel motor ids of the real hand: index 0-3, middle 4-7, ring 8-11, thumb 12-15. In each finger
  joint "1" (palm -> mcp_joint) is the MCP flexion, "0" (mcp_joint -> pip) the abduction, "2" PIP and
  "3" DIP flexion.
- geometry: solid boxes and cylinders sized to the real hand. The outlines follow the collision boxes of
  MuJoCo Menagerie's `leap_hand` (MIT, same body frames) merged into solid blocks per part (motor, bracket,
  phalanx), plus a cylindrical rounded tip per finger: finger tips end 50 mm (thumb 55 mm) past the last
  joint, fingers are 20 mm thick and 35 mm wide, the palm is ~100 x 120 x 46 mm.
- inertia: each link's published mass spread over its primitives by volume; COM at the volume centroid.

The palm faces -z of `palm_lower`; fingers point along +x, the thumb along +y at q = 0. Finger tips point
along -y of their `fingertip*` frames.

Regenerate the asset with `python -m shared.robots.hands.leap_urdf` (tests check the committed file is current).
"""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ASSET_PATH = Path(__file__).resolve().parents[1] / "assets" / "leap_hand" / "leap_right.urdf"
ROBOT_NAME = "leap_hand_right"
HALF_PI = 1.5707963
EFFORT_NM = 0.95
VELOCITY_RAD_S = 8.48


@dataclass(frozen=True)
class Box:
    center: tuple[float, float, float]
    size: tuple[float, float, float]

    def volume(self) -> float:
        return float(np.prod(self.size))

    def inertia_about_center(self, mass: float) -> np.ndarray:
        x, y, z = self.size
        return mass / 12.0 * np.diag([y * y + z * z, x * x + z * z, x * x + y * y])


@dataclass(frozen=True)
class ZCylinder:
    """Cylinder with its axis along the link's z axis (URDF cylinders are z-aligned)."""

    center: tuple[float, float, float]
    radius: float
    length: float

    def volume(self) -> float:
        return math.pi * self.radius**2 * self.length

    def inertia_about_center(self, mass: float) -> np.ndarray:
        r, h = self.radius, self.length
        side = mass * (3 * r * r + h * h) / 12.0
        return np.diag([side, side, mass * r * r / 2.0])


Shape = Box | ZCylinder


def _span_box(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> Box:
    """Box given by its min and max corners (how the outlines below were measured)."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    center = (round((x0 + x1) / 2, 6), round((y0 + y1) / 2, 6), round((z0 + z1) / 2, 6))
    size = (round(x1 - x0, 6), round(y1 - y0, 6), round(z1 - z0, 6))
    return Box(center, size)


# Link geometry in each link's own frame. Finger parts are identical for index, middle and ring.
_FINGER_PARTS = {
    "mcp_joint": (  # knuckle bracket around the MCP axis + abduction motor behind it (dorsal side)
        _span_box((-0.010, -0.005, -0.003), (0.010, 0.021, 0.032)),
        _span_box((-0.0432, 0.017, 0.0046), (-0.0092, 0.062, 0.033)),
    ),
    "pip": (_span_box((-0.0095, -0.0132, -0.022), (0.0245, 0.0128, 0.0)),),  # abduction horn + bracket
    "dip": (  # proximal phalanx: bracket around the PIP axis + DIP motor
        _span_box((-0.010, -0.023, -0.002), (0.010, 0.0055, 0.032)),
        _span_box((-0.0095, -0.046, 0.002), (0.0245, -0.024, 0.028)),
    ),
    "fingertip": (  # distal phalanx + rounded tip (tip along -y)
        _span_box((-0.010, -0.040, -0.003), (0.010, 0.005, 0.032)),
        ZCylinder((0.0, -0.040, 0.0145), 0.010, 0.035),
    ),
}
_GEOMETRY = {
    "palm_lower": (
        _span_box((-0.060, -0.095, -0.0345), (-0.020, 0.025, 0.012)),  # plate behind the knuckles
        _span_box((-0.100, -0.095, -0.0345), (-0.060, -0.027, 0.012)),  # heel (the thumb motor sits beside it)
        _span_box((-0.020, -0.095, -0.028), (0.002, 0.021, 0.006)),  # MCP motor mounts
    ),
    "pip_4": (_span_box((-0.0245, -0.0132, -0.022), (0.0095, 0.0128, 0.0)),),
    "thumb_pip": (_span_box((-0.009, -0.0165, -0.023), (0.009, 0.0165, 0.0005)),),
    "thumb_dip": (_span_box((-0.010, -0.0095, -0.031), (0.010, 0.052, 0.001)),),
    "thumb_fingertip": (
        _span_box((-0.010, -0.045, -0.029), (0.010, 0.0095, 0.001)),
        ZCylinder((0.0, -0.045, -0.014), 0.010, 0.030),
    ),
}
for _suffix in ("", "_2", "_3"):
    for _part, _shapes in _FINGER_PARTS.items():
        _GEOMETRY[_part + _suffix] = _shapes

_MASS_KG = {"palm_lower": 0.237, "mcp_joint": 0.044, "pip": 0.032, "dip": 0.037, "fingertip": 0.016,
            "pip_4": 0.032, "thumb_pip": 0.003, "thumb_dip": 0.038, "thumb_fingertip": 0.049}

# (name, parent, child, xyz, rpy, lower, upper) in kinematic-tree order, as published.
_JOINTS = []
for _suffix, _y, _first in (("", 0.02305776, 0), ("_2", -0.02239224, 4), ("_3", -0.06784224, 8)):
    _JOINTS += [
        (str(_first + 1), "palm_lower", "mcp_joint" + _suffix, (-0.00709525, _y, -0.0187224),
         (HALF_PI, HALF_PI, 0.0), -0.314, 2.23),
        (str(_first), "mcp_joint" + _suffix, "pip" + _suffix, (-0.0122, 0.0381, 0.0145),
         (-HALF_PI, 0.0, HALF_PI), -1.047, 1.047),
        (str(_first + 2), "pip" + _suffix, "dip" + _suffix, (0.015, 0.0143, -0.013),
         (HALF_PI, -HALF_PI, 0.0), -0.506, 1.885),
        (str(_first + 3), "dip" + _suffix, "fingertip" + _suffix, (0.0, -0.0361, 0.0002),
         (0.0, 0.0, 0.0), -0.366, 2.042),
    ]
_JOINTS += [
    ("12", "palm_lower", "pip_4", (-0.06939525, -0.00124224, -0.0216224), (0.0, HALF_PI, 0.0), -0.349, 2.094),
    ("13", "pip_4", "thumb_pip", (0.0, 0.0143, -0.013), (HALF_PI, -HALF_PI, 0.0), -0.47, 2.443),
    ("14", "thumb_pip", "thumb_dip", (0.0, 0.0145, -0.017), (-HALF_PI, 0.0, 0.0), -1.20, 1.90),
    ("15", "thumb_dip", "thumb_fingertip", (0.0, 0.0466, 0.0002), (0.0, 0.0, 3.1415927), -1.34, 1.88),
]

_COLOURS = {"palm": (0.25, 0.25, 0.25, 1.0), "tip": (0.95, 0.95, 0.95, 1.0), "other": (0.1, 0.1, 0.1, 1.0)}


def _link_mass(link: str) -> float:
    finger_copy = link.endswith(("_2", "_3")) and link != "pip_4"
    return _MASS_KG[link[:-2] if finger_copy else link]


def _inertial(shapes: Sequence[Shape], mass: float) -> tuple[np.ndarray, np.ndarray]:
    """COM (volume centroid) and inertia about it, treating the primitives as disjoint solids."""
    volumes = np.array([s.volume() for s in shapes])
    centers = np.array([s.center for s in shapes])
    com = (volumes[:, None] * centers).sum(0) / volumes.sum()
    inertia = np.zeros((3, 3))
    for shape, volume, center in zip(shapes, volumes, centers, strict=True):
        m = mass * volume / volumes.sum()
        d = center - com
        inertia += shape.inertia_about_center(m) + m * (d @ d * np.eye(3) - np.outer(d, d))
    return com, inertia


def _fmt(values: Iterable[float]) -> str:
    return " ".join(f"{float(v):.6g}" for v in values)


def _add_geometry(parent: ET.Element, shape: Shape) -> None:
    ET.SubElement(parent, "origin", {"xyz": _fmt(shape.center), "rpy": "0 0 0"})
    geometry = ET.SubElement(parent, "geometry")
    if isinstance(shape, Box):
        ET.SubElement(geometry, "box", {"size": _fmt(shape.size)})
    else:
        ET.SubElement(geometry, "cylinder", {"radius": _fmt([shape.radius]), "length": _fmt([shape.length])})


def _link_element(name: str) -> ET.Element:
    shapes = _GEOMETRY[name]
    link = ET.Element("link", {"name": name})
    colour = "palm" if name == "palm_lower" else ("tip" if "fingertip" in name else "other")
    for shape in shapes:
        visual = ET.SubElement(link, "visual")
        _add_geometry(visual, shape)
        material = ET.SubElement(visual, "material", {"name": f"leap_{colour}"})
        ET.SubElement(material, "color", {"rgba": _fmt(_COLOURS[colour])})
    for shape in shapes:
        _add_geometry(ET.SubElement(link, "collision"), shape)
    mass = _link_mass(name)
    com, inertia = _inertial(shapes, mass)
    inertial = ET.SubElement(link, "inertial")
    ET.SubElement(inertial, "origin", {"xyz": _fmt(com), "rpy": "0 0 0"})
    ET.SubElement(inertial, "mass", {"value": _fmt([mass])})
    ET.SubElement(inertial, "inertia", {
        "ixx": _fmt([inertia[0, 0]]), "ixy": _fmt([inertia[0, 1]]), "ixz": _fmt([inertia[0, 2]]),
        "iyy": _fmt([inertia[1, 1]]), "iyz": _fmt([inertia[1, 2]]), "izz": _fmt([inertia[2, 2]]),
    })
    return link


def build_leap_urdf() -> str:
    """The LEAP right-hand URDF text (deterministic)."""
    robot = ET.Element("robot", {"name": ROBOT_NAME})
    robot.append(ET.Comment(" Generated by shared/robots/hands/leap_urdf.py - edit the tables there, not this file. "))
    robot.append(_link_element("palm_lower"))
    for name, parent, child, xyz, rpy, lower, upper in _JOINTS:
        robot.append(_link_element(child))
        joint = ET.SubElement(robot, "joint", {"name": name, "type": "revolute"})
        ET.SubElement(joint, "parent", {"link": parent})
        ET.SubElement(joint, "child", {"link": child})
        ET.SubElement(joint, "origin", {"xyz": _fmt(xyz), "rpy": _fmt(rpy)})
        ET.SubElement(joint, "axis", {"xyz": "0 0 -1"})
        ET.SubElement(joint, "limit", {"lower": _fmt([lower]), "upper": _fmt([upper]),
                                       "effort": _fmt([EFFORT_NM]), "velocity": _fmt([VELOCITY_RAD_S])})
    ET.indent(robot)
    return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"


def main() -> None:
    ASSET_PATH.parent.mkdir(parents=True, exist_ok=True)
    ASSET_PATH.write_text(build_leap_urdf())
    print(f"wrote {ASSET_PATH}")


if __name__ == "__main__":
    main()
