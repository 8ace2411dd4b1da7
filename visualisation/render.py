"""CPU pictures of a scene: the table, objects, hands (or whole robots) and markers, from several views.

    from visualisation.render import HAND_COLORS, hand_item, mesh_item, push_markers, render_scene
    items = [mesh_item("object", obj.mesh, T_world_O), hand_item("pose 0", hand, pose_world, HAND_COLORS[0]),
             *push_markers(T_world_D, 0.20, 0.03)]
    render_scene(items, "scene.png", title="proc-box-001 · allegro")

Everything is drawn by PyBullet's TinyRenderer in a DIRECT client, so it works headless on a CPU with
no display or GPU. Items are plain data (a mesh, a URDF with joint angles, points, an arrow, a ring), so
the same function draws `gd2p show`'s pose pictures and the planner's storyboard frames.

Conventions and choices:
- World z is up and the table top is z = 0 (docs/architecture.md §Frames). The table is drawn as a finite slab sized
  to the scene, with a grid (`GRID_M`) for scale.
- Views are defined relative to a *heading* (the push direction's yaw): "side" looks at the push from
  its right so the push always reads left to right, whatever the direction in the world. A small world
  axes glyph (x red, y green) on the table shows how the scene sits in the world.
- Each view frames the items automatically (the camera distance is solved so that every mesh vertex and
  link bounding box is in the image, with a margin), or given `frame_points` so that several renders share
  one camera. Side and top views use a narrow field of view, close to an orthographic drawing.
- TinyRenderer ignores alpha. Items with alpha < 1 are made see-through by compositing: the scene is
  rendered with and without them, and their pixels are blended by alpha.
- TinyRenderer does not anti-alias; views are rendered `supersample` times larger and downsampled.
"""
from __future__ import annotations

import io
import math
import tempfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar, cast

import numpy as np
import pybullet as pb
import trimesh
from numpy.typing import ArrayLike
from PIL import Image

from shared.frames import invert_transform, matrix_to_quat_xyzw, pose25_to_matrix, transform_points, yaw_rotation
from shared.world.sim.scene import c_stdout_to_stderr, pos_quat_to_transform

if TYPE_CHECKING:
    from shared.robots.hands import HandModel

RGBA = tuple[float, float, float, float]

GRID_M = 0.05  # table grid spacing, stated in the picture's title
TABLE_MARGIN_M = 0.25  # table extends this far beyond the items: its edges stay out of most views
TABLE_THICKNESS_M = 0.012
TABLE_RGBA: RGBA = (0.87, 0.86, 0.83, 1.0)
GRID_RGBA: RGBA = (0.70, 0.70, 0.68, 1.0)
OBJECT_RGBA: RGBA = (0.42, 0.55, 0.78, 1.0)
MARKER_RGBA: RGBA = (0.12, 0.12, 0.12, 1.0)
# Distinct hand colours (matplotlib's tab10 without its blue, which is close to the object's colour).
HAND_COLORS: tuple[RGBA, ...] = (
    (1.00, 0.50, 0.05, 1.0), (0.17, 0.63, 0.17, 1.0), (0.84, 0.15, 0.16, 1.0), (0.58, 0.40, 0.74, 1.0),
    (0.55, 0.34, 0.29, 1.0), (0.89, 0.47, 0.76, 1.0), (0.74, 0.74, 0.13, 1.0), (0.09, 0.75, 0.81, 1.0),
)
# Contact-candidate colours by region kind (the prefix of ContactCandidates.region_names).
CANDIDATE_COLORS: dict[str, RGBA] = {
    "tip": (0.95, 0.05, 0.85, 1.0), "finger": (1.00, 0.90, 0.00, 1.0), "palm": (0.00, 0.90, 0.90, 1.0),
}
CANDIDATE_RADIUS_M = 0.0025
WORLD_X_RGBA: RGBA = (0.85, 0.10, 0.10, 1.0)
WORLD_Y_RGBA: RGBA = (0.10, 0.65, 0.10, 1.0)
AXES_LENGTH_M = 0.04
LIGHT_DIRECTION = (0.4, -0.6, 1.0)  # from the upper right of the side view: shadows fall behind, to the left
LIGHT_AMBIENT, LIGHT_DIFFUSE, LIGHT_SPECULAR = 0.5, 0.55, 0.05  # soft, matte: no glare spots on flat faces
_FRAMING_MARGIN = 1.10  # items fill about nine tenths of the tighter image dimension
_MIN_DEPTH_M = 0.02
_HIDDEN_Z_M = -1000.0  # where translucent bodies go while the scene behind them is rendered


class RenderError(ValueError):
    """A scene that cannot be drawn (unloadable URDF, unknown joint, empty scene, bad size or view)."""


