"""The MuJoCo world's own randomisation, the cameras' extrinsic errors and MuJoCo's depth cameras: what is
drawn (reproducibly, the old `real` draws unchanged), what the MuJoCo model then holds, what the drawn
physics does to a push, where rendered depth lands, and the refusals of bad input."""
from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from shared.contracts.messages import ObjectRef
from shared.execution.robot import JointTrajectory
from shared.execution.robots.mujoco.config import MujocoConfig
from shared.execution.robots.mujoco.model import ModelError
from shared.execution.robots.mujoco.robot import MujocoRobot
from shared.execution.robots.sim.robot import TrueWorld
from shared.world.objects import load_object
from shared.world.perception.depth import DepthFrame, Intrinsics
from shared.world.sim.camera import CameraPose, capture_object, default_cameras
from shared.world.sim.params import REFERENCE_PARAMS
from shared.world.sim.world import (
    MAX_CAMERAS,
    REAL_RANGES,
    CameraError,
    MujocoDraw,
    PoseError,
    sample_world,
)

mujoco = pytest.importorskip("mujoco")
torch.set_num_threads(1)

ROOT = Path(__file__).resolve().parents[1]
HALF_EXTENTS = np.array([0.05, 0.03, 0.04])
BOX = "proc-box-013"  # 13.9 x 4.6 x 7.5 cm, 0.24 kg

# ------------------------------------------------------------------------------------------ draws

# `real` draws as sample_world made them before camera errors and the `mujoco` level existed (seed: table
# friction, hand friction, rolling friction, position gain, latency; mass scale; centre of mass; pose error).
OLD_REAL_DRAWS = {
    0: ((0.5547846749285816, 0.652663496808877, 8.194704787238938e-05, 0.2129749743951352, 0.016265404784005448),
        0.7019169501191036, (0.008255111545554436, 0.0012796293092061583, 0.0018359724878719876),
        (0.0008724998293084575, 0.008701448475755364, 3.158535541215322)),
    11: ((0.3514280811076798, 0.7995378319616736, 0.001202996715246715, 0.21516402150695, 0.0029585216915491187),
         1.0579730152622837, (0.00856422045920739, -0.005154953086149638, -0.0029618084048056163),
         (0.008966569065835503, 0.0024376718559276575, -1.3100687627020902)),
    2**31 + 5: ((0.5907904099336392, 0.7850581967143848, 0.0005228889823608356, 0.2753989104632764,
                 0.009481500525610505), 1.1786888553742136,
                (0.00959022400323985, 0.003982874514435582, 0.0014740116460102552),
                (0.001288128469668283, -0.005177311740674662, 3.3834723093345733)),
}


@pytest.mark.parametrize("seed", sorted(OLD_REAL_DRAWS))
def test_the_real_draws_from_before_camera_errors_are_unchanged_bit_for_bit(seed):
    physics, mass, com, pose = OLD_REAL_DRAWS[seed]
    world = sample_world("real", seed, HALF_EXTENTS)
    p = world.physics
    assert (p.table_friction, p.hand_friction, p.object_rolling_friction, p.arm_position_gain,
            p.arm_command_latency_s) == physics
    assert world.mass_scale == mass and world.com_offset_m == com
    assert (world.pose_error.dx_m, world.pose_error.dy_m, world.pose_error.dyaw_deg) == pose
    assert len(world.camera_errors) == MAX_CAMERAS and world.mujoco is None


