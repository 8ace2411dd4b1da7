"""The geometry of a request's obstacles (`shared.contracts.messages.Obstacle`): cylinders and walls on the table.

One place for what every engine, the planner's checks, perception and the recordings need of them: where a
wall's box stands, a mesh of each to draw or render, which points of a cloud lie on one (perception cuts the
workcell's known obstacles from what the cameras see, as a real pipeline subtracts its static scene), how deep
an obstacle reaches into an object's footprint, and discs covering a wall (the multi-step path planner plans
around discs).

The two kinds differ in what may touch them: nothing may touch a cylinder (the robot or the pushed object: it
may be fragile); the pushed object may slide along a wall, the robot may not.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import trimesh
from scipy.spatial import ConvexHull

from shared.contracts.messages import CircleObstacle, ObjectRef, Obstacle, PushRequest, WallObstacle

# Points this close to a known obstacle are taken for it. A camera's depth noise and calibration error put a wall's
# far face up to 1 cm beyond it in the cloud (measured on the wall task's captures: at 6 mm that residue joined the
# object's reconstruction, which then reached 5-6 mm into the wall; at 12 mm every reconstruction of 8 trials
# stayed 7-12 mm clear of it, the true gap 10 mm). An object that close loses the sliver of its face nearest it.
FIXTURE_MARGIN_M = 0.012


def height_of(obstacle: Obstacle) -> float:
    return obstacle.height_m


def wall_pose(wall: WallObstacle) -> np.ndarray:
    """World <- wall box (x along its length, y across, z up; origin at the box's centre)."""
    yaw = math.radians(wall.yaw_deg)
    T = np.eye(4)
    T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    T[:3, 3] = [wall.x, wall.y, wall.height_m / 2.0]
    return T


def wall_half_extents(wall: WallObstacle) -> np.ndarray:
    return np.array([wall.length_m, wall.thickness_m, wall.height_m]) / 2.0


def wall_outline(wall: WallObstacle) -> np.ndarray:
    """[4, 2] the wall's footprint on the table, counterclockwise."""
    half = wall_half_extents(wall)
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * half[:2]
    T = wall_pose(wall)
    return np.asarray(corners @ T[:2, :2].T + T[:2, 3], dtype=np.float64)


def obstacle_mesh(obstacle: Obstacle) -> trimesh.Trimesh:
    """The obstacle's solid in the world frame (standing on the table)."""
    if isinstance(obstacle, WallObstacle):
        box: trimesh.Trimesh = trimesh.creation.box(2.0 * wall_half_extents(obstacle), transform=wall_pose(obstacle))
        return box
    T = np.eye(4)
    T[:3, 3] = [obstacle.x, obstacle.y, obstacle.height_m / 2.0]
    cylinder: trimesh.Trimesh = trimesh.creation.cylinder(obstacle.radius, obstacle.height_m, transform=T)
    return cylinder


def on_obstacles(points: np.ndarray, obstacles: Sequence[Obstacle], margin_m: float) -> np.ndarray:
    """[N] bool: the points (world [N, 3]) within `margin_m` of an obstacle's solid (its surface as a camera sees
    it, with the camera's noise and calibration error inside the margin)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    hit = np.zeros(len(points), dtype=bool)
    for obstacle in obstacles:
        low = points[:, 2] <= height_of(obstacle) + margin_m
        if isinstance(obstacle, CircleObstacle):
            gap = np.hypot(points[:, 0] - obstacle.x, points[:, 1] - obstacle.y) - obstacle.radius
            hit |= low & (gap <= margin_m)
            continue
        T = wall_pose(obstacle)
        local = (points - T[:3, 3]) @ T[:3, :3]
        half = wall_half_extents(obstacle)
        hit |= low & np.all(np.abs(local[:, :2]) <= half[:2] + margin_m, axis=1)
    return hit


def off_obstacles(points: np.ndarray, obstacles: Sequence[Obstacle]) -> np.ndarray:
    """The points (world [N, 3]) not taken for a known obstacle (FIXTURE_MARGIN_M)."""
    points = np.asarray(points)
    return points[~on_obstacles(points, obstacles, FIXTURE_MARGIN_M)] if len(obstacles) else points


def cut_known_obstacles(request: PushRequest) -> PushRequest:
    """The request with its cloud's points on its obstacles and walls left out: they are known parts of the scene,
    not of the object (a wall or a neighbour 1 cm from the object would join its cluster and its reconstruction)."""
    cloud = request.object.point_cloud
    if cloud is None or not request.obstacles:
        return request
    points = cloud.to_numpy()
    kept = off_obstacles(points, request.obstacles)
    if len(kept) == len(points):
        return request
    return request.model_copy(update={"object": ObjectRef(point_cloud=kept)})


def distance_to_hull(hull: ConvexHull, point: np.ndarray) -> float:
    """Distance (m) from `point` to a convex polygon (a 2-D `hull`, e.g. an object's footprint), negative inside."""
    offsets = hull.equations[:, :2] @ point + hull.equations[:, 2]  # unit outward normals: signed edge distances
    if np.all(offsets <= 0.0):
        return float(offsets.max())
    starts = hull.points[hull.vertices]
    edges = np.roll(starts, -1, axis=0) - starts
    along = np.clip(np.einsum("ij,ij->i", point - starts, edges) / np.einsum("ij,ij->i", edges, edges), 0.0, 1.0)
    return float(np.min(np.linalg.norm(starts + along[:, None] * edges - point, axis=1)))


def wall_depth_into(wall: WallObstacle, outline_xy: np.ndarray) -> float:
    """How far the wall's footprint and a convex outline ([K, 2], e.g. an object's footprint hull) overlap: the
    least shift along any axis that parts them (the separating axis theorem); <= 0 when they do not touch."""
    a, b = wall_outline(wall), np.asarray(outline_xy, dtype=np.float64)
    depth = math.inf
    for polygon in (a, b):
        edges = np.roll(polygon, -1, axis=0) - polygon
        for edge in edges:
            length = float(np.hypot(*edge))
            if length < 1e-12:
                continue
            axis = np.array([-edge[1], edge[0]]) / length
            pa, pb = a @ axis, b @ axis
            depth = min(depth, min(pa.max() - pb.min(), pb.max() - pa.min()))
    return float(depth)


def covering_discs(wall: WallObstacle) -> list[tuple[float, float, float]]:
    """(x, y, radius) discs whose union covers the wall's footprint: radius the half-diagonal of each square-ish
    piece, so a path kept clear of the discs is clear of the wall (by up to that radius more than needed)."""
    pieces = max(1, math.ceil(wall.length_m / wall.thickness_m))
    step = wall.length_m / pieces
    radius = math.hypot(step, wall.thickness_m) / 2.0
    T = wall_pose(wall)
    along = T[:2, 0]
    return [(float(T[0, 3] + along[0] * s), float(T[1, 3] + along[1] * s), radius)
            for s in (np.arange(pieces) + 0.5) * step - wall.length_m / 2.0]


def as_discs(obstacles: Sequence[Obstacle]) -> list[tuple[float, float, float]]:
    """(x, y, radius) of each cylinder, and discs covering each wall: what the multi-step path planner plans around."""
    discs: list[tuple[float, float, float]] = []
    for obstacle in obstacles:
        discs += (covering_discs(obstacle) if isinstance(obstacle, WallObstacle)
                  else [(obstacle.x, obstacle.y, obstacle.radius)])
    return discs


def describe(obstacle: Obstacle) -> str:
    if isinstance(obstacle, WallObstacle):
        return (f"a wall {obstacle.length_m:.2f} m long at ({obstacle.x:.3f}, {obstacle.y:.3f}) along "
                f"{obstacle.yaw_deg:g} degrees")
    return f"a cylinder of radius {obstacle.radius:.3f} m at ({obstacle.x:.3f}, {obstacle.y:.3f})"
