"""What an evaluation trial asks of the system: the task families (docs/evaluation.md, "Tasks").

Every task meets the same placements and execution worlds (an episode's seeds do not depend on its task), so a
method's tasks pair trial by trial. Light on purpose: the CLI reads it to check `--tasks`.
"""
from __future__ import annotations

# "paper": the paper's push, 0.20 m along a direction, within 3 cm, turned <= 45 degrees;
# "pose": the same point and the object turned POSE_TASK_TURN_DEG, within 2 cm and 15 degrees of that yaw (a
# PushRequest goal_xy + goal_yaw_deg), on the objects whose yaw a camera can see.
TASKS = ("paper", "pose")
POSE_TASK_TURN_DEG = 30.0  # counterclockwise on even trials, clockwise on odd
TASK_CRITERIA = {
    "paper": "0.20 m along the direction, within 3 cm, turned <= 45 degrees, upright (round objects: position only)",
    "pose": f"the same point and the start's yaw turned {POSE_TASK_TURN_DEG:g} degrees (either way), within 2 cm and "
            "15 degrees of that yaw, upright; objects whose yaw a camera can see",
}