def test_the_mujoco_level_draws_its_own_within_range_reproducibly_and_shares_every_real_draw():
    worlds = [sample_world("mujoco", seed, HALF_EXTENTS) for seed in range(200)]
    assert sample_world("mujoco", 7, HALF_EXTENTS) == worlds[7]
    for seed, world in enumerate(worlds[:20]):
        real = sample_world("real", seed, HALF_EXTENTS)
        # Common draws: the same friction, gains, mass, pose and camera errors as `real` at the seed.
        assert world.level == "mujoco" and world.physics == real.physics and world.pose_error == real.pose_error
        assert world.camera_errors == real.camera_errors and world.mass_scale == real.mass_scale
        draw = world.mujoco
        assert draw is not None and draw.table_friction == real.physics.table_friction
        assert draw.hand_friction == real.physics.hand_friction and draw.mass_scale == real.mass_scale
        assert draw.com_offset_m == real.com_offset_m and draw.command_latency_s == real.physics.arm_command_latency_s
        assert draw.arm_kp_scale == pytest.approx(real.physics.arm_position_gain / REFERENCE_PARAMS.arm_position_gain)
    draws = [w.mujoco for w in worlds]
    assert all(d is not None for d in draws)

    def spread(values, rng):
        values = np.asarray(values)
        assert rng.low <= values.min() and values.max() <= rng.high
        assert values.max() - values.min() > 0.8 * (rng.high - rng.low)  # the range is used, not a constant

    spread([d.finger_stiffness_scale for d in draws], REAL_RANGES.finger_stiffness_scale)
    spread([d.finger_damping_scale for d in draws], REAL_RANGES.finger_damping_scale)
    spread([d.arm_kv_scale for d in draws], REAL_RANGES.arm_damping_scale)
    spread([d.torsional_friction_m for d in draws], REAL_RANGES.torsional_friction_m)
    spread([s for d in draws for s in d.finger_friction_scales], REAL_RANGES.finger_friction_scale)
    assert {len(d.finger_friction_scales) for d in draws} == {4}
    assert len({d.finger_friction_scales for d in draws}) == 200  # each finger's own draw
    record = worlds[0].record()
    assert record["level"] == "mujoco" and record["mujoco"]["finger_friction_scales"]
    assert len(record["camera_errors"]) == MAX_CAMERAS


def test_camera_errors_are_a_few_mm_and_tenths_of_a_degree_per_camera_and_none_at_exact():
    errors = [e for seed in range(100) for e in sample_world("real", seed, HALF_EXTENTS).camera_errors]
    shifts = np.array([e.translation_m for e in errors])
    turns = np.array([e.rotation_deg for e in errors])
    assert np.abs(shifts).max() <= REAL_RANGES.camera_translation_m and np.abs(shifts).max() > 0.0025
    assert np.abs(turns).max() <= REAL_RANGES.camera_rotation_deg and np.abs(turns).max() > 0.25
    assert sample_world("exact", 3, HALF_EXTENTS).camera_errors == ()
    with_cameras = sample_world("mujoco", 3, HALF_EXTENTS, cameras=2)
    assert with_cameras.pose_error == PoseError()  # perception's own pose error replaces the drawn one
    assert with_cameras.camera_errors == sample_world("mujoco", 3, HALF_EXTENTS).camera_errors
    # The true pose is the calibrated one composed with the error, in the camera's own frame.
    T = CameraPose("c", (0.0, -0.5, 0.5), (0.0, 0.0, 0.0)).T_world_camera()
    true = CameraError((0.005, 0.0, 0.0), (0.0, 0.0, 0.0)).true_pose(T)
    assert np.allclose(true[:3, 3] - T[:3, 3], 0.005 * T[:3, 0]) and np.allclose(true[:3, :3], T[:3, :3])
    turned = CameraError((0.0, 0.0, 0.0), (0.0, 0.0, 0.3)).true_pose(T)
    angle = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3].T @ turned[:3, :3]) - 1) / 2, -1, 1)))
    assert angle == pytest.approx(0.3, abs=1e-6) and np.allclose(turned[:3, 2], T[:3, 2])  # about the optical axis


def nominal_draw(**changes: object) -> MujocoDraw:
    values: dict[str, object] = dict(
        table_friction=0.5, hand_friction=0.8, finger_friction_scales=(1.0, 1.0, 1.0, 1.0), torsional_friction_m=0.005,
        rolling_friction_m=0.0, mass_scale=1.0, com_offset_m=(0.0, 0.0, 0.0), arm_kp_scale=1.0, arm_kv_scale=1.0,
        command_latency_s=0.0, finger_stiffness_scale=1.0, finger_damping_scale=1.0)
    return MujocoDraw(**(values | changes))  # type: ignore[arg-type]


