"""Shared simulator fixtures: environments are built once per test module (compiling takes ~0.3 s)."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import pytest

from studio.sim.env import SimEnv


@pytest.fixture(scope="module")
def env_factory():
    made: dict = {}

    def make(scene: str, robot: str) -> SimEnv:
        key = (scene, robot)
        if key not in made:
            made[key] = SimEnv(scene, robot)
        return made[key]

    yield make
    for env in made.values():
        env.close()
