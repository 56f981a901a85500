"""Simulation core: scenes, robots, tasks, cameras, teleop IK, waypoint controller, scripted experts."""

import os

# Headless rendering by default. This must happen before anything imports mujoco (every module of this
# package may), or MuJoCo picks GLFW, which aborts without a display.
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
