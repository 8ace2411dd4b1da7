"""The execution world: drawn apart from what the planner knows, turned into the truth by the evaluation,
applied by the simulated robot, and one control law for rollouts and executions."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pybullet as pb
import pytest

from evaluation.local_system import true_world
from evaluation.stats import difference_interval, success_interval
from shared.contracts.messages import ObjectRef, SimWorld
from shared.execution.robots.sim.config import SimConfig
from shared.execution.robots.sim.robot import SimRobot, TrueWorld
from shared.world.objects import load_object
from shared.world.push_outcome import object_pose
from shared.world.sim.params import REFERENCE_PARAMS
from shared.world.sim.world import REAL_RANGES, PoseError, rollout_worlds, sample_world

BOX = "proc-box-001"
HALF_EXTENTS = np.array([0.05, 0.03, 0.04])


def test_exact_is_the_planners_world_and_real_draws_within_its_ranges():
    exact = sample_world("exact", 7, HALF_EXTENTS)
    assert exact.physics == REFERENCE_PARAMS and exact.pose_error == PoseError() and exact.mass_scale == 1.0
    draws = [sample_world("real", seed, HALF_EXTENTS) for seed in range(200)]
    tables = np.array([w.physics.table_friction / REFERENCE_PARAMS.table_friction for w in draws])
    assert REAL_RANGES.table_friction_scale.low <= tables.min() and tables.max() <= REAL_RANGES.table_friction_scale.high
    assert tables.max() - tables.min() > 0.6  # the range is used, not a constant
    shifts = np.array([[w.pose_error.dx_m, w.pose_error.dy_m] for w in draws])
    assert np.abs(shifts).max() <= REAL_RANGES.pose_error_m and np.abs(shifts).max() > 0.008
    coms = np.array([w.com_offset_m for w in draws])
    assert np.all(np.abs(coms) <= np.array([0.2, 0.2, 0.1]) * HALF_EXTENTS + 1e-12)
    assert sample_world("real", 3, HALF_EXTENTS) == sample_world("real", 3, HALF_EXTENTS)
    with pytest.raises(ValueError, match="unknown world level"):
        sample_world("mars", 0, HALF_EXTENTS)


def test_the_planners_own_draws_are_seeded_by_the_request_and_never_the_executions_draw():
    worlds = rollout_worlds(11, 4, HALF_EXTENTS, REFERENCE_PARAMS)
    assert worlds == rollout_worlds(11, 4, HALF_EXTENTS, REFERENCE_PARAMS)  # every plan of a request: same worlds
    assert len({w.seed for w in worlds}) == 4 and worlds != rollout_worlds(12, 4, HALF_EXTENTS, REFERENCE_PARAMS)
    assert all(w.level == "real" and w.pose_error != PoseError() for w in worlds)
    execution = sample_world("real", 11, HALF_EXTENTS)  # an evaluation's trial seeded like the request
    assert all(w.physics != execution.physics for w in worlds)


def test_the_simulated_robot_executes_in_the_drawn_world_not_the_told_one():
    obj = load_object(BOX)
    told = obj.T_D_O()
    told[:2, 3] = (0.45, 0.0)
    world = SimWorld(object=ObjectRef(library_id=BOX), object_pose=object_pose(told))
    drawn = replace(sample_world("real", 11, HALF_EXTENTS), pose_error=PoseError(0.02, -0.01, 4.0), mass_scale=1.3)
    with SimRobot(SimConfig("panda", "allegro")) as backend:
        backend.reset_world(true_world(world, drawn))
        scene = backend.scene
        true = scene.object.pose()
        assert np.allclose(true[:2, 3], told[:2, 3] + (0.02, -0.01), atol=1e-6)
        yaw = np.degrees(np.arctan2(true[1, 0], true[0, 0]) - np.arctan2(told[1, 0], told[0, 0]))
        assert yaw == pytest.approx(4.0, abs=1e-6)
        mass = pb.getDynamicsInfo(scene.object.id, -1, physicsClientId=scene.client)[0]
        assert mass == pytest.approx(obj.mass * 1.3, rel=1e-6)
        table = pb.getDynamicsInfo(scene.sim.table.id, -1, physicsClientId=scene.client)[1]
        assert table == pytest.approx(drawn.physics.table_friction)
        assert backend.params.arm_command_latency_s == drawn.physics.arm_command_latency_s
        backend.reset_world(true_world(world, None))  # without a drawn world: the nominal physics and the told pose
        assert np.allclose(backend.scene.object.pose(), told, atol=1e-6)
        assert backend.params == REFERENCE_PARAMS
        backend.reset_world(TrueWorld.told(world))  # what the bus bridge does: the same
        assert np.allclose(backend.scene.object.pose(), told, atol=1e-6)
        assert backend.params == REFERENCE_PARAMS


def test_command_latency_delays_the_arm():
    """The one control law: a joint step commanded at t = 0 is followed later under 20 ms latency."""
    from shared.world.sim.plan_runner import ArmController

    def joint0_after(latency_s: float, steps: int) -> float:
        with SimRobot(SimConfig("panda", "allegro")) as backend:
            params = replace(REFERENCE_PARAMS, arm_command_latency_s=latency_s)
            q0 = backend.observe().positions
            target = q0.copy()
            target[0] += 0.2
            controller = ArmController(backend.scene, params, np.array([0.0, 0.01]), np.stack([q0, target]))
            for step in range(1, steps + 1):
                controller.step(step)
            return float(backend.observe().positions[0] - q0[0])

    assert joint0_after(0.0, 5) > 0.002  # 5 steps = 21 ms: the arm is on its way
    assert abs(joint0_after(0.02, 4)) < 1e-4  # still waiting for the command


def test_intervals_are_clustered_by_object():
    # Two objects, one always succeeding and one always failing: trial-level resampling would make the
    # interval narrow; resampling objects spans 0..1.
    split = [{"object_id": "a", "success": True}] * 10 + [{"object_id": "b", "success": False}] * 10
    interval = success_interval(split)
    assert interval.value == 0.5 and interval.low == 0.0 and interval.high == 1.0
    even = [{"object_id": o, "success": i % 2 == 0} for o in "abcdefgh" for i in range(10)]
    assert success_interval(even).low == success_interval(even).high == 0.5
    better = [{"object_id": o, "success": True} for o in "abcdefgh" for _ in range(10)]
    difference = difference_interval(better, even)
    assert difference.value == pytest.approx(0.5) and difference.low == pytest.approx(0.5)
