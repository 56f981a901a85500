"""The Compare tab's checkpoint lists: only the chosen scene's checkpoints, and the two it starts with."""

from __future__ import annotations

import os

import pytest

from studio.ui.panels.compare import default_checkpoints, scene_checkpoints
from studio.ui.runs import RunRegistry


def write_run(root, name: str, tasks: list[str], mtime: float) -> None:
    import torch

    path = root / "runs" / name / "best.pt"
    path.parent.mkdir(parents=True)
    torch.save({"tasks": tasks, "step": 1}, path)
    os.utime(path, (mtime, mtime))


@pytest.fixture
def runs(tmp_path):
    write_run(tmp_path, "push-run", ["push/red-forward"], 1000.0)
    write_run(tmp_path, "pp-old", ["pick_place/cube->red"], 2000.0)
    write_run(tmp_path, "pp-new", ["pick_place/cube->red", "pick_place/cube->green"], 3000.0)
    return RunRegistry(tmp_path)


def test_only_checkpoints_of_the_scene_are_offered_best_first(runs):
    ids = [c.id for c in scene_checkpoints(runs, "pick_place")]
    assert ids == [
        "default/pick-place-cpu",
        "default/pick-place-no-world-model",
        "default/pick-place-panda-demos",
        "default/pick-place-human-demos",
        "pp-new/best",
        "pp-old/best",
        "oracle",
    ]
    push = [c.id for c in scene_checkpoints(runs, "push")]
    assert "push-run/best" in push and not [i for i in push if "pick" in i or "metaworld" in i]
    assert [c.id for c in scene_checkpoints(runs, "metaworld")] == ["default/metaworld-cpu", "oracle"]


def test_a_fresh_comparison_starts_from_the_active_policy_against_the_next_best(runs):
    assert default_checkpoints(runs, "pick_place") == (
        "default/pick-place-cpu",
        "default/pick-place-no-world-model",
    )
    assert default_checkpoints(runs, "push") == ("default/push-cpu", "default/push-human-demos")
    assert default_checkpoints(runs, "metaworld") == ("default/metaworld-cpu", "oracle")
    runs.set_active("pp-old/best", "pick_place")
    assert default_checkpoints(runs, "pick_place") == ("pp-old/best", "default/pick-place-cpu")
    runs.set_active("oracle", "push")
    assert default_checkpoints(runs, "push") == ("oracle", "default/push-human-demos")
