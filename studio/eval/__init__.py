"""Evaluation: where the model and the simulator meet — imitation rollouts, planners, `studio eval`, `studio results`.

Layered above ``sim``, ``data`` and ``model`` (it may import all three) and below ``backend``, whose rollout and
plan jobs are thin handlers around it.
"""
