"""Re-export: the fixed spatula pose moved to `shared.fixed_poses` (the planner uses it too)."""
from shared.fixed_poses import (  # noqa: F401
    SPATULA_GAP_M,
    SPATULA_JOINTS,
    SPATULA_TABLE_CLEARANCE_M,
    FixedPoseError,
    spatula_joints,
    spatula_pose,
    spatula_rotation,
)
