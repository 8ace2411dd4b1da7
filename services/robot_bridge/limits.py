"""Re-export: the robot limits moved to `shared.robot_limits` (the planner checks plans against them too)."""
from shared.robot_limits import (  # noqa: F401
    DEFAULT_WORKSPACE,
    POSITION_EPS_RAD,
    VELOCITY_EPS,
    WORKSPACE_STEP_RAD,
    LimitViolation,
    RobotLimits,
    WorkspaceBox,
    densify,
)
