import os

# MuJoCo picks its OpenGL platform from MUJOCO_GL once, when it is first imported, and pytorch_kinematics imports it
# with the robot models, before any renderer is made. A robot has no display: headless EGL, unless the user chose
# another (shared/execution/robots/mujoco/cameras.py's RenderUnavailable names the choice when none works).
os.environ.setdefault("MUJOCO_GL", "egl")
