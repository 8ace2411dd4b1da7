"""What an evaluation trial asks of the system: the task families (docs/evaluation.md, "Tasks").

Every task meets the same placements and execution worlds (an episode's seeds do not depend on its task), so a
method's tasks pair trial by trial. Light on purpose: the CLI reads it to check `--tasks`.
"""
from __future__ import annotations

# "paper": the paper's push, 0.20 m along a direction, within 3 cm, turned <= 45 degrees;
# "pose": the same point and the object turned POSE_TASK_TURN_DEG, within 2 cm and 15 degrees of that yaw (a
# PushRequest goal_xy + goal_yaw_deg), on the objects whose yaw a camera can see.
# The shape-class tasks ask the paper's push of objects of one class (docs/evaluation.md, "Shape classes"), drawn
# from the split's procedural and everyday families (SHAPE_TASK_OBJECTS of each, spread over the families).
# "wall": the paper's push away from a wall: the wall WALL_GAP_M beside the object where it rests, behind it at
# WALL_ANGLE_DEG to the push (on one side, or the other on a mirrored trial: `Episode.mirrored`), so the push leads away from it. A hand
# square behind the object would stand where the wall is: the robot must find another way to push (a fingertip on
# the free corner, a pull from above), never touching the wall.
# "corner": the wall task's two walls at once (both sides), meeting behind the object: it stands in a right-angled
# corner, WALL_GAP_M from each wall, and is pushed out of it.
# "clutter": the paper's push with neighbours standing CLUTTER_GAP_M from the object (cans and cups: CLUTTER_PROPS,
# library objects of the train split): one beside it, and unless the trial is mirrored a second behind it on the other side. The
# request tells where they stand as cylinder obstacles (what a user's perception gives); the cameras see them. A
# neighbour moved more than NEIGHBOUR_MOVED_M fails the trial.
SHAPE_TASKS = ("tall", "flat", "small", "round")
TASKS = ("paper", "pose", "wall", "corner", "clutter", *SHAPE_TASKS)
POSE_TASK_TURN_DEG = 30.0  # counterclockwise, clockwise on a mirrored trial
SHAPE_TASK_OBJECTS = 6
WALL_GAP_M = 0.01  # the object's footprint to the wall's face
WALL_ANGLE_DEG = 45.0  # between the push and the wall
WALL_LENGTH_M = 0.30  # centred beside the object
WALL_HEIGHT_M = 0.06
CLUTTER_PROPS = ("proc-cylinder-007", "proc-cylinder-010", "proc-cylinder-016", "proc-cylinder-025")
CLUTTER_GAP_M = (0.01, 0.03)  # the object's footprint to a neighbour's, drawn per neighbour
CLUTTER_BEARINGS_DEG = ((90.0, -135.0), (-90.0,))  # from the push direction; on a mirrored trial
NEIGHBOUR_MOVED_M = 0.01
PAPER_CRITERION = "0.20 m along the direction, within 3 cm, turned <= 45 degrees, upright"
TASK_CRITERIA = {
    "paper": PAPER_CRITERION + " (round objects: position only)",
    "pose": f"the same point and the start's yaw turned {POSE_TASK_TURN_DEG:g} degrees (either way), within 2 cm and "
            "15 degrees of that yaw, upright; objects whose yaw a camera can see",
    "wall": PAPER_CRITERION + f"; away from a wall {WALL_GAP_M * 100:g} cm from the object, at {WALL_ANGLE_DEG:g} "
            "degrees to the push behind it (left or right): the robot touching the wall fails",
    "corner": PAPER_CRITERION + f"; out of a right-angled corner behind it, {WALL_GAP_M * 100:g} cm from each wall, the "
              f"walls at {WALL_ANGLE_DEG:g} degrees to the push on either side: the robot touching a wall fails",
    "clutter": PAPER_CRITERION + f"; one or two neighbours (cans, cups) {CLUTTER_GAP_M[0] * 100:g}-"
               f"{CLUTTER_GAP_M[1] * 100:g} cm from the object, beside and behind it: a neighbour moved more than "
               f"{NEIGHBOUR_MOVED_M * 100:g} cm fails",
    "tall": PAPER_CRITERION + "; standing objects over 1.5 times as tall as their footprint is wide (bottles, boxes on "
            "end): toppling fails",
    "flat": PAPER_CRITERION + "; lying objects under 0.4 times as tall as their footprint is wide (plates, books, spatulas)",
    "small": PAPER_CRITERION + "; objects no side of which is over 4 cm",
    "round": "0.20 m along the direction, within 3 cm, position only (turn and tilt reported, not judged); objects that "
             "roll where they rest (balls, fruit, cans on their side)",
}
