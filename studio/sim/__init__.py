"""Simulation core: scenes, robots, tasks, cameras, teleop IK, waypoint controller, scripted experts."""
