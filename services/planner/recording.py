"""Recording of one push request for people: an MCAP viewable in Foxglove, and a PNG storyboard.

`<record_dir>/push-<request id>.mcap` holds
- Foxglove channels: `/scene` (SceneUpdate: the object's mesh in its own frame - for a point cloud,
  its reconstruction -, the table, the obstacles), `/cloud` (PointCloud: the received point cloud,
  world frame, when the object came as one), `/tf` (FrameTransforms: world -> object and world -> every arm and hand link, per
  robot state), `/joint_states` (JointStates);
- the bus messages as they travel (msgpack, `visualisation.recording`): the PushRequest, each push's
  PushDecision (candidates, rollouts: what `gd2p replay --view` draws), every executed Plan, the robot's ExecutionStates and the PushResponse;
- the metadata record `gd2p.decision` (`shared.planning.decision`): what the decision depended on beyond the
  request (its capture included): the commit, the models' SHA-256, the seeds, the pipeline's settings.
  `gd2p replay FILE.mcap --resim` plans it again from these.
`<record_dir>/push-<request id>.png` is the storyboard: one row per push — start, pre-contact
(the first waypoint of the push segment) and end — drawn by `visualisation.render` from one camera. The
planner service renders it after answering (it takes about as long as a push); it appears complete.
"""
from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pybullet as pb
from foxglove import messages as fg

from shared.contracts.messages import ExecutionState, Obstacle, PushDecision, PushRequest, WallObstacle
from shared.planning.decision import METADATA_NAME, decision_metadata
from shared.planning.outcome import PushOutcome, StepRecord
from shared.robots.arms import combined_urdf
from shared.sampling.models import model_ids
from shared.world.object_refs import load_object_ref
from shared.world.objects import write_object_urdf
from shared.world.obstacles import height_of, obstacle_mesh, wall_half_extents, wall_pose
from shared.world.push_outcome import pose_matrix
from shared.world.sim.robot_scene import RobotScene
from shared.world.sim.scene import transform_to_pos_quat
from visualisation.recording import McapWriter
from visualisation.render import VIEWS, Item, UrdfItem, compose_png, mesh_item, render_views

WORLD_FRAME = "world"
OBJECT_FRAME = "object"
IMAGE_SIZE = (480, 360)
OBSTACLE_RGBA = (0.80, 0.15, 0.15, 1.0)
# No anti-aliasing: the storyboard is written before the push request is answered, and TinyRenderer
# at 2x took 1.2 s per frame here under load (3.6 s of a 6 s storyboard), at 1x 0.3 s.
STORYBOARD_SUPERSAMPLE = 1


def record_push(record_dir: Path, request: PushRequest, outcome: PushOutcome, scene: RobotScene,
                defer: Callable[[Callable[[], Path]], object] | None = None, settings: object = None,
                decisions: list[PushDecision] | None = None) -> Path:
    """Write the MCAP and the storyboard PNG of a served request (`outcome`: its response and the
    records of its executed pushes); returns the MCAP's path.

    `scene` is an empty robot scene of the request's arm and hand (forward kinematics; the object and
    obstacles are added to it here). `decisions`: what the planner chose for each push (candidates, rollouts:
    `shared.planning.decision_tap`), written before that push's plan, for `gd2p replay --view`. `defer`, when given, is handed the storyboard's rendering (about
    as long as a push, measured 3-4 s on 2 loaded cores) to run later, e.g. on a background thread,
    so the request can be answered first. `settings`: the pipeline's (`PipelineSettings`), for the
    decision's metadata.
    """
    record_dir.mkdir(parents=True, exist_ok=True)
    mcap_path = record_dir / f"push-{request.id[:16]}.mcap"
    records = outcome.records
    obj = load_object_ref(request.object)
    scene.add_object(write_object_urdf(obj), records[0].T_world_O_start)
    scene.add_obstacles(request.obstacles)
    with McapWriter(str(mcap_path)) as writer:
        start_ns = time.time_ns()
        writer.write_message("gd2p/planner/request", request, start_ns)
        _write_scene(writer, obj.mesh, request, start_ns)
        if request.object.point_cloud is not None:
            _write_cloud(writer, request.object.point_cloud.to_numpy(), start_ns)
        decided = list(decisions or [])
        for record in records:
            for decision in [d for d in decided if d.plan is record.step.plan or _same_plan(d, record)][:1]:
                writer.write_message("gd2p/planner/decision", decision, _first_stamp(record, start_ns))
                decided.remove(decision)
            writer.write_message("gd2p/planner/plan", record.step.plan, start_ns)
            for state in record.execution.states + [record.execution.final]:
                _write_state(writer, scene, state)
        writer.write_message("gd2p/planner/response", outcome.response, time.time_ns())
        writer.add_metadata(METADATA_NAME, decision_metadata(request, settings, model_ids(request.hand)))
    render = storyboard(scene, records, obj.mesh, request.obstacles, mcap_path.with_suffix(".png"))
    if defer is None:
        render()
    else:
        defer(render)
    return mcap_path


