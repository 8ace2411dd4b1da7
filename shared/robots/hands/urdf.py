"""URDF files for the robot models: locate packaged assets, write resolved copies, read structure, merge.

The hand and arm descriptions come from the `example-robot-data` wheel, whose meshes are referenced as
`package://example-robot-data/...`. Neither PyBullet nor pytorch_kinematics resolves ROS package URIs, so
every model is loaded from a *resolved copy*: absolute mesh paths, ROS-only tags stripped (ros2_control,
gazebo, transmission) and optionally a sub-tree pruned (the Franka gripper). Copies live in the cache
directory (`$GD2P_CACHE_DIR/urdf`, default `~/.cache/gd2p/urdf`), named by a hash of their inputs, and are
written atomically so concurrent workers never read a half-written file.

`read_urdf` parses the parts the models need (joints, collision primitives, inertial frames) into plain
dataclasses with 4x4 numpy transforms; `merge_urdf` attaches one robot to a link of another by a fixed joint.
"""
from __future__ import annotations

import hashlib
import importlib.metadata
import os
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from shared.atomic import atomic_write_text

CACHE_ENV = "GD2P_CACHE_DIR"
# Bump when the resolving/sanitising rules change so stale cached copies are not reused.
_RESOLVER_VERSION = "1"
_ROS_ONLY_TAGS = ("ros2_control", "gazebo", "transmission")
# Attributes urdf_parser_py (used by pytorch_kinematics) understands in <dynamics>; others only produce warnings.
_DYNAMICS_ATTRS = ("damping", "friction")


class RobotAssetError(RuntimeError):
    """A robot description is missing, unreadable or inconsistent."""


# ----------------------------------------------------------------------------------------------- locations


def cache_dir() -> Path:
    """Directory for generated URDFs (`$GD2P_CACHE_DIR/urdf`, default `~/.cache/gd2p/urdf`)."""
    root = Path(os.environ.get(CACHE_ENV) or Path.home() / ".cache" / "gd2p")
    path = root / "urdf"
    path.mkdir(parents=True, exist_ok=True)
    return path


def package_share_dir() -> Path:
    """The `cmeel.prefix/share` directory of the installed example-robot-data wheel (holds its packages)."""
    try:
        dist = importlib.metadata.distribution("example-robot-data")
    except importlib.metadata.PackageNotFoundError as exc:
        raise RobotAssetError("the 'example-robot-data' package is not installed (pip install example-robot-data)") from exc
    share = Path(str(dist.locate_file("cmeel.prefix/share")))
    if not (share / "example-robot-data" / "robots").is_dir():
        raise RobotAssetError(f"example-robot-data is installed but its robots directory is missing under {share}")
    return share


def example_robot_data_file(relative: str) -> Path:
    """Absolute path of a file inside example-robot-data's `robots/` folder, e.g. 'panda_description/urdf/panda.urdf'."""
    path = package_share_dir() / "example-robot-data" / "robots" / relative
    if not path.is_file():
        raise RobotAssetError(f"example-robot-data has no file robots/{relative}")
    return path


# ------------------------------------------------------------------------------------------ resolved copies


def resolved_urdf(source: Path, name: str, prune_below_link: str | None = None) -> Path:
    """Write (once) a copy of `source` loadable by PyBullet and pytorch_kinematics; return its path.

    `prune_below_link`: drop every joint and link below this link (it is kept), e.g. an arm's gripper.
    """
    text = Path(source).read_text()
    # The copy holds absolute mesh paths, so where the assets are installed is one of its inputs: two installs
    # (two clones' virtualenvs) sharing one cache must not load each other's meshes, which vanish with them.
    share = package_share_dir()
    key = content_key(text, name, prune_below_link or "", str(share), str(Path(source).resolve().parent))
    target = cache_dir() / f"{name}-{key}.urdf"
    if target.is_file():
        return target
    root = _parse_xml(text, str(source))
    _strip_ros_tags(root)
    _resolve_mesh_uris(root, share, Path(source).parent)
    if prune_below_link is not None:
        _prune_below(root, prune_below_link)
    atomic_write_text(target, _to_text(root))
    return target


