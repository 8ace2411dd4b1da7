"""The goal of a multi-step request (`PushRequest.goal_xy`, with `goal_yaw_deg` a pose goal): what is checked
before the robot moves, and how a pose goal's push is to turn the object.

Checked before any motion (`check_goal`), each a PushError naming the problem:
- the object's footprint at the goal (the multi-step disc: its radius around the centre of mass, whatever
  yaw it ends at) lies on the table top the robot's world stands on (`TABLE_TOP_HALF_EXTENTS_M`, a square
  around the robot's base at the world origin): else "bad_request", no push can put it there;
- some point of that footprint is within the robot's reach (`shared.robots.reach`, a bound no hand point
  exceeds in any configuration): else "infeasible", for the robot, not the request, cannot do it;
- a goal yaw needs an object whose turn a camera can see (`push_outcome.turn_observable`): a body of
  revolution looks the same at every yaw, so its yaw can be neither measured nor judged ("bad_request").
Of every request, direction or goal (`check_obstacles`): no obstacle may reach into the object's footprint as
it stands (more than OBSTACLE_OVERLAP_TOLERANCE_M): an obstacle drawn through the object is a mistake in the
request, and simulated it would throw the object out of the table ("bad_request").

Every push of a pose goal is to bring the object's yaw toward the goal's (`turn_to_make_deg`; a turn of 0 keeps
it): the pose source's hand poses are then also tried turned about the object's vertical axis (`turning_poses`).
The model is the flat push's: a palm pushing an object squares the edge of its footprint it meets against itself
(the object turns until that edge lies flat on the palm, then slides with it), so a push turns the object by the
palm's slant to that edge. A palm square to the push squares the object to the push too, and a pose goal's push
made that way would undo the turn the last one made. Each copy is slanted to the edge the push meets
(`facing_edge_deg`) plus the turn to make; a fingertip turned so presses beside the centre of mass on the side that
turns the object the same way. The rollouts tell how far each really turns it, and the ranking (its yaw miss)
chooses.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.spatial import ConvexHull

from shared.contracts.messages import Obstacle, PushRequest, WallObstacle
from shared.frames import make_transform, transform_poses, yaw_rotation
from shared.planning.outcome import PushError
from shared.robots.reach import reach
from shared.world.obstacles import describe, distance_to_hull, wall_depth_into
from shared.world.push_outcome import YawGoal
from shared.world.sim.scene import TABLE_TOP_HALF_EXTENTS_M

# How far an obstacle may reach into the object's footprint before the request is refused: a reconstruction's
# outline is a few millimetres off the true one, and a neighbour touching the object is a real scene.
OBSTACLE_OVERLAP_TOLERANCE_M = 0.002
# The most a push is asked to turn the object: a larger turn takes more pushes.
MAX_TURN_PER_PUSH_DEG = 30.0
# The most a turned palm is slanted from square to the push: slanted further, it slides along the object's edge
# rather than pushing it.
MAX_PALM_SLANT_DEG = 45.0
# A palm whose normal leans this close to vertical has no slant to speak of (a hand pressing from above, a
# fingertip poke): its copy is turned by the turn to make alone.
UPRIGHT_PALM_MAX_HORIZONTAL = 0.5


def check_goal(request: PushRequest, footprint_radius_m: float, T_world_base: np.ndarray,
               turn_observable: bool) -> None:
    """PushError when the request's goal cannot be reached (see the module docstring); nothing has moved yet."""
    assert request.goal_xy is not None  # only a multi-step request has a goal
    goal = np.asarray(request.goal_xy, dtype=np.float64)
    _check_on_table(goal, footprint_radius_m)
    _check_within_reach(request, goal, footprint_radius_m, T_world_base)
    if request.goal_yaw_deg is not None and not turn_observable:
        raise PushError("bad_request", "goal_yaw_deg: the object looks the same at every yaw about its vertical axis "
                        "(a body of revolution), so no camera can tell its yaw; ask for the goal point alone")


def check_obstacles(obstacles: Sequence[Obstacle], footprint_xy: np.ndarray) -> None:
    """PushError("bad_request") naming the first obstacle that reaches more than OBSTACLE_OVERLAP_TOLERANCE_M into
    the object's footprint (`footprint_xy` [N, 2]: the object's points in the table plane where it stands)."""
    hull = ConvexHull(np.asarray(footprint_xy, dtype=np.float64))
    for index, obstacle in enumerate(obstacles):
        if isinstance(obstacle, WallObstacle):
            depth = wall_depth_into(obstacle, hull.points[hull.vertices])
        else:
            depth = obstacle.radius - distance_to_hull(hull, np.array([obstacle.x, obstacle.y]))
        if depth > OBSTACLE_OVERLAP_TOLERANCE_M:
            raise PushError("bad_request", f"obstacle {index} ({describe(obstacle)}) reaches {depth * 1000:.0f} mm into "
                            "the object's footprint: an obstacle must stand clear of the object to be pushed (a "
                            "neighbour or a wall may touch it, not pass through it)")


