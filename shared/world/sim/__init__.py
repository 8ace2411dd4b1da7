"""PyBullet scene builder shared by the validator, the planner's collision checks and the simulated robot.

    from shared.world.sim import SimScene, PhysicsParams
    with SimScene(PhysicsParams()) as scene:
        obj = scene.add_object(urdf, T_world_object)
        hand = scene.add_floating_hand(hand_model.urdf_path, hand_model.joint_names)
        hand.place(T_world_base, q); hand.drive(T_next); scene.step()
"""
from shared.world.sim.params import REFERENCE_PARAMS, PhysicsParams
from shared.world.sim.scene import (
    Body,
    FloatingHand,
    SimError,
    SimScene,
    c_stdout_to_stderr,
    pos_quat_to_transform,
    transform_to_pos_quat,
)

__all__ = [
    "REFERENCE_PARAMS", "PhysicsParams", "Body", "FloatingHand", "SimError", "SimScene",
    "c_stdout_to_stderr", "pos_quat_to_transform", "transform_to_pos_quat",
]
