"""Dataset v2 placements on the bus (issue 17 item 2): a GenerationJob and a floating-hand ValidationJob
with the same resting pose and yaw put the object in the same place, and a placement the object
cannot have is refused with a clear error."""
from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from services.generator import service as generator_service
from shared.contracts.errors import ServiceError
from shared.contracts.messages import GenerationJob, ObjectRef, ValidationJob
from shared.data_engine import Placement, placement_frame
from shared.robots.hands import load_hand
from shared.synthesis.config import GenerationConfig
from shared.validation import jobs as validator_service
from shared.validation.push import PushSimulator, table_object
from shared.world.fixed_poses import spatula_pose
from shared.world.objects import load_object

BOX_ID = "proc-box-004"
BOX = ObjectRef(library_id=BOX_ID)


@pytest.fixture(scope="module")
def box():
    return load_object(BOX_ID)


@pytest.fixture(scope="module")
def side_pose(box) -> int:
    """A resting pose of the box other than its default one."""
    return next(i for i in range(len(box.resting_poses)) if i != box.default_pose_index)


def test_generator_and_validator_place_the_object_alike(box, side_pose):
    placement = Placement(side_pose, 2.1)
    scene = generator_service.scene_for(BOX, GenerationConfig(), placement.pose_index, placement.yaw_rad)
    np.testing.assert_array_equal(scene.transform_d, box.T_D_O(side_pose, 2.1))

    hand = load_hand("allegro")
    placed = table_object(box, side_pose, 2.1)
    pose = spatula_pose(hand, placed.vertices_d)
    job = ValidationJob(object=BOX, hand="allegro", poses=pose[None], pose_index=side_pose,
                        frame=placement_frame(box, placement))
    index, yaw = validator_service.placement(job, box)
    assert index == side_pose and yaw == pytest.approx(2.1, abs=1e-12)
    np.testing.assert_allclose(table_object(box, index, yaw).transform_d, scene.transform_d, atol=1e-12)
    result = validator_service.validate(job)
    with PushSimulator(hand, placed) as sim:
        expected = sim.run(pose)
    assert bool(result.success.to_numpy()[0]) == expected.success
    assert result.position_error_m.to_numpy()[0] == pytest.approx(expected.position_error_m, abs=1e-6)


def test_default_placement_is_unchanged_for_existing_callers(box):
    assert generator_service.scene_for(BOX, GenerationConfig()).transform_d.tolist() == box.T_D_O(None, 0.0).tolist()
    job = ValidationJob(object=BOX, hand="allegro", poses=np.zeros((1, 25), np.float32))
    assert validator_service.placement(job, box) == (None, 0.0)
    assert GenerationJob(object=BOX, hand="allegro", batch_size=1).pose_index is None


def test_a_placement_the_object_cannot_have_is_refused(box, side_pose):
    missing = len(box.resting_poses)
    with pytest.raises(ServiceError, match=f"pose index {missing} does not exist") as generator_error:
        generator_service.run_job(GenerationJob(object=BOX, hand="allegro", batch_size=1, iterations=1,
                                                pose_index=missing))
    assert generator_error.value.code == "bad_request"
    pose = np.zeros((1, 25), np.float32)
    with pytest.raises(ServiceError, match=f"pose_index {missing} does not exist"):
        validator_service.placement(ValidationJob(object=BOX, hand="allegro", poses=pose, pose_index=missing), box)
    other = placement_frame(box, Placement(box.default_pose_index, 0.5))  # the default pose, said to be the side one
    with pytest.raises(ServiceError, match=f"away from resting pose {side_pose}"):
        validator_service.placement(ValidationJob(object=BOX, hand="allegro", poses=pose, pose_index=side_pose,
                                                  frame=other), box)
    with pytest.raises(ValidationError, match="greater than or equal to 0"):
        GenerationJob(object=BOX, hand="allegro", batch_size=1, pose_index=-1)
    with pytest.raises(ValidationError, match=r"less than or equal to 6\.28"):
        GenerationJob(object=BOX, hand="allegro", batch_size=1, yaw_rad=7.0)
    with pytest.raises(ValidationError, match="pose_index places the object for a floating hand"):
        ValidationJob(object=BOX, hand="allegro", poses=pose, pose_index=0, with_arm=True)