def _same_plan(decision: PushDecision, record: StepRecord) -> bool:
    a, b = decision.plan.positions.to_numpy(), record.step.plan.positions.to_numpy()
    return a.shape == b.shape and bool(np.array_equal(a, b))


def _first_stamp(record: StepRecord, default_ns: int) -> int:
    """Just before the push's first robot state (its decision came before the robot moved)."""
    states = record.execution.states
    return int(states[0].stamp * 1e9) - 1 if states else default_ns


# ------------------------------------------------------------------------------------- Foxglove


def _stamp(ns: int) -> fg.Timestamp:
    return fg.Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def _foxglove(writer: McapWriter, topic: str, message, log_time_ns: int) -> None:
    schema = type(message).get_schema()
    writer.write_foreign(topic, schema.name, schema.encoding, schema.data, "protobuf", message.encode(), log_time_ns)


def _write_scene(writer: McapWriter, mesh, request: PushRequest, ns: int) -> None:
    """The object's mesh (frame-locked to its frame: it moves with /tf), the table and the obstacles."""
    triangles = mesh.vertices[mesh.faces].reshape(-1, 3)
    entities = [
        fg.SceneEntity(timestamp=_stamp(ns), frame_id=OBJECT_FRAME, id="object", frame_locked=True,
                       triangles=[fg.TriangleListPrimitive(
                           points=[fg.Point3(x=float(x), y=float(y), z=float(z)) for x, y, z in triangles],
                           color=fg.Color(r=0.9, g=0.5, b=0.1, a=1.0))]),
        fg.SceneEntity(timestamp=_stamp(ns), frame_id=WORLD_FRAME, id="table",
                       cubes=[fg.CubePrimitive(pose=fg.Pose(position=fg.Vector3(x=0.6, y=0.0, z=-0.01)),
                                               size=fg.Vector3(x=1.2, y=1.6, z=0.02),
                                               color=fg.Color(r=0.6, g=0.6, b=0.6, a=0.5))]),
    ]
    entities += [_obstacle_entity(f"obstacle {i}", o, ns) for i, o in enumerate(request.obstacles)]
    _foxglove(writer, "/scene", fg.SceneUpdate(entities=entities), ns)


def _write_cloud(writer: McapWriter, points: np.ndarray, ns: int) -> None:
    """The point cloud the request carried, as received (world frame, float32 x y z)."""
    packed = np.ascontiguousarray(points, dtype="<f4")
    fields = [fg.PackedElementField(name=name, offset=4 * i, type=fg.PackedElementFieldNumericType.Float32)
              for i, name in enumerate("xyz")]
    _foxglove(writer, "/cloud", fg.PointCloud(timestamp=_stamp(ns), frame_id=WORLD_FRAME, pose=fg.Pose(),
                                             point_stride=12, fields=fields, data=packed.tobytes()), ns)


def _transform(parent: str, child: str, position, quat_xyzw, ns: int) -> fg.FrameTransform:
    x, y, z = (float(v) for v in position)
    qx, qy, qz, qw = (float(v) for v in quat_xyzw)
    return fg.FrameTransform(timestamp=_stamp(ns), parent_frame_id=parent, child_frame_id=child,
                             translation=fg.Vector3(x=x, y=y, z=z), rotation=fg.Quaternion(x=qx, y=qy, z=qz, w=qw))


def _link_poses(scene: RobotScene) -> list[tuple[str, tuple, tuple]]:
    """(name, position, quaternion xyzw) of every robot link's URDF frame, by one batched FK call."""
    links = [j for j in scene.link_names if j >= 0]
    states = pb.getLinkStates(scene.robot_id, links, computeForwardKinematics=True, physicsClientId=scene.client)
    base_position, base_quat = transform_to_pos_quat(scene.T_world_base)  # the base's URDF frame, not its COM
    poses = [(scene.link_names[-1], base_position, base_quat)]
    return poses + [(scene.link_names[j], state[4], state[5]) for j, state in zip(links, states, strict=True)]


def _write_state(writer: McapWriter, scene: RobotScene, state: ExecutionState) -> None:
    """One robot state: the bus message, the joint states, and world -> object / link transforms."""
    ns = int(state.stamp * 1e9)
    writer.write_message("gd2p/robot_bridge/state", state, ns)
    q = state.positions.to_numpy().astype(np.float64)
    joints = [fg.JointState(name=name, position=float(p), velocity=float(v))
              for name, p, v in zip(state.joint_names, q, state.velocities.to_numpy(), strict=False)]
    _foxglove(writer, "/joint_states", fg.JointStates(timestamp=_stamp(ns), joints=joints), ns)
    n_arm = len(scene.arm_joints)
    scene.set_configuration(q[:n_arm], q[n_arm:])
    transforms = [_transform(WORLD_FRAME, name, position, quat, ns) for name, position, quat in _link_poses(scene)]
    if state.object_pose is not None:
        pose = state.object_pose
        transforms.append(_transform(WORLD_FRAME, OBJECT_FRAME, pose.position, pose.quaternion_xyzw, ns))
    _foxglove(writer, "/tf", fg.FrameTransforms(transforms=transforms), ns)