def _check_on_table(goal: np.ndarray, footprint_radius_m: float) -> None:
    half = np.asarray(TABLE_TOP_HALF_EXTENTS_M[:2])
    overhang = np.abs(goal) + footprint_radius_m - half
    if np.any(overhang > 0.0):
        raise PushError("bad_request", f"the goal {_xy(goal)} is off the table: the object there (its footprint "
                        f"{footprint_radius_m:.3f} m around its centre) would stand {float(overhang.max()):.3f} m "
                        f"past the table top's edge ({half[0]:.1f} x {half[1]:.1f} m either side of the robot's base)")


def _check_within_reach(request: PushRequest, goal: np.ndarray, footprint_radius_m: float,
                        T_world_base: np.ndarray) -> None:
    bound = reach(request.arm, request.hand)
    shoulder = bound.shoulder_world(T_world_base)
    gap = float(np.linalg.norm(goal - shoulder[:2])) - footprint_radius_m - bound.radius_m
    if gap > 0.0:
        raise PushError("infeasible", f"the goal {_xy(goal)} is out of the robot's reach: the object there would be "
                        f"{gap:.3f} m beyond where any part of the {request.hand} hand on the {request.arm} can "
                        f"get ({bound.radius_m:.2f} m from the arm's shoulder at {_xy(shoulder[:2])})")


def turn_to_make_deg(T_world_O: np.ndarray, yaw_goal: YawGoal | None) -> float | None:
    """The turn (degrees, counterclockwise positive) a push of the object at `T_world_O` is to make toward
    `yaw_goal`: the turn to the goal yaw the short way, at most MAX_TURN_PER_PUSH_DEG either way (near 0 at
    the goal yaw: keep it); None without a goal yaw (no turned poses)."""
    if yaw_goal is None:
        return None
    turn = yaw_goal.turn_deg(T_world_O[:3, :3])
    return float(np.clip(turn, -MAX_TURN_PER_PUSH_DEG, MAX_TURN_PER_PUSH_DEG))


def facing_edge_deg(vertices_d: np.ndarray) -> float:
    """How far (degrees about D's z, counterclockwise positive) the edge of the object's footprint that a push
    along +x of D meets is turned from square to the push: the slant of the convex hull's edge (of the footprint,
    `vertices_d` [V, 3] in D) whose outward normal points most nearly back along -x."""
    hull = ConvexHull(np.asarray(vertices_d, dtype=np.float64)[:, :2])
    outward = hull.equations[:, :2]  # unit outward normals of the hull's edges
    back = outward[np.argmin(outward[:, 0])]
    return math.degrees(math.atan2(-back[1], -back[0]))


def turning_poses(poses_d: np.ndarray, palm_normals_d: np.ndarray, vertices_d: np.ndarray,
                  turn_deg: float) -> np.ndarray:
    """The hand poses [K, 25] in D, each turned about D's z axis (the vertical through the object's centre of mass)
    so that its palm (normals `palm_normals_d` [K, 3], in D) is slanted `turn_deg` to the footprint edge the push
    meets (`facing_edge_deg`; at most MAX_PALM_SLANT_DEG from square to the push), then backed off along its
    palm normal by how much farther the object's outline (`vertices_d` [V, 3], in D) reaches toward the turned
    palm than toward the palm as it was: a palm on the object's back stays on the outline, no hand ends inside.

    Slanted counterclockwise, a palm meets the object on D's -y side of its centre of mass first: pushed along +x
    of D there, the object turns counterclockwise (a push f along x at y has the torque -y f about z)."""
    vertices = np.asarray(vertices_d, dtype=np.float64)
    slant = math.radians(float(np.clip(facing_edge_deg(vertices) + turn_deg, -MAX_PALM_SLANT_DEG, MAX_PALM_SLANT_DEG)))
    normals = np.asarray(palm_normals_d, dtype=np.float64)
    slanted = np.linalg.norm(normals[:, :2], axis=1) >= UPRIGHT_PALM_MAX_HORIZONTAL
    palm_angle = np.arctan2(normals[:, 1], normals[:, 0])
    turned = [_turned_about_the_object(pose, slant - angle, angle, vertices) if has_slant
              else _turned_about_the_object(pose, math.radians(turn_deg), 0.0, vertices)  # by the turn alone
              for pose, angle, has_slant in zip(poses_d, palm_angle, slanted, strict=True)]
    return np.stack(turned) if turned else np.zeros_like(poses_d)


def _turned_about_the_object(pose_d: np.ndarray, turn_rad: float, facing_rad: float,
                             vertices_d: np.ndarray) -> np.ndarray:
    """One pose [25] in D turned `turn_rad` about D's z axis, backed off along the direction it faced (at
    `facing_rad` from D's x, horizontal) turned with it by how much farther the outline reaches back against it."""
    turn = yaw_rotation(turn_rad)
    facing = np.array([math.cos(facing_rad), math.sin(facing_rad), 0.0])
    turned_facing = turn @ facing

    def reach_behind(direction: np.ndarray) -> float:  # how far the outline reaches back against `direction`
        return float(np.max(-(vertices_d @ direction)))

    back_off = reach_behind(turned_facing) - reach_behind(facing)
    moved: np.ndarray = transform_poses(pose_d, make_transform(turn, -back_off * turned_facing))
    return moved


def _xy(point: np.ndarray) -> str:
    return f"({point[0]:.3f}, {point[1]:.3f})"
