"""Getting a planner: ``"oracle"`` plans from the simulator; models and other per-process values are made once."""

from __future__ import annotations

import pickle
import zipfile

import pytest

from studio.eval.oracle import OraclePlanner
from studio.eval.planners import load_planner, process_cached
from studio.sim.env import SimEnv


def test_process_cached_makes_a_value_once_per_key():
    made: list[str] = []

    def make(name: str):
        return lambda: made.append(name) or name

    assert process_cached(("test", "a"), make("a")) == "a"
    assert process_cached(("test", "a"), make("again")) == "a"
    assert process_cached(("test", "b"), make("b")) == "b"
    assert made == ["a", "b"]


def test_oracle_is_a_fresh_oracle_planner_on_the_jobs_env():
    env = SimEnv("pick_place", "panda", image_size=(60, 80))
    try:
        planner = load_planner("oracle", env)
        assert isinstance(planner, OraclePlanner) and planner.env is env
        assert load_planner("oracle", env) is not planner  # bound to its env: never cached across jobs
        env.reset("pick_place/cube->red", 0)
        frame = env.render("external")
        cam = env.camera_model("external")
        plan = planner.plan(frame[None], frame, cam.K, cam.T_world_cam)
        assert plan.waypoints_world.shape == (5, 4) and plan.waypoints_cam.shape == (5, 4)
    finally:
        env.close()


def test_a_checkpoint_of_another_scene_is_refused_before_it_is_loaded(tmp_path):
    """A push model never plans a pick-and-place task (the file's recorded tasks say which scene it learnt)."""
    path = tmp_path / "push-model.pt"
    with zipfile.ZipFile(path, "w") as zf:  # a checkpoint's metadata as torch.save writes it, without weights
        zf.writestr("push-model/data.pkl", pickle.dumps({"tasks": ["push/red-forward"]}, protocol=2))
    env = SimEnv("pick_place", "panda", image_size=(60, 80))
    try:
        with pytest.raises(ValueError, match="trained on push tasks: it does not plan pick_place tasks"):
            load_planner(str(path), env)
    finally:
        env.close()