def merge_urdf(parent_path: Path, child_path: Path, parent_link: str, transform: np.ndarray,
               joint_name: str, robot_name: str) -> str:
    """URDF text with `child`'s root link fixed to `parent_link` of `parent` at `transform` (4x4, parent_link→child root)."""
    parent = _parse_xml(Path(parent_path).read_text(), str(parent_path))
    child = _parse_xml(Path(child_path).read_text(), str(child_path))
    parent_links = {_attr(link, "name") for link in parent.iter("link")}
    if parent_link not in parent_links:
        raise RobotAssetError(f"{parent_path} has no link {parent_link!r} to attach to")
    clash = parent_links & {_attr(link, "name") for link in child.iter("link")}
    clash |= {_attr(j, "name") for j in parent.iter("joint")} & {_attr(j, "name") for j in child.iter("joint")}
    if clash:
        raise RobotAssetError(f"cannot merge {child_path} into {parent_path}: duplicate names {sorted(clash)}")
    child_root = read_urdf(child_path).root_link
    merged = ET.Element("robot", {"name": robot_name})
    material_names: set[str | None] = set()
    for element in list(parent) + list(child):
        if element.tag == "material":  # top-level materials are global: keep the first definition of a name
            if element.get("name") in material_names:
                continue
            material_names.add(element.get("name"))
        merged.append(element)
    joint = ET.SubElement(merged, "joint", {"name": joint_name, "type": "fixed"})
    ET.SubElement(joint, "parent", {"link": parent_link})
    ET.SubElement(joint, "child", {"link": child_root})
    xyz, rpy = matrix_to_xyz_rpy(transform)
    ET.SubElement(joint, "origin", {"xyz": _fmt(xyz), "rpy": _fmt(rpy)})
    return _to_text(merged)


def content_key(*parts: str) -> str:
    """Short stable hash naming a cached file after everything it was generated from."""
    digest = hashlib.sha256(_RESOLVER_VERSION.encode())
    for part in parts:
        digest.update(b"\0" + part.encode())
    return digest.hexdigest()[:12]


def _attr(element: ET.Element | None, key: str) -> str:
    """The attribute `key` a URDF element must have (RobotAssetError when it or the element is missing)."""
    value = None if element is None else element.get(key)
    if value is None:
        where = "a missing element" if element is None else f"<{element.tag}>"
        raise RobotAssetError(f"{where} has no {key!r} attribute")
    return value


def _parse_xml(text: str, origin: str) -> ET.Element:
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise RobotAssetError(f"{origin} is not valid XML: {exc}") from exc
    if root.tag != "robot":
        raise RobotAssetError(f"{origin} is not a URDF (root element <{root.tag}>)")
    return root


def _to_text(root: ET.Element) -> str:
    ET.indent(root)
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def _strip_ros_tags(root: ET.Element) -> None:
    for tag in _ROS_ONLY_TAGS:
        for element in root.findall(tag):
            root.remove(element)
    for dynamics in root.iter("dynamics"):
        for attr in list(dynamics.attrib):
            if attr not in _DYNAMICS_ATTRS:
                del dynamics.attrib[attr]


def _resolve_mesh_uris(root: ET.Element, share: Path, source_dir: Path) -> None:
    for mesh in root.iter("mesh"):
        uri = mesh.get("filename", "")
        if uri.startswith("package://"):
            path = share / uri[len("package://"):]
        elif uri.startswith("file://"):
            path = Path(uri[len("file://"):])
        else:
            path = (source_dir / uri).resolve()
        if not path.is_file():
            raise RobotAssetError(f"mesh {uri!r} not found (looked at {path})")
        mesh.set("filename", str(path))


def _prune_below(root: ET.Element, keep_link: str) -> None:
    children: dict[str, list[ET.Element]] = {}
    for joint in root.findall("joint"):
        children.setdefault(_attr(joint.find("parent"), "link"), []).append(joint)
    if keep_link not in {_attr(link, "name") for link in root.findall("link")}:
        raise RobotAssetError(f"cannot prune below unknown link {keep_link!r}")
    doomed_links: set[str] = set()
    stack = list(children.get(keep_link, []))
    while stack:
        joint = stack.pop()
        root.remove(joint)
        child = _attr(joint.find("child"), "link")
        doomed_links.add(child)
        stack.extend(children.get(child, []))
    for link in root.findall("link"):
        if link.get("name") in doomed_links:
            root.remove(link)


# ------------------------------------------------------------------------------------------------ reading


@dataclass(frozen=True)
class UrdfGeometry:
    """One collision/visual shape: kind in {'box','sphere','cylinder','mesh'}; box `size` is full extents."""

    kind: str
    size: tuple[float, float, float] = (0.0, 0.0, 0.0)
    radius: float = 0.0
    length: float = 0.0
    filename: str = ""


@dataclass(frozen=True)
class UrdfShape:
    link: str
    geometry: UrdfGeometry
    origin: np.ndarray  # 4x4, link frame -> shape frame


@dataclass(frozen=True)
class UrdfJoint:
    name: str
    kind: str  # revolute | continuous | prismatic | fixed
    parent: str
    child: str
    origin: np.ndarray  # 4x4, parent link frame -> child link frame at q = 0
    axis: np.ndarray
    lower: float
    upper: float
    velocity: float
    effort: float


