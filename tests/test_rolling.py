"""Objects that roll: which they are, how a push of one is judged, and that a trial waits for one to come to rest
before its cameras look (a drawn centre of mass puts a ball or a lying can off balance)."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import trimesh

from shared.contracts.messages import ObjectRef
from shared.frames import make_transform, yaw_rotation
from shared.world.objects import load_object
from shared.world.objects.geometry import ROLLS_BELOW_DEG, rolls, tipping_angle_deg
from shared.world.push_outcome import judge_push, object_pose

UPRIGHT = np.eye(3)


def lying(mesh: trimesh.Trimesh) -> np.ndarray:
    """The rotation that lays a z-axis body on its side (its axis along the table's x)."""
    return trimesh.transformations.rotation_matrix(math.pi / 2, [0, 1, 0])[:3, :3]


def test_balls_and_lying_cans_roll_boxes_standing_cans_and_lumps_do_not():
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.03)
    can = trimesh.creation.cylinder(radius=0.03, height=0.12, sections=48)
    box = trimesh.creation.box((0.06, 0.04, 0.10))
    assert rolls(ball, UPRIGHT) and rolls(can, lying(can))
    assert not rolls(can, UPRIGHT) and not rolls(box, UPRIGHT)
    # a box on end must tilt atan(half its width / its centre's height) before it tips: no roll, however slender
    assert tipping_angle_deg(box, UPRIGHT) == pytest.approx(math.degrees(math.atan2(0.02, 0.05)), abs=0.01)
    assert tipping_angle_deg(can, lying(can)) < ROLLS_BELOW_DEG
    # an irregular lump balanced close to an edge of its support tips: it is no body of revolution
    lump = trimesh.convex.convex_hull(np.random.default_rng(3).normal(size=(40, 3)) * [0.05, 0.03, 0.02])
    lump.apply_translation(-lump.center_mass)
    assert not rolls(lump, UPRIGHT)


def test_a_ball_on_a_flat_of_its_own_rolls_a_prism_lying_on_a_facet_does_not():
    """A ball or fruit cut flat where it sits stands still where put and rolls when pushed: the flat holds it,
    it is a body of revolution beyond it. A 16-sided prism lying on one of its facets stays (a wide support)."""
    ball = trimesh.creation.icosphere(subdivisions=4, radius=0.03)
    keep = trimesh.creation.box(bounds=[[-1, -1, -0.0294], [1, 1, 1]])  # a 0.6 mm cut: a flat 6 mm across
    on_flat = trimesh.boolean.intersection([ball, keep], engine="manifold")
    on_flat.apply_translation(-on_flat.center_mass)
    assert tipping_angle_deg(on_flat, UPRIGHT) > ROLLS_BELOW_DEG and rolls(on_flat, UPRIGHT)
    prism = trimesh.creation.cylinder(radius=0.03, height=0.12, sections=16)
    on_facet = trimesh.transformations.rotation_matrix(math.pi / 2, [0, 1, 0])[:3, :3]
    on_facet = trimesh.transformations.rotation_matrix(math.pi / 16, [1, 0, 0])[:3, :3] @ on_facet  # a facet down
    assert tipping_angle_deg(prism, on_facet) > ROLLS_BELOW_DEG and not rolls(prism, on_facet)
    box = trimesh.creation.box((0.06, 0.06, 0.06))
    assert not rolls(box, UPRIGHT)


def test_library_objects_roll_as_they_lie():
    assert rolls(load_object("proc-lying-000").mesh, load_object("proc-lying-000").default_pose.rotation)
    for object_id in ("proc-box-000", "proc-cylinder-000", "proc-ellipsoid-001", "pb-mug", "pb-toy-cylinder"):
        obj = load_object(object_id)
        assert not rolls(obj.mesh, obj.default_pose.rotation), object_id


def test_a_rolled_object_is_judged_on_where_it_ended_alone():
    start = np.eye(4)
    start[:3, 3] = (0.4, 0.0, 0.03)
    rolled = make_transform(trimesh.transformations.rotation_matrix(math.radians(170), [0, 1, 0])[:3, :3],
                            np.array([0.6, 0.01, 0.03]))  # half a turn about its axis, 1 cm off the target
    target = np.array([0.6, 0.0])
    as_paper = judge_push(start, target, object_pose(rolled))
    as_rolling = judge_push(start, target, object_pose(rolled), rolling=True)
    assert not as_paper.success and as_paper.toppled  # its up axis went round with it
    assert as_rolling.success and as_rolling.rotation_deg == pytest.approx(170.0, abs=0.1)
    missed = rolled.copy()
    missed[1, 3] = 0.05
    assert not judge_push(start, target, object_pose(missed), rolling=True).success  # 5 cm off: a miss all the same


@pytest.mark.parametrize("world_level", ["real", "mujoco"])
def test_a_trial_starts_where_the_object_came_to_rest(world_level):
    """A can lying with its centre of mass drawn 8 mm off its axis rolls off the spot it was put on; the trial's
    true start (what the cameras see and the judge measures from) is where it stopped. A box stays put."""
    from evaluation import push_protocol as protocol
    from evaluation.local_system import LocalRobot

    robot = LocalRobot(tracking="truth")
    try:
        for object_id, moves in (("proc-lying-000", True), ("proc-box-000", False)):
            episode = protocol.Episode("gd2p", "allegro", object_id, 60.0, 0, world=world_level)
            obj = load_object(object_id)
            T_put = protocol.put_down(episode, protocol.execution_world(episode))
            # across the can's axis (O's x for the lying family) and level: off balance, it rolls
            across_O = T_put[:3, :3].T @ (yaw_rotation(math.pi / 2) @ T_put[:3, 0] * [1, 1, 0])
            offset = tuple(0.008 * across_O / np.linalg.norm(across_O))
            world = protocol.execution_world(episode)
            world = replace(world, com_offset_m=offset,
                            mujoco=None if world.mujoco is None else replace(world.mujoco, com_offset_m=offset))
            robot.execution_world = world
            robot.true_object = (ObjectRef(library_id=object_id), T_put)
            T_rest = robot.settle_true_object("panda", "allegro", protocol.SETTLE_S)
            moved = float(np.linalg.norm(T_rest[:2, 3] - T_put[:2, 3]))
            assert (moved > 0.004) if moves else (moved < 0.002), (object_id, moved)
            assert robot.true_object is not None and np.allclose(robot.true_object[1], T_rest)
            assert np.allclose(robot.true_object_pose("panda", "allegro").position, T_rest[:3, 3])
            assert rolls(obj.mesh, T_rest[:3, :3]) == moves
    finally:
        robot.close()


def test_a_trial_reports_its_object_under_one_shape_class():
    from evaluation import push_protocol as protocol

    def start(object_id: str) -> np.ndarray:
        return protocol.put_down(protocol.Episode("gd2p", "allegro", object_id, 60.0, 0),
                                 protocol.execution_world(protocol.Episode("gd2p", "allegro", object_id, 60.0, 0)))

    assert protocol.shape_of("proc-lying-000", start("proc-lying-000")) == "round"
    assert protocol.shape_of("proc-box-000", start("proc-box-000")) == load_object("proc-box-000").info.shape_class
    assert protocol.shape_of("proc-cylinder-000", start("proc-cylinder-000")) == "flat"