@pytest.mark.parametrize(("field", "value", "message"), [
    ("table_friction", -0.1, "table_friction must be >= 0"),
    ("hand_friction", float("nan"), "hand_friction must be finite"),
    ("finger_friction_scales", (1.0, -0.2, 1.0, 1.0), r"finger_friction_scales\[1\] must be >= 0"),
    ("finger_friction_scales", (), "one scale per finger"),
    ("rolling_friction_m", -1e-4, "rolling_friction_m must be >= 0"),
    ("mass_scale", 0.0, "mass_scale must be > 0"),
    ("mass_scale", -1.0, "mass_scale must be > 0"),
    ("arm_kp_scale", 0.0, "arm_kp_scale must be > 0"),
    ("finger_damping_scale", float("inf"), "finger_damping_scale must be finite"),
    ("command_latency_s", -0.01, "command_latency_s must be >= 0"),
    ("com_offset_m", (0.0, float("nan"), 0.0), "com_offset_m must be 3 finite numbers"),
])
def test_a_mujoco_draw_outside_its_physical_range_is_refused(field, value, message):
    with pytest.raises(ValueError, match=message):
        nominal_draw(**{field: value})


def test_unknown_world_levels_and_camera_counts_are_refused_naming_the_known_ones():
    for level in ("mars", "MuJoCo", "pybullet", ""):
        with pytest.raises(ValueError, match=r"unknown world level .*known: exact, real, mujoco"):
            sample_world(level, 0, HALF_EXTENTS)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="cameras must be 0"):
        sample_world("mujoco", 0, HALF_EXTENTS, cameras=4)


# ------------------------------------------------------------------------------------------ capture


def test_a_camera_5_mm_off_along_its_x_shifts_the_captured_points_5_mm_against_it():
    """The camera truly stands 5 mm to its right; the system back-projects from where it believes it is, so
    everything it sees lands 5 mm to the camera's left (and the table stays at z = 0: the camera's x is level)."""
    obj = load_object("proc-cylinder-001")
    T_world_O = obj.T_D_O(yaw_rad=0.2)
    T_world_O[:2, 3] = (0.5, 0.05)
    camera = default_cameras((0.5, 0.05), 2, 0.1)[1]
    error = CameraError((0.005, 0.0, 0.0), (0.0, 0.0, 0.0))
    capture = capture_object(obj, T_world_O, cameras=[camera], noise=None, size=(160, 120), camera_errors=[error])
    frame, mask = capture.frames[0], capture.object_masks[0]
    assert np.allclose(frame.T_world_camera, camera.T_world_camera())  # the frame carries the calibrated pose
    on_object = dataclasses.replace(frame, depth_m=np.where(mask, frame.depth_m, 0.0)).points_world()
    table = dataclasses.replace(frame, depth_m=np.where(mask, 0.0, frame.depth_m)).points_world()
    truth = obj.mesh.copy()
    truth.apply_transform(T_world_O)
    shift = -0.005 * camera.T_world_camera()[:3, 0]
    assert len(on_object) > 50
    assert np.abs(trimesh.proximity.signed_distance(truth, on_object - shift)).max() < 1e-3
    assert np.abs(trimesh.proximity.signed_distance(truth, on_object)).max() > 4e-3  # uncorrected: off the surface
    assert np.abs(table[:, 2]).max() < 1e-3
    calibrated = capture_object(obj, T_world_O, cameras=[camera], noise=None, size=(160, 120))
    exact = dataclasses.replace(calibrated.frames[0], depth_m=np.where(calibrated.object_masks[0],
                                                                       calibrated.frames[0].depth_m, 0.0))
    moved = on_object.mean(axis=0) - exact.points_world().mean(axis=0)
    assert np.linalg.norm(moved - shift) < 1e-3, f"the object's points moved {moved}, expected {shift}"
    with pytest.raises(ValueError, match="1 camera errors for 2 cameras"):
        capture_object(obj, T_world_O, n_cameras=2, noise=None, size=(32, 24), camera_errors=[error])


# ------------------------------------------------------------------------------------------ the MuJoCo model


def box_pose(xy: tuple[float, float] = (0.5, 0.3)) -> np.ndarray:
    T = load_object(BOX).T_D_O()
    T[:2, 3] = xy
    return T


@pytest.fixture(scope="module")
def robot():
    with MujocoRobot(MujocoConfig("panda", "allegro")) as robot:
        yield robot


def geoms_of(model, bodies: set[str]) -> list[int]:
    return [g for g in range(model.ngeom) if model.body(model.geom_bodyid[g]).name in bodies]


