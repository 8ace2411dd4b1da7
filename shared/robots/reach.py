"""How far an arm with its hand can touch anything: a ball around the arm's shoulder.

Every point of the hand lies within `radius_m` of the shoulder (the origin of the arm's first joint, which
that joint turns about and so never moves) in every configuration: the sum of the distances between the
successive link frames from there to the flange (each fixed by its joint's origin, whatever the joint
angles), the mount's offset from the flange to the hand base, and how far the open hand's contact points
stand from its base (fingers stretched: as far as they reach). The bound is generous (no joint limit, no
self-collision, the arm folded straight out), so a point outside it is out of reach for certain, and a point
inside may still be: IK says that one.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from shared.robots.arms import ArmModel, load_arm, mount
from shared.robots.hands import HandModel, load_hand


@dataclass(frozen=True)
class Reach:
    """The ball that holds every point the hand can be at, in the arm's base frame."""

    shoulder_base: np.ndarray  # [3], the origin of the arm's first joint
    radius_m: float

    def shoulder_world(self, T_world_base: np.ndarray) -> np.ndarray:
        T = np.asarray(T_world_base, dtype=np.float64)
        shoulder: np.ndarray = T[:3, :3] @ self.shoulder_base + T[:3, 3]
        return shoulder


@functools.cache
def reach(arm_name: str, hand_name: str) -> Reach:
    """The reach of `arm_name` carrying `hand_name` (computed once per process)."""
    arm, hand = load_arm(arm_name), load_hand(hand_name)
    first_joint = arm.robot.joint(arm.joint_names[0])
    radius = _chain_length_m(arm) + float(np.linalg.norm(mount(arm, hand)[:3, 3])) + _hand_extent_m(hand)
    return Reach(shoulder_base=first_joint.origin[:3, 3].astype(np.float64), radius_m=radius)


def _chain_length_m(arm: ArmModel) -> float:
    """Sum of the distances between successive link frames from the first joint's link to the flange."""
    length, link = 0.0, arm.flange_link
    while (joint := arm.robot.parent_joint(link)) is not None and joint.name != arm.joint_names[0]:
        length += float(np.linalg.norm(joint.origin[:3, 3]))
        link = joint.parent
    return length


def _hand_extent_m(hand: HandModel) -> float:
    """How far the open hand's contact points stand from its base link's origin."""
    points, _ = hand.contact_candidates_world(hand.forward(hand.open_pose(1)))
    return float(np.linalg.norm(points[0].double().numpy(), axis=1).max())