# ----------------------------------------------------------------------------------------------- items


@dataclass(frozen=True, eq=False)
class MeshItem:
    """A rigid triangle mesh (an object, an obstacle); `transform` places its vertices in the world."""

    name: str
    vertices: np.ndarray  # [V,3] in the mesh's own frame
    faces: np.ndarray  # [F,3] vertex indices
    transform: np.ndarray = field(default_factory=lambda: np.eye(4))
    rgba: RGBA = OBJECT_RGBA


@dataclass(frozen=True, eq=False)
class UrdfItem:
    """An articulated body (a hand, an arm, an arm with its hand) at a base pose with joint angles.

    `base_transform` is the URDF base link frame in the world (not PyBullet's centre-of-mass frame).
    `rgba` None keeps the URDF's own colours.
    """

    name: str
    urdf_path: Path
    base_transform: np.ndarray
    joint_positions: Mapping[str, float] = field(default_factory=dict)
    rgba: RGBA | None = None


@dataclass(frozen=True, eq=False)
class PointsItem:
    """Small spheres at world points (contact candidates, keypoints)."""

    name: str
    points: np.ndarray  # [N,3]
    rgba: RGBA
    radius_m: float = CANDIDATE_RADIUS_M


@dataclass(frozen=True, eq=False)
class ArrowItem:
    """A flat arrow lying on the table from `start` to `end` (their z is ignored)."""

    name: str
    start: np.ndarray
    end: np.ndarray
    rgba: RGBA = MARKER_RGBA
    width_m: float = 0.008


@dataclass(frozen=True, eq=False)
class RingItem:
    """A flat ring on the table (a target and its tolerance)."""

    name: str
    centre: np.ndarray
    radius_m: float
    rgba: RGBA = MARKER_RGBA
    width_m: float = 0.004


Item = MeshItem | UrdfItem | PointsItem | ArrowItem | RingItem


def mesh_item(name: str, mesh: trimesh.Trimesh, transform: np.ndarray, rgba: RGBA = OBJECT_RGBA) -> MeshItem:
    """A MeshItem from a trimesh (e.g. `ObjectModel.mesh` in O with T_world_O)."""
    return MeshItem(name, np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64),
                    np.asarray(transform, dtype=np.float64), rgba)


def hand_item(name: str, hand: HandModel, pose_world: np.ndarray, rgba: RGBA | None) -> UrdfItem:
    """A hand (`shared.robots.hands.HandModel`) at a 25-d pose [p, r6, q] given in the world."""
    base, joints = pose25_to_matrix(np.asarray(pose_world, dtype=np.float64))
    joint_values = dict(zip(hand.joint_names, (float(q) for q in joints), strict=False))
    return UrdfItem(name, Path(hand.urdf_path), base, joint_values, rgba)


def candidate_items(name: str, hand: HandModel, pose_world: np.ndarray) -> list[PointsItem]:
    """The hand's contact candidates at a world pose, one PointsItem per region kind (tip, finger, palm)."""
    import torch  # only needed here: the renderer itself is numpy + PyBullet

    with torch.no_grad():
        state = hand.forward(torch.as_tensor(np.asarray(pose_world), dtype=torch.float32).reshape(1, -1))
        candidates_world, _ = hand.contact_candidates_world(state)
    points = candidates_world[0].double().numpy()
    cands = hand.contact_candidates
    kinds = np.array([region.split(":", 1)[0] for region in cands.region_names])[cands.region_index.numpy()]
    return [PointsItem(f"{name} {kind} candidates", points[kinds == kind], rgba)
            for kind, rgba in CANDIDATE_COLORS.items() if np.any(kinds == kind)]


def push_markers(T_world_D: np.ndarray, distance_m: float, tolerance_m: float,
                 rgba: RGBA = MARKER_RGBA) -> list[Item]:
    """An arrow along +x of D from the object's centre to the target, and a ring of the success tolerance."""
    T = np.asarray(T_world_D, dtype=np.float64)
    start, end = T[:3, 3], T[:3, 3] + distance_m * T[:3, 0]
    return [ArrowItem("push", start, end, rgba), RingItem("target", end, tolerance_m, rgba)]


# ----------------------------------------------------------------------------------------------- views


@dataclass(frozen=True)
class View:
    """A camera direction: azimuth from the heading (0 = looking back from the front, -90 = from the right).

    The camera sits on the ray from the scene's centre at `azimuth_deg` (counter-clockwise from the heading,
    in the table plane) and `elevation_deg` above the table, and looks at the centre.
    """

    name: str
    azimuth_deg: float
    elevation_deg: float
    fov_deg: float = 30.0
    label: str = ""

    @property
    def title(self) -> str:
        return self.label or self.name