def test_a_drawn_world_is_what_the_mujoco_model_holds_and_no_draw_the_nominal_one(robot):
    draw = nominal_draw(table_friction=0.37, hand_friction=0.9, finger_friction_scales=(0.8, 0.9, 1.1, 1.2),
                        torsional_friction_m=0.007, rolling_friction_m=0.0015, mass_scale=1.3,
                        com_offset_m=(0.004, -0.003, 0.002), arm_kp_scale=0.8, arm_kv_scale=1.2, command_latency_s=0.01,
                        finger_stiffness_scale=1.4, finger_damping_scale=0.6)
    box = load_object(BOX)
    robot.reset_world(TrueWorld(ObjectRef(library_id=BOX), box_pose(), mass_scale=0.5, mujoco=draw))
    model, control = robot.model, robot.config.control
    table = model.geom("table").id
    assert np.allclose(model.geom_friction[table], [0.37, 0.007, 0.0015]) and model.geom_condim[table] == 6
    body = model.body("object")
    assert model.body_mass[body.id] == pytest.approx(box.mass * 1.3)  # the draw's, not the TrueWorld's 0.5
    assert np.allclose(model.body_ipos[body.id], (0.004, -0.003, 0.002))
    pieces = [g for g in range(model.ngeom) if model.geom_bodyid[g] == body.id]
    assert all(model.geom_priority[g] < model.geom_priority[table] and model.geom_condim[g] == 6 for g in pieces)
    fingers = [{f"link_{4 * k + j}.0" for j in range(4)} | {f"link_{4 * k + 3}.0_tip"} for k in range(4)]
    for k, bodies in enumerate(fingers):
        geoms = geoms_of(model, bodies)
        assert geoms and np.allclose(model.geom_friction[geoms, 0], 0.9 * draw.finger_friction_scales[k])
    palm = geoms_of(model, {"panda_link7"})  # the flange, the mount and the palm: rigid with the last arm joint
    assert palm and np.allclose(model.geom_friction[palm, 0], 0.9)
    arm, hand = robot._actuators[:7], robot._actuators[7:]
    assert np.allclose(model.actuator_gainprm[arm, 0], control.arm_kp * 0.8)
    assert np.allclose(model.actuator_biasprm[arm, 2], -control.arm_kv * 1.2)
    assert np.allclose(model.actuator_gainprm[hand, 0], control.hand_kp * 1.4)
    assert np.allclose(model.actuator_biasprm[hand, 2], -control.hand_kv * 0.6)
    assert np.allclose(model.dof_damping[robot._qvel[7:]], control.hand_damping * 0.6)
    assert robot.world_config.control.command_latency_s == 0.01

    robot.reset_world(TrueWorld(ObjectRef(library_id=BOX), box_pose(), mass_scale=0.5))  # no draw: nominal
    model = robot.model
    assert np.allclose(model.geom_friction[model.geom("table").id, 0], robot.config.materials.table_friction)
    assert model.geom_condim[model.geom("table").id] == 3
    assert model.body_mass[model.body("object").id] == pytest.approx(box.mass * 0.5)
    assert np.allclose(model.actuator_gainprm[robot._actuators[:7], 0], control.arm_kp)
    assert robot.world_config.control.command_latency_s == 0.0

    with pytest.raises(ModelError, match="3 finger friction scales for a hand of 4 fingers"):
        robot.reset_world(TrueWorld(ObjectRef(library_id=BOX), box_pose(),
                                    mujoco=nominal_draw(finger_friction_scales=(1.0, 1.0, 1.0))))


@pytest.mark.parametrize("friction", [0.3, 0.7])
def test_a_box_slides_as_far_as_its_drawn_table_friction_lets_it(robot, friction):
    """A box launched at 0.6 m/s stops after v^2 / (2 mu g): the drawn coefficient is the one that acts."""
    robot.reset_world(TrueWorld(ObjectRef(library_id=BOX), box_pose(), mujoco=nominal_draw(table_friction=friction)))
    model, data = robot.model, robot.data
    body = model.body("object")
    dof = model.jnt_dofadr[body.jntadr[0]]
    data.qvel[dof] = 0.6
    for _ in range(500):
        mujoco.mj_step(model, data)
    slid = data.xpos[body.id][0] - 0.5
    assert slid == pytest.approx(0.6**2 / (2 * friction * 9.81), rel=0.03)