# ----------------------------------------------------------------------------------- storyboard


def storyboard(scene: RobotScene, records: list[StepRecord], mesh, obstacles, path: Path) -> Callable[[], Path]:
    """A function that writes the storyboard PNG (`visualisation.render`): per push, the start, the pre-contact
    configuration and the end, all from one camera.

    What needs `scene` (forward kinematics for the camera's framing) is done now; the returned function
    renders in PyBullet clients of its own, so it may run on another thread while `scene` is reused. The
    PNG appears at `path` complete (written beside, then renamed).
    """
    robot_urdf = combined_urdf(scene.arm, scene.hand)
    frames = []  # (label, joint positions, T_world_O)
    for i, record in enumerate(records):
        plan = record.step.plan
        positions = plan.positions.to_numpy().astype(np.float64)
        push = next(s for s in plan.segments if s.label == "push")
        result = record.step.result
        frames += [(f"push {i + 1}: start", positions[0], record.T_world_O_start),
                   (f"push {i + 1}: pre-contact", positions[push.start], record.T_world_O_start),
                   ((f"push {i + 1}: end ({'success' if result.success else 'miss'}, "
                     f"{result.position_error_m * 100:.1f} cm off)"),
                    record.execution.final.positions.to_numpy().astype(np.float64), pose_matrix(result.final_object_pose))]
    obstacle_items = [mesh_item(f"obstacle {k}", obstacle_mesh(o), np.eye(4), OBSTACLE_RGBA) for k, o in enumerate(obstacles)]
    joint_names = list(records[0].step.plan.joint_names)
    framing = np.concatenate([_robot_points(scene, q) for _, q, _ in frames]
                             + [mesh.vertices @ T[:3, :3].T + T[:3, 3] for _, _, T in frames])
    heading = math.degrees(math.atan2(*_push_direction(records[0])[::-1]))
    T_world_base = scene.T_world_base.copy()

    def render() -> Path:
        rendered = []
        for label, q, T_world_O in frames:
            items: list[Item] = [UrdfItem("robot", robot_urdf, T_world_base, dict(zip(joint_names, map(float, q), strict=False))),
                     mesh_item("object", mesh, T_world_O), *obstacle_items]
            view = dataclasses.replace(VIEWS["iso"], label=label)
            rendered += render_views(items, [view], IMAGE_SIZE, heading, supersample=STORYBOARD_SUPERSAMPLE,
                                     frame_points=framing)
        partial = path.with_name(path.name + ".partial.png")
        compose_png(rendered, partial, title=f"push request: {len(records)} push(es)", columns=3)
        os.replace(partial, path)
        return path

    return render


def _robot_points(scene: RobotScene, q: np.ndarray) -> np.ndarray:
    """Link origins of the robot at joints q (what the storyboard's camera must keep in view)."""
    n_arm = len(scene.arm_joints)
    scene.set_configuration(q[:n_arm], q[n_arm:])
    return np.array([position for _, position, _ in _link_poses(scene)], dtype=np.float64)


def _push_direction(record: StepRecord) -> np.ndarray:
    """The planned push direction (world xy) of a step: from the object's start toward where it should go."""
    start = record.T_world_O_start[:2, 3]
    end = np.array(record.step.result.final_object_pose.position[:2])
    delta = end - start
    return delta / np.linalg.norm(delta) if np.linalg.norm(delta) > 1e-6 else np.array([1.0, 0.0])


def _obstacle_entity(name: str, obstacle: Obstacle, ns: int) -> fg.SceneEntity:
    """A cylinder or a wall for Foxglove's 3D panel."""
    red = fg.Color(r=0.8, g=0.1, b=0.1, a=0.8)
    height = height_of(obstacle)
    if isinstance(obstacle, WallObstacle):
        position, quaternion = transform_to_pos_quat(wall_pose(obstacle))
        size = wall_half_extents(obstacle) * 2.0
        pose = fg.Pose(position=fg.Vector3(x=position[0], y=position[1], z=position[2]),
                       orientation=fg.Quaternion(x=quaternion[0], y=quaternion[1], z=quaternion[2], w=quaternion[3]))
        return fg.SceneEntity(timestamp=_stamp(ns), frame_id=WORLD_FRAME, id=name, cubes=[fg.CubePrimitive(
            pose=pose, size=fg.Vector3(x=float(size[0]), y=float(size[1]), z=float(size[2])), color=red)])
    return fg.SceneEntity(timestamp=_stamp(ns), frame_id=WORLD_FRAME, id=name, cylinders=[fg.CylinderPrimitive(
        pose=fg.Pose(position=fg.Vector3(x=obstacle.x, y=obstacle.y, z=height / 2)),
        size=fg.Vector3(x=2 * obstacle.radius, y=2 * obstacle.radius, z=height), bottom_scale=1.0, top_scale=1.0,
        color=red)])