VIEWS: dict[str, View] = {
    "iso": View("iso", -125.0, 32.0, 30.0, "iso"),
    "side": View("side", -90.0, 8.0, 14.0, "side (push →)"),
    "top": View("top", -90.0, 90.0, 14.0, "top (push →)"),
    "front": View("front", 0.0, 15.0, 20.0, "front (push toward the camera)"),
    "back": View("back", 180.0, 15.0, 20.0, "back (behind the hand)"),
}
DEFAULT_VIEWS: tuple[str, ...] = ("iso", "side", "top")


def views_by_name(names: Sequence[str]) -> list[View]:
    """Look up views by name; RenderError lists the known ones."""
    unknown = [n for n in names if n not in VIEWS]
    if unknown or not names:
        raise RenderError(f"unknown view(s) {unknown or names}; known views: {sorted(VIEWS)}")
    return [VIEWS[n] for n in names]


@dataclass(frozen=True)
class Camera:
    view_matrix: list[float]
    projection_matrix: list[float]


def frame_camera(view: View, points: np.ndarray, heading_deg: float, aspect: float) -> Camera:
    """A camera looking along `view` whose image just contains `points` [N,3] (with a margin)."""
    azimuth, elevation = math.radians(heading_deg + view.azimuth_deg), math.radians(view.elevation_deg)
    toward_eye = np.array([math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth),
                           math.sin(elevation)])
    forward = -toward_eye
    # Looking straight down, "up" in the image is the direction away from the camera's azimuth.
    up_hint = np.array([0.0, 0.0, 1.0]) if view.elevation_deg < 85 else -np.array([math.cos(azimuth), math.sin(azimuth), 0.0])
    right = np.cross(forward, up_hint)
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    centre = (points.min(axis=0) + points.max(axis=0)) / 2.0
    x, y = (points - centre) @ right, (points - centre) @ up
    centre = centre + right * (x.min() + x.max()) / 2.0 + up * (y.min() + y.max()) / 2.0
    offsets = points - centre
    x, y, depth = offsets @ right * _FRAMING_MARGIN, offsets @ up * _FRAMING_MARGIN, offsets @ forward
    tan_v = math.tan(math.radians(view.fov_deg) / 2.0)
    # A point at depth d (along forward, from the centre) is in view iff |x| <= tan_h (distance + d).
    distance = float(np.max(np.maximum(np.abs(x) / (tan_v * aspect), np.abs(y) / tan_v) - depth))
    distance = max(distance, float(np.max(-depth)) + _MIN_DEPTH_M)  # nothing at or behind the eye
    eye = centre + toward_eye * distance
    # The near plane stays close to the eye: the table reaches out toward the camera beyond the items.
    radius = float(np.linalg.norm(offsets, axis=1).max())
    near, far = min(_MIN_DEPTH_M, 0.02 * distance), distance + 4.0 * radius + 2.0 * TABLE_MARGIN_M + 1.0
    return Camera(pb.computeViewMatrix(eye.tolist(), centre.tolist(), up.tolist()),
                  pb.computeProjectionMatrixFOV(view.fov_deg, aspect, near, far))


# ----------------------------------------------------------------------------------------------- world


@dataclass
class RenderedView:
    """One view: RGB pixels and, per pixel, the index of the item drawn there (-1: table or background)."""

    view: View
    rgb: np.ndarray  # [H,W,3] uint8
    item_index: np.ndarray  # [H,W] int, at the rendered (supersampled) resolution


