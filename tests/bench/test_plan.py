"""`studio bench plan`: grasp/release read-out of plans, object matching and scene dependence on stored scenes."""

from __future__ import annotations

import argparse

import numpy as np
import pytest
import torch

from studio.bench import plan as plan_bench
from studio.cli import main
from studio.data.paths import SHIPPED_POLICY_DIR

torch.set_num_threads(1)
TASK = "pick_place/bar->blue"


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    plan_bench.add_arguments(parser)
    return parser.parse_args(list(argv))


def test_grasp_is_the_first_closed_waypoint_and_release_the_next_open_one():
    wps = np.array(
        [[0.1, 0.0, 0.3, 0], [0.2, 0.1, 0.05, 1], [0.2, 0.1, 0.3, 1], [0.4, 0.2, 0.1, 0], [0.4, 0.2, 0.3, 0]]
    )
    grasp, release = plan_bench.grasp_and_release(wps)
    assert np.allclose(grasp, [0.2, 0.1]) and np.allclose(release, [0.4, 0.2])
    assert plan_bench.grasp_and_release(np.zeros((5, 4))) == (None, None)
    arrays = {"gripper_cmd": np.array([0, 0, 1, 1, 1, 0, 0.0]), "ee_pos_world": np.arange(21.0).reshape(7, 3)}
    assert np.allclose(
        plan_bench.scripted_release(arrays), [15.0, 16.0]
    )  # the step after the opening command
    assert plan_bench.task_object("pick_place/cube->red") == "cube"
    with pytest.raises(SystemExit, match="scene/object->target"):
        plan_bench.task_object("metaworld/door-unlock-v3")


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    root = tmp_path_factory.mktemp("store")
    for robot, n in (("sawyer", "2"), ("panda", "3")):
        assert (
            main(
                [
                    "collect",
                    "--robot",
                    robot,
                    "--tasks",
                    TASK,
                    "--episodes",
                    n,
                    "--seed",
                    "3",
                    "--data-dir",
                    str(root),
                    "--no-progress",
                ]
            )
            == 0
        )
    return root


class _FixedPlanner:
    """Plans the same waypoints whatever it sees: a policy that ignores both demonstration and scene."""

    def plan(self, expert_frames, agent_frame, K, T_world_cam):
        wps = np.array(
            [
                [0.0, 0.0, 1.0, 0],
                [0.05, 0.0, 0.85, 1],
                [0.05, 0.0, 1.0, 1],
                [0.1, 0.2, 0.9, 0],
                [0.1, 0.2, 1.0, 0],
            ]
        )
        return type("Plan", (), {"waypoints_world": wps})()

    def name_demonstration(self, expert_frames):
        return None  # no demonstration-task head


def test_a_plan_that_ignores_the_scene_has_zero_scene_dependence(store, monkeypatch):
    from studio.model import planner as planner_module

    monkeypatch.setattr(planner_module.Planner, "load", classmethod(lambda cls, path: _FixedPlanner()))
    result = plan_bench.measure(_args("--checkpoint", "fixed", "--data-dir", str(store), "--tasks", TASK))
    row = result["tasks"][TASK]
    assert row["scenes"] == 3 and row["scene_dependence"] == 0.0
    assert result["chance_right_object"] == 0.25 and 0.0 <= result["right_object"] <= 1.0
    assert row["grasp_err_m"] > 0 and row["release_err_m"] > 0
    assert "named" not in row


def test_the_shipped_policy_is_measured_on_plain_and_mirrored_demonstrations(store):
    policy = str(SHIPPED_POLICY_DIR / "pick-place-cpu.pt")
    plain = plan_bench.measure(_args("--checkpoint", policy, "--data-dir", str(store), "--tasks", TASK))
    mirrored = plan_bench.measure(
        _args("--checkpoint", policy, "--data-dir", str(store), "--tasks", TASK, "--mirror")
    )
    for result in (plain, mirrored):
        row = result["tasks"][TASK]
        assert row["scenes"] == 3 and np.isfinite(row["grasp_err_m"]) and row["scene_dependence"] is not None
    assert mirrored["mirror"] and not plain["mirror"]
    named = plain["tasks"][TASK]["named"]  # its head names whole training tasks; bar->blue is not one of them
    assert sum(named.values()) == 3 and all("->" in name and name != "bar->blue" for name in named)
    assert plain["grasp_to_demo_object_m"] != mirrored["grasp_to_demo_object_m"]


def test_missing_episodes_are_a_clear_error(tmp_path):
    with pytest.raises(SystemExit, match="needs stored agent and expert episodes"):
        plan_bench.measure(
            _args(
                "--checkpoint",
                str(SHIPPED_POLICY_DIR / "pick-place-cpu.pt"),
                "--data-dir",
                str(tmp_path),
                "--tasks",
                TASK,
            )
        )
