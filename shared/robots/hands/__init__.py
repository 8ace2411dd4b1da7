"""Dexterous hand models (Allegro right, LEAP right): kinematics, collision primitives, contact candidates.

    from shared.robots.hands import load_hand
    hand = load_hand("allegro")
    state = hand.forward(pose)              # pose [B,25] = [p, r6, q] of the base link in some frame
    hand.signed_distance(points, state)     # [B,N], negative inside the hand
    hand.contact_points(state, indices)     # selected contact candidates and their normals
"""
from shared.frames import POSE_DIM
from shared.robots.hands.config import HAND_SPECS, ContactRegion, HandSpec
from shared.robots.hands.model import (
    ContactCandidates,
    HandModel,
    HandModelError,
    HandState,
    load_hand,
)
from shared.robots.hands.urdf import RobotAssetError

__all__ = [
    "HAND_SPECS",
    "POSE_DIM",
    "ContactCandidates",
    "ContactRegion",
    "HandModel",
    "HandModelError",
    "HandSpec",
    "HandState",
    "RobotAssetError",
    "load_hand",
]