class RenderWorld:
    """The items loaded into a PyBullet DIRECT client, ready to be rendered from any camera.

    Use as a context manager. `body_ids[i]` are the PyBullet bodies of `items[i]` (for inspection).
    `heading_deg` is the yaw the views are relative to; the table and its grid are aligned with it.
    `frame_points` [N,3], when given, are framed instead of the items: several renders then share their
    cameras and table (e.g. a storyboard's frames, with the union of everything they show).
    """

    def __init__(self, items: Sequence[Item], *, heading_deg: float = 0.0, table: bool = True,
                 frame_points: np.ndarray | None = None):
        if not items:
            raise RenderError("nothing to render: the scene has no items")
        if not math.isfinite(heading_deg):
            raise RenderError(f"heading must be finite, got {heading_deg}")
        self.items = list(items)
        self.heading_deg = float(heading_deg)
        self.T_world_heading = _translation([0.0, 0.0, 0.0])
        self.T_world_heading[:3, :3] = yaw_rotation(math.radians(heading_deg))
        with c_stdout_to_stderr():  # PyBullet prints warnings on file descriptor 1
            self.client = pb.connect(pb.DIRECT)
        if self.client < 0:
            raise RenderError("could not start a PyBullet DIRECT client")
        try:
            self.body_ids: list[list[int]] = [self._add(item) for item in self.items]
            if frame_points is None:
                item_points = np.concatenate([self._framing_points(i) for i in range(len(self.items))])
            else:
                item_points = np.asarray(frame_points, dtype=np.float64).reshape(-1, 3)
                if len(item_points) == 0 or not np.all(np.isfinite(item_points)):
                    raise RenderError("frame_points must be a non-empty array of finite [N,3] points")
            # The world axes glyph (an L of two arrows) sits just outside the items' rear-left corner as seen
            # along the heading, framed with them; its bounding circle has radius AXES_LENGTH_M / 2 + ~1 cm.
            in_heading = transform_points(invert_transform(self.T_world_heading), item_points)
            reach = AXES_LENGTH_M / 2 + 0.012
            centre = transform_points(self.T_world_heading, np.array(
                [in_heading[:, 0].min() - reach, in_heading[:, 1].max() + reach, 0.0]))
            self.axes_origin = centre - np.array([AXES_LENGTH_M / 2, AXES_LENGTH_M / 2, 0.0])
            glyph = centre + reach * np.array([[-1.0, -1, 0], [1, -1, 0], [-1, 1, 0], [1, 1, 0]])
            self.framing_points = np.concatenate([item_points, glyph]) if table else item_points
            self.scenery_ids = self._add_table() if table else []
            self._item_of_body = self._body_lookup()
        except Exception:
            self.close()
            raise

    def close(self) -> None:
        if self.client >= 0:
            pb.disconnect(physicsClientId=self.client)
            self.client = -1

    def __enter__(self) -> RenderWorld:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------------------------ rendering

    def render(self, view: View, width: int, height: int, supersample: int = 2) -> RenderedView:
        """Render one view at width x height pixels (items framed automatically)."""
        if width < 16 or height < 16 or supersample < 1:
            raise RenderError(f"image size must be at least 16x16 and supersample >= 1, got {width}x{height}, {supersample}")
        camera = frame_camera(view, self.framing_points, self.heading_deg, width / height)
        big_w, big_h = width * supersample, height * supersample
        rgb, segmentation = self._capture(camera, big_w, big_h)
        item_index = self._item_of_body[segmentation]  # segmentation -1 (background) picks the last entry, -1
        rgb = self._blend_translucent(camera, big_w, big_h, rgb, item_index)
        image = Image.fromarray(rgb)
        if supersample > 1:
            image = image.resize((width, height), Image.Resampling.BOX)
        return RenderedView(view, np.asarray(image), item_index)

    def _body_lookup(self) -> np.ndarray:
        """Array mapping a PyBullet body id to its item index; its last entry (-1 = background) is -1."""
        highest = max((body for bodies in self.body_ids + [self.scenery_ids] for body in bodies), default=0)
        lookup = np.full(highest + 2, -1, dtype=np.int64)
        for index, bodies in enumerate(self.body_ids):
            lookup[bodies] = index
        return lookup

    def _capture(self, camera: Camera, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        _, _, rgba, _, segmentation = pb.getCameraImage(
            width, height, camera.view_matrix, camera.projection_matrix, shadow=1, lightDirection=LIGHT_DIRECTION,
            lightAmbientCoeff=LIGHT_AMBIENT, lightDiffuseCoeff=LIGHT_DIFFUSE, lightSpecularCoeff=LIGHT_SPECULAR,
            renderer=pb.ER_TINY_RENDERER, physicsClientId=self.client)
        rgb = np.asarray(rgba, dtype=np.uint8).reshape(height, width, 4)[:, :, :3]
        return rgb, np.asarray(segmentation).reshape(height, width)

    def _blend_translucent(self, camera: Camera, width: int, height: int, rgb: np.ndarray,
                           item_index: np.ndarray) -> np.ndarray:
        """Blend the pixels of items with alpha < 1 over a render of the scene without them."""
        alphas = np.array([_alpha(item) for item in self.items] + [1.0])  # last entry: index -1
        pixel_alpha = alphas[item_index]
        if np.all(pixel_alpha >= 1.0):
            return rgb
        hidden = [body for i, item in enumerate(self.items) if _alpha(item) < 1.0 for body in self.body_ids[i]]
        poses = {body: pb.getBasePositionAndOrientation(body, physicsClientId=self.client) for body in hidden}
        for body, (position, orientation) in poses.items():
            pb.resetBasePositionAndOrientation(body, [position[0], position[1], _HIDDEN_Z_M], orientation,
                                               physicsClientId=self.client)
        behind, _ = self._capture(camera, width, height)
        for body, (position, orientation) in poses.items():
            pb.resetBasePositionAndOrientation(body, position, orientation, physicsClientId=self.client)
        blended = pixel_alpha[..., None] * rgb + (1.0 - pixel_alpha[..., None]) * behind
        blended_rgb: np.ndarray = np.clip(np.rint(blended), 0, 255).astype(np.uint8)
        return blended_rgb

    # ------------------------------------------------------------------------------------ bodies

    def _add(self, item: Item) -> list[int]:
        if isinstance(item, MeshItem):
            return [self._add_mesh(item.vertices, item.faces, item.transform, item.rgba)]
        if isinstance(item, UrdfItem):
            return [self._add_urdf(item)]
        if isinstance(item, PointsItem):
            return self._add_points(item)
        if isinstance(item, ArrowItem):
            return self._add_arrow(item)
        if isinstance(item, RingItem):
            ring = trimesh.creation.annulus(item.radius_m - item.width_m / 2, item.radius_m + item.width_m / 2,
                                            height=0.002, sections=64)
            return [self._add_mesh(ring.vertices, ring.faces, _translation([item.centre[0], item.centre[1], 0.001]), item.rgba)]
        raise RenderError(f"cannot render an item of type {type(item).__name__}")

    def _add_mesh(self, vertices: np.ndarray, faces: np.ndarray, transform: np.ndarray, rgba: RGBA,
                  *, smooth: bool = True) -> int:
        """A visual-only body. `smooth` splits vertices at sharp edges so flat faces shade flat, curves smooth."""
        vertices, faces = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise RenderError(f"a mesh needs [V,3] vertices and [F,3] faces, got {vertices.shape} and {faces.shape}")
        mesh = trimesh.Trimesh(vertices, faces, process=False)
        if smooth:
            mesh = mesh.smooth_shaded
        shape = pb.createVisualShape(pb.GEOM_MESH, vertices=mesh.vertices.tolist(), indices=mesh.faces.reshape(-1).tolist(),
                                     normals=mesh.vertex_normals.tolist(), rgbaColor=list(rgba), physicsClientId=self.client)
        if shape < 0:
            raise RenderError(f"PyBullet rejected a mesh of {len(vertices)} vertices")
        position, quaternion = _pos_quat(transform)
        body: int = pb.createMultiBody(0.0, -1, shape, position, quaternion, physicsClientId=self.client)
        return body

    def _add_urdf(self, item: UrdfItem) -> int:
        path = Path(item.urdf_path)
        if not path.is_file():
            raise RenderError(f"{item.name}: URDF not found: {path}")
        try:
            with c_stdout_to_stderr():
                body: int = pb.loadURDF(str(path), physicsClientId=self.client)
        except pb.error as exc:
            raise RenderError(f"{item.name}: PyBullet cannot load {path}: {exc}") from exc
        # PyBullet's base pose is the base's centre-of-mass frame (docs/architecture.md §Simulation).
        local_position, local_orientation = pb.getDynamicsInfo(body, -1, physicsClientId=self.client)[3:5]
        com = np.asarray(item.base_transform, dtype=np.float64) @ pos_quat_to_transform(local_position, local_orientation)
        pb.resetBasePositionAndOrientation(body, *_pos_quat(com), physicsClientId=self.client)
        joints = _joint_indices(body, self.client)
        unknown = sorted(set(item.joint_positions) - set(joints))
        if unknown:
            raise RenderError(f"{item.name}: {path.name} has no joints {unknown}")
        for name, angle in item.joint_positions.items():
            pb.resetJointState(body, joints[name], float(angle), physicsClientId=self.client)
        if item.rgba is not None:
            for link in range(-1, pb.getNumJoints(body, physicsClientId=self.client)):
                pb.changeVisualShape(body, link, rgbaColor=list(item.rgba), physicsClientId=self.client)
        return body

    def _add_points(self, item: PointsItem) -> list[int]:
        points = np.asarray(item.points, dtype=np.float64).reshape(-1, 3)
        if len(points) == 0:
            return []
        shape = pb.createVisualShape(pb.GEOM_SPHERE, radius=item.radius_m, rgbaColor=list(item.rgba),
                                     physicsClientId=self.client)
        bodies = pb.createMultiBody(0.0, -1, shape, batchPositions=points.tolist(), physicsClientId=self.client)
        return list(bodies) if isinstance(bodies, (tuple, list)) else [bodies]

    def _add_arrow(self, item: ArrowItem) -> list[int]:
        start, end = np.asarray(item.start, dtype=np.float64)[:2], np.asarray(item.end, dtype=np.float64)[:2]
        length = float(np.linalg.norm(end - start))
        if length < 1e-6:
            raise RenderError(f"{item.name}: an arrow needs distinct start and end points")
        head = min(4.0 * item.width_m, 0.5 * length)
        shaft = trimesh.creation.box([length - head, item.width_m, 0.002])
        shaft.apply_translation([(length - head) / 2, 0.0, 0.0])
        tip = [(length, 0.0), (length - head, 1.5 * item.width_m), (length - head, -1.5 * item.width_m)]
        head_mesh = trimesh.convex.convex_hull(np.array([(x, y, z) for x, y in tip for z in (-0.001, 0.001)]))
        arrow = cast(trimesh.Trimesh, trimesh.util.concatenate([shaft, head_mesh]))  # meshes in, a mesh out
        yaw = math.atan2(*(end - start)[::-1])
        transform = _translation([start[0], start[1], 0.0015])
        transform[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
        return [self._add_mesh(arrow.vertices, arrow.faces, transform, item.rgba)]

    def _add_table(self) -> list[int]:
        """A square table slab under the items (top at z = 0), aligned with the heading, with a grid texture.

        The grid is a texture on one quad: TinyRenderer rasterises every triangle over its screen bounding
        box, so long thin grid-line boxes seen at an angle would cost a full-screen pass each. The table is
        square so that it still fills the top view when the image is wider than the items.
        """
        points = transform_points(invert_transform(self.T_world_heading), self.framing_points)[:, :2]
        centre = (points.min(axis=0) + points.max(axis=0)) / 2
        cells = int(np.ceil((np.ptp(points, axis=0).max() + 2 * TABLE_MARGIN_M) / GRID_M))
        half = cells * GRID_M / 2
        centre = np.round(centre / GRID_M) * GRID_M  # grid lines on round coordinates of the heading frame
        slab = trimesh.creation.box([2 * half, 2 * half, TABLE_THICKNESS_M])
        slab.apply_translation([*centre, -TABLE_THICKNESS_M / 2 - 2e-4])
        bodies = [self._add_mesh(slab.vertices, slab.faces, self.T_world_heading, TABLE_RGBA, smooth=False)]
        corners = [[centre[0] + sx * half, centre[1] + sy * half, 0.0] for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        top = pb.createVisualShape(pb.GEOM_MESH, vertices=corners, indices=[0, 1, 2, 0, 2, 3],
                                   uvs=[[0, 0], [1, 0], [1, 1], [0, 1]], normals=[[0, 0, 1]] * 4, physicsClientId=self.client)
        bodies.append(pb.createMultiBody(0.0, -1, top, *_pos_quat(self.T_world_heading), physicsClientId=self.client))
        pb.changeVisualShape(bodies[-1], -1, textureUniqueId=self._grid_texture(cells), rgbaColor=[1, 1, 1, 1],
                             physicsClientId=self.client)
        for axis, rgba in ((0, WORLD_X_RGBA), (1, WORLD_Y_RGBA)):
            end = self.axes_origin + AXES_LENGTH_M * np.eye(3)[axis]
            bodies += self._add_arrow(ArrowItem("world axis", self.axes_origin, end, rgba, width_m=0.005))
        return bodies

    def _grid_texture(self, cells: int) -> int:
        """A texture of cells x cells grid cells in the table colours."""
        pixels = max(4, min(32, 2048 // cells))
        image = np.empty((cells * pixels, cells * pixels, 3), dtype=np.uint8)
        image[:] = np.rint(np.array(TABLE_RGBA[:3]) * 255)
        line = np.rint(np.array(GRID_RGBA[:3]) * 255)
        image[::pixels, :], image[:, ::pixels] = line, line
        image[-1, :], image[:, -1] = line, line
        with tempfile.TemporaryDirectory(prefix="gd2p-render-") as directory:
            path = Path(directory) / "grid.png"
            Image.fromarray(image).save(path)
            texture: int = pb.loadTexture(str(path), physicsClientId=self.client)
        if texture < 0:
            raise RenderError("PyBullet could not load the table texture")
        return texture

    def _framing_points(self, index: int) -> np.ndarray:
        """World points that bound item `index` (what the cameras must show): vertices, link boxes, centres."""
        item, bodies = self.items[index], self.body_ids[index]
        if isinstance(item, MeshItem):
            return transform_points(item.transform, item.vertices)
        if isinstance(item, UrdfItem):
            links = range(-1, pb.getNumJoints(bodies[0], physicsClientId=self.client))
            boxes = [pb.getAABB(bodies[0], link, physicsClientId=self.client) for link in links]
            return np.array([[x, y, z] for low, high in boxes for x in (low[0], high[0]) for y in (low[1], high[1])
                             for z in (low[2], high[2])])
        if isinstance(item, PointsItem):
            return np.asarray(item.points, dtype=np.float64).reshape(-1, 3)
        if isinstance(item, ArrowItem):
            return np.array([[*item.start[:2], 0.0], [*item.end[:2], 0.0]])
        reach = item.radius_m + item.width_m
        return np.array([[item.centre[0] + dx, item.centre[1] + dy, 0.0] for dx in (-reach, reach) for dy in (-reach, reach)])


def _alpha(item: Item) -> float:
    rgba = getattr(item, "rgba", None)
    return 1.0 if rgba is None else float(rgba[3])


def _joint_indices(body: int, client: int) -> dict[str, int]:
    out = {}
    for j in range(pb.getNumJoints(body, physicsClientId=client)):
        info = pb.getJointInfo(body, j, physicsClientId=client)
        if info[2] in (pb.JOINT_REVOLUTE, pb.JOINT_PRISMATIC):
            out[info[1].decode()] = j
    return out


def _translation(xyz: ArrayLike) -> np.ndarray:
    out = np.eye(4)
    out[:3, 3] = xyz
    return out


def _pos_quat(transform: np.ndarray) -> tuple[list[float], list[float]]:
    transform = np.asarray(transform, dtype=np.float64)
    return transform[:3, 3].tolist(), matrix_to_quat_xyzw(transform[:3, :3]).tolist()


# ----------------------------------------------------------------------------------------------- picture


@dataclass(frozen=True)
class LegendEntry:
    label: str
    rgba: RGBA


def render_views(items: Sequence[Item], views: Sequence[View | str] = DEFAULT_VIEWS, size: tuple[int, int] = (480, 360),
                 heading_deg: float = 0.0, *, table: bool = True, supersample: int = 2,
                 frame_points: np.ndarray | None = None) -> list[RenderedView]:
    """Render the items from each view at `size` = (width, height) pixels (see RenderWorld for the options)."""
    resolved = [views_by_name([v])[0] if isinstance(v, str) else v for v in views]
    if not resolved:
        raise RenderError("at least one view is needed")
    with RenderWorld(items, heading_deg=heading_deg, table=table, frame_points=frame_points) as world:
        return [world.render(view, size[0], size[1], supersample) for view in resolved]


def picture_size(view_count: int, size: tuple[int, int], columns: int | None = None, *, title: str = "",
                 legend: Sequence[LegendEntry] = ()) -> tuple[int, int]:
    """Pixel size (width, height) of the PNG `compose_png` writes for these views, title and legend."""
    columns = _columns(view_count, columns)
    width = columns * size[0]
    return width, math.ceil(view_count / columns) * size[1] + _header_layout(width, title, legend).height


def compose_png(rendered: Sequence[RenderedView], out: str | Path, *, title: str = "",
                legend: Sequence[LegendEntry] = (), columns: int | None = None) -> Path:
    """Tile the views into one PNG under a header (title, legend) with a label on each view; returns the path.

    The header is laid out from measured text widths: the title wraps at its " · " separators and the
    legend at entry boundaries, so nothing is cut off however narrow the picture.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    if not rendered:
        raise RenderError("no views to compose")
    tile_h, tile_w = rendered[0].rgb.shape[:2]
    columns = _columns(len(rendered), columns)
    width, height = picture_size(len(rendered), (tile_w, tile_h), columns, title=title, legend=legend)
    header = _header_layout(width, title, legend)
    figure = plt.figure(figsize=(width / _DPI, height / _DPI), dpi=_DPI, facecolor="white")

    def px_x(x: float) -> float:  # header pixels (from the top-left) -> figure
        return x / width

    def px_y(y: float) -> float:
        return 1.0 - y / height

    try:
        for index, view in enumerate(rendered):
            row, col = divmod(index, columns)
            bottom = height - header.height - (row + 1) * tile_h
            axes = figure.add_axes((col * tile_w / width, bottom / height, tile_w / width, tile_h / height))
            axes.imshow(view.rgb, interpolation="nearest", aspect="auto")
            axes.set_xticks([])
            axes.set_yticks([])
            for spine in axes.spines.values():  # a thin frame separates the tiles
                spine.set_edgecolor("0.55")
                spine.set_linewidth(1.0)
            axes.text(8, 8, view.view.title, fontsize=_LABEL_PT, va="top", ha="left",
                      bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none", "pad": 2})
        y = _PAD_PX
        for line in header.title_lines:
            figure.text(px_x(_PAD_PX), px_y(y), line, fontsize=_TITLE_PT, fontweight="bold", va="top", ha="left")
            y += _TITLE_LINE_PX
        for legend_row in header.legend_rows:
            x: float = _PAD_PX
            for entry in legend_row:
                figure.add_artist(Rectangle((px_x(x), px_y(y + _SWATCH_PX + 3)), px_x(_SWATCH_PX) - px_x(0),
                                            _SWATCH_PX / height, facecolor=entry.rgba[:3], edgecolor="black",
                                            linewidth=0.5, transform=figure.transFigure))
                figure.text(px_x(x + _SWATCH_PX + _SWATCH_GAP_PX), px_y(y + 1), entry.label, fontsize=_LEGEND_PT,
                            va="top", ha="left")
                x += _legend_entry_width(entry.label)
            y += _LEGEND_LINE_PX
        buffer = io.BytesIO()
        figure.savefig(buffer, dpi=_DPI, format="png", facecolor="white")
    finally:
        plt.close(figure)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    # An adaptive 256-colour palette keeps the file small (renders are flat-shaded) and looks the same.
    Image.open(buffer).convert("RGB").quantize(256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(
        out, optimize=True)
    return out


def render_scene(items: Sequence[Item], out: str | Path, *, views: Sequence[View | str] = DEFAULT_VIEWS,
                 size: tuple[int, int] = (480, 360), heading_deg: float = 0.0, title: str = "",
                 legend: Sequence[LegendEntry] = (), columns: int | None = None, supersample: int = 2,
                 frame_points: np.ndarray | None = None) -> Path:
    """Render the items from several views and write them, tiled and labelled, to a PNG."""
    rendered = render_views(items, views, size, heading_deg, supersample=supersample, frame_points=frame_points)
    return compose_png(rendered, out, title=title, legend=legend, columns=columns)


_DPI = 100
_TITLE_PT, _LEGEND_PT, _LABEL_PT = 12, 9, 11
_PAD_PX = 8
_TITLE_LINE_PX = 22
_LEGEND_LINE_PX = 20
_SWATCH_PX = 11
_SWATCH_GAP_PX = 5
_ENTRY_GAP_PX = 16
_TEXT_WIDTH_SAFETY = 1.05  # measured outlines vs the renderer's hinted text: a few % wider at most


@dataclass(frozen=True)
class _HeaderLayout:
    title_lines: list[str]
    legend_rows: list[list[LegendEntry]]

    @property
    def height(self) -> int:
        if not self.title_lines and not self.legend_rows:
            return 0
        return 2 * _PAD_PX + len(self.title_lines) * _TITLE_LINE_PX + len(self.legend_rows) * _LEGEND_LINE_PX


def _columns(view_count: int, columns: int | None) -> int:
    """Tiles per row: as asked, else rows of at most 3 filled evenly (4 views -> 2 x 2)."""
    if view_count < 1:
        raise RenderError("at least one view is needed")
    if columns is None:
        columns = math.ceil(view_count / math.ceil(view_count / 3))
    return max(1, min(view_count, columns))


def _text_width_px(text: str, size_pt: float, bold: bool = False) -> float:
    from matplotlib.font_manager import FontProperties
    from matplotlib.textpath import TextToPath

    width_pt, _, _ = TextToPath().get_text_width_height_descent(
        text, FontProperties(size=size_pt, weight="bold" if bold else "normal"), ismath=False)
    return width_pt * _DPI / 72.0 * _TEXT_WIDTH_SAFETY


def _legend_entry_width(label: str) -> float:
    return _SWATCH_PX + _SWATCH_GAP_PX + _text_width_px(label, _LEGEND_PT) + _ENTRY_GAP_PX


def _header_layout(width: int, title: str, legend: Sequence[LegendEntry]) -> _HeaderLayout:
    """Greedy line filling: title parts (split at " · ") and legend entries, each line within the width."""
    available = width - 2 * _PAD_PX
    parts = [p for p in title.split(" · ") if p] if title else []
    title_lines = _fill_lines(parts, lambda line: _text_width_px(" · ".join(line), _TITLE_PT, bold=True), available)
    rows = _fill_lines(list(legend), lambda row: sum(_legend_entry_width(e.label) for e in row) - _ENTRY_GAP_PX, available)
    return _HeaderLayout([" · ".join(line) for line in title_lines], rows)


_Piece = TypeVar("_Piece")


def _fill_lines(pieces: list[_Piece], line_width: Callable[[list[_Piece]], float],
                available: float) -> list[list[_Piece]]:
    lines: list[list[_Piece]] = []
    for piece in pieces:
        if lines and line_width(lines[-1] + [piece]) <= available:
            lines[-1].append(piece)
        else:
            lines.append([piece])  # a piece wider than the line gets a line of its own
    return lines