def test_command_latency_delays_the_arm_by_the_drawn_time():
    def start_of_motion(latency: float) -> float:
        states = []
        with MujocoRobot(MujocoConfig("panda", "allegro", state_rate_hz=500.0), publish=states.append) as robot:
            robot.reset_world(TrueWorld(ObjectRef(library_id=BOX), box_pose(),
                                        mujoco=nominal_draw(command_latency_s=latency)))
            start = robot.observe().positions.copy()
            goal = start.copy()
            goal[0] += 0.2
            robot.send(JointTrajectory(robot.joint_names, np.stack([start, goal]), np.array([0.0, 0.5])),
                       realtime_factor=1000.0)
        moved = [s.plan_time_s for s in states if abs(s.positions.to_numpy()[0] - start[0]) > 2e-3]
        return float(moved[0])

    delay = start_of_motion(0.02) - start_of_motion(0.0)
    assert delay == pytest.approx(0.02, abs=0.0041)


@pytest.fixture(scope="module")
def push():
    """The planner's push of the box 0.15 m sideways with the open Allegro hand (tests/test_mujoco_robot.py's)."""
    from tests.test_mujoco_robot import planned_box_push

    _, plan, T_world_O, T_world_D = planned_box_push()
    return plan, T_world_O, T_world_D


def run_push(push, draw: MujocoDraw) -> tuple[float, float]:
    """(how far the box moved along the push, the fingers' largest lag behind the plan)."""
    plan, T_world_O, T_world_D = push
    states = []
    with MujocoRobot(MujocoConfig("panda", "allegro"), publish=states.append) as robot:
        robot.reset_world(TrueWorld(ObjectRef(library_id=BOX), T_world_O, mujoco=draw))
        trajectory = JointTrajectory(robot.joint_names, plan.positions.to_numpy(), plan.times_s.to_numpy())
        robot.send(trajectory, realtime_factor=1000.0)
        truth = robot.true_object_pose()
    lag = max(float(np.abs(s.positions.to_numpy()[7:] - trajectory.sample(s.plan_time_s)[7:]).max()) for s in states)
    return float((np.array(truth.position) - T_world_O[:3, 3]) @ T_world_D[:3, 0]), lag


def test_in_the_same_push_less_table_friction_slides_further_and_stiffer_fingers_deflect_less(push):
    slippery, _ = run_push(push, nominal_draw(table_friction=0.3))
    sticky, _ = run_push(push, nominal_draw(table_friction=0.7))
    print(f"box moved {slippery:.4f} m at table friction 0.3, {sticky:.4f} m at 0.7")
    assert 0.10 < sticky < slippery < 0.20
    _, soft = run_push(push, nominal_draw(finger_stiffness_scale=0.5))
    _, stiff = run_push(push, nominal_draw(finger_stiffness_scale=1.5))
    print(f"largest finger lag {soft:.4f} rad at 0.5 x kp, {stiff:.4f} rad at 1.5 x kp")
    assert stiff < 0.85 * soft


# ------------------------------------------------------------------------------------------ depth cameras