@dataclass(frozen=True)
class UrdfRobot:
    name: str
    root_link: str
    links: tuple[str, ...]
    joints: tuple[UrdfJoint, ...]
    collisions: dict[str, tuple[UrdfShape, ...]] = field(default_factory=dict)
    inertial_origins: dict[str, np.ndarray] = field(default_factory=dict)  # link -> 4x4 (COM frame)
    masses: dict[str, float] = field(default_factory=dict)

    def joint(self, name: str) -> UrdfJoint:
        for joint in self.joints:
            if joint.name == name:
                return joint
        raise RobotAssetError(f"robot {self.name!r} has no joint {name!r}")

    @property
    def movable_joints(self) -> tuple[UrdfJoint, ...]:
        return tuple(j for j in self.joints if j.kind != "fixed")

    def parent_joint(self, link: str) -> UrdfJoint | None:
        return next((j for j in self.joints if j.child == link), None)


def read_urdf(path: Path) -> UrdfRobot:
    """Parse joints, collision shapes and inertial frames of a URDF file."""
    root = _parse_xml(Path(path).read_text(), str(path))
    links = tuple(_attr(link, "name") for link in root.findall("link"))
    joints = tuple(_read_joint(j) for j in root.findall("joint"))
    children = {j.child for j in joints}
    roots = [name for name in links if name not in children]
    if len(roots) != 1:
        raise RobotAssetError(f"{path} must have exactly one root link, found {roots}")
    collisions: dict[str, tuple[UrdfShape, ...]] = {}
    inertials: dict[str, np.ndarray] = {}
    masses: dict[str, float] = {}
    for link in root.findall("link"):
        name = _attr(link, "name")
        collisions[name] = tuple(
            UrdfShape(name, _read_geometry(c.find("geometry"), path), _read_origin(c.find("origin")))
            for c in link.findall("collision")
        )
        inertial = link.find("inertial")
        if inertial is not None:
            inertials[name] = _read_origin(inertial.find("origin"))
            mass = inertial.find("mass")
            masses[name] = float(_attr(mass, "value")) if mass is not None else 0.0
    return UrdfRobot(root.get("name", ""), roots[0], links, joints, collisions, inertials, masses)


def _read_joint(element: ET.Element) -> UrdfJoint:
    limit = element.find("limit")
    axis = element.find("axis")

    def get(key: str, default: float) -> float:
        return float(limit.get(key, default)) if limit is not None else default

    return UrdfJoint(
        name=_attr(element, "name"),
        kind=_attr(element, "type"),
        parent=_attr(element.find("parent"), "link"),
        child=_attr(element.find("child"), "link"),
        origin=_read_origin(element.find("origin")),
        axis=np.array([float(v) for v in _attr(axis, "xyz").split()]) if axis is not None else np.array([1.0, 0.0, 0.0]),
        lower=get("lower", 0.0),
        upper=get("upper", 0.0),
        velocity=get("velocity", 0.0),
        effort=get("effort", 0.0),
    )


def _read_geometry(element: ET.Element | None, path: Path) -> UrdfGeometry:
    shape = element[0] if element is not None and len(element) else None
    if shape is None:
        raise RobotAssetError(f"{path}: a collision element has no geometry")
    if shape.tag == "box":
        x, y, z = (float(v) for v in _attr(shape, "size").split())
        return UrdfGeometry("box", size=(x, y, z))
    if shape.tag == "sphere":
        return UrdfGeometry("sphere", radius=float(_attr(shape, "radius")))
    if shape.tag == "cylinder":
        return UrdfGeometry("cylinder", radius=float(_attr(shape, "radius")), length=float(_attr(shape, "length")))
    if shape.tag == "mesh":
        return UrdfGeometry("mesh", filename=_attr(shape, "filename"))
    raise RobotAssetError(f"{path}: unsupported geometry <{shape.tag}>")


def _read_origin(element: ET.Element | None) -> np.ndarray:
    xyz = [0.0, 0.0, 0.0]
    rpy = [0.0, 0.0, 0.0]
    if element is not None:
        xyz = [float(v) for v in element.get("xyz", "0 0 0").split()]
        rpy = [float(v) for v in element.get("rpy", "0 0 0").split()]
    return xyz_rpy_to_matrix(xyz, rpy)


# ------------------------------------------------------------------------------------------- conversions


def xyz_rpy_to_matrix(xyz: Sequence[float] | np.ndarray, rpy: Sequence[float] | np.ndarray) -> np.ndarray:
    """4x4 transform from a URDF origin (rpy = fixed-axis roll, pitch, yaw: R = Rz(y) Ry(p) Rx(r))."""
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_euler("xyz", rpy).as_matrix()
    matrix[:3, 3] = xyz
    return matrix


def matrix_to_xyz_rpy(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of xyz_rpy_to_matrix. At pitch = +-90 deg the angles are not unique; scipy then returns one
    valid decomposition (yaw folded into roll) that reproduces the rotation exactly, so its warning is noise."""
    matrix = np.asarray(matrix, dtype=np.float64)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Gimbal lock detected")
        rpy = Rotation.from_matrix(matrix[:3, :3]).as_euler("xyz")
    return matrix[:3, 3].copy(), rpy


def _fmt(values: Iterable[float]) -> str:
    return " ".join(f"{float(v):.10g}" for v in values)