def test_rendered_depth_back_projects_onto_the_table_and_the_object_and_the_mask_is_the_robots(robot):
    box = load_object(BOX)
    T_world_O = box_pose((0.55, 0.0))
    robot.reset_world(TrueWorld(ObjectRef(library_id=BOX), T_world_O))
    intrinsics = Intrinsics.from_hfov(160, 120, 87.0)
    cameras = default_cameras((0.55, 0.0), 3, 0.08)  # head (behind the robot: the arm in view), tripod, opposite
    images = robot.render_depth(cameras, intrinsics)
    renderer = robot._renderers._renderer
    truth = box.mesh.copy()
    truth.apply_transform(T_world_O)
    model, data = robot.model, robot.data
    for camera, (depth, robot_mask) in zip(cameras, images, strict=True):
        assert depth.shape == robot_mask.shape == (120, 160) and robot_mask.dtype == bool
        T = camera.T_world_camera()
        seen = DepthFrame(np.where(robot_mask, 0.0, depth), intrinsics, T).points_world()
        on_table = np.abs(seen[:, 2]) < 1e-4
        off_table = seen[~on_table]
        distance = np.abs(trimesh.proximity.signed_distance(truth, off_table)) if len(off_table) else np.zeros(0)
        assert on_table.sum() > 1000 and (distance < 1e-3).all(), f"{camera.name}: {distance.max():.4f} m off"
        if camera.name != "head":  # the head camera's view of the box is behind the arm
            assert len(off_table) > 50
        # The mask is where a ray from the pixel centre first meets a robot link.
        rows, cols = np.mgrid[0:120:3, 0:160:3]
        hit = np.zeros(rows.shape, dtype=bool)
        geom = np.array([-1], dtype=np.int32)
        for index in np.ndindex(rows.shape):
            v, u = rows[index], cols[index]
            ray = T[:3, :3] @ np.array([(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy, 1.0])
            if mujoco.mj_ray(model, data, T[:3, 3], ray, None, 1, -1, geom) >= 0:
                hit[index] = bool(model.geom_contype[geom[0]] & 1)
        assert (hit == robot_mask[rows, cols]).mean() > 0.99
        if camera.name == "head":
            assert robot_mask.mean() > 0.2
    # Kept between calls; a 4x4 camera pose renders as its CameraPose; a new world gets a new renderer.
    again = robot.render_depth([cameras[1].T_world_camera()], intrinsics)
    assert robot._renderers._renderer is renderer and np.array_equal(again[0][0], images[1][0])
    robot.reset_world(TrueWorld(ObjectRef(library_id=BOX), T_world_O))
    robot.render_depth(cameras[:1], intrinsics)
    assert robot._renderers._renderer is not renderer and renderer.closed


def test_rendering_costs_a_few_ms_per_camera_at_424_x_240(robot):
    robot.reset_world(TrueWorld(ObjectRef(library_id=BOX), box_pose((0.55, 0.0))))
    intrinsics = Intrinsics.from_hfov(424, 240, 87.0)
    cameras = default_cameras((0.55, 0.0), 3, 0.08)
    robot.render_depth(cameras, intrinsics)  # the renderer is built once
    start = time.perf_counter()
    for _ in range(3):
        robot.render_depth(cameras, intrinsics)
    per_camera = (time.perf_counter() - start) / 9
    print(f"MuJoCo depth + robot mask at 424 x 240: {per_camera * 1000:.1f} ms per camera")
    assert per_camera < 0.1  # generous for a loaded 2-core machine


def test_rendering_from_another_thread_works():
    """The OpenGL context is current only while a render runs, so a tracker thread may render too."""
    import threading

    with MujocoRobot(MujocoConfig("xarm7", "leap")) as robot:
        intrinsics = Intrinsics.from_hfov(64, 48, 87.0)
        camera = [CameraPose("side", (0.5, -0.6, 0.4), (0.4, 0.0, 0.2))]
        first = robot.render_depth(camera, intrinsics)
        other: list = []
        thread = threading.Thread(target=lambda: other.append(robot.render_depth(camera, intrinsics)))
        thread.start()
        thread.join()
        assert other and np.array_equal(other[0][0][0], first[0][0]) and first[0][1].any()


@pytest.mark.parametrize("setting", [None, "disable"])
def test_without_a_usable_opengl_platform_rendering_says_to_set_mujoco_gl(setting):
    """MUJOCO_GL unset: the project picks headless EGL itself and renders; set to a platform that cannot render:
    one clear refusal naming MUJOCO_GL."""
    script = textwrap.dedent("""
        from shared.execution.robots.mujoco.cameras import RenderUnavailable
        from shared.execution.robots.mujoco.config import MujocoConfig
        from shared.execution.robots.mujoco.robot import MujocoRobot
        from shared.world.perception.depth import Intrinsics
        from shared.world.sim.camera import CameraPose
        robot = MujocoRobot(MujocoConfig("panda", "allegro"))
        robot.connect()
        try:
            robot.render_depth([CameraPose("c", (0.5, -0.5, 0.5), (0.5, 0.0, 0.0))], Intrinsics.from_hfov(64, 48, 87.0))
            print("RENDERED")
        except RenderUnavailable as exc:
            assert isinstance(exc, RuntimeError)
            print("REFUSED", exc)
        robot.disconnect()
    """)
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "DISPLAY", "WAYLAND_DISPLAY", "PYOPENGL_PLATFORM")}
    if setting is not None:
        env["MUJOCO_GL"] = setting
    env["PYTHONPATH"] = str(ROOT)
    done = subprocess.run([sys.executable, "-c", script], env=env, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    if setting is None:
        assert "RENDERED" in done.stdout.splitlines()
        return
    line = next(x for x in done.stdout.splitlines() if x.startswith("REFUSED"))
    assert "MUJOCO_GL=egl" in line and "MUJOCO_GL=osmesa" in line and "failed" in line
    assert repr(setting) in line

