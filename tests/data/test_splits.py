"""Split files: the shipped task splits, validation hold-out, malformed specs."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from studio.data.splits import SplitSpec, available_splits, load_split, validation_ids
from studio.sim.tasks import list_tasks


def test_pick_place_split_follows_paper():
    spec = load_split("pick_place")
    assert len(spec.train) == 14
    assert spec.test == ("pick_place/bar->blue", "pick_place/bar->yellow")
    assert sorted(spec.train + spec.test) == sorted(list_tasks("pick_place"))
    assert spec.tasks("val") == spec.train


def test_push_split():
    spec = load_split("push")
    assert len(spec.train) == 3 and spec.test == ("push/blue-backward",)
    assert sorted(spec.train + spec.test) == sorted(list_tasks("push"))
    assert available_splits() == ["metaworld", "metaworld_ablation", "pick_place", "push"]


def test_metaworld_splits_follow_paper():
    spec = load_split("metaworld")
    raw = json.loads((Path(__file__).parents[2] / "studio/splits/metaworld.json").read_text())
    easy, hard = raw["test_groups"]["easy"], raw["test_groups"]["hard"]
    assert easy == ["metaworld/button-press-v3", "metaworld/pick-place-wall-v3"]
    assert hard == ["metaworld/window-open-v3", "metaworld/door-unlock-v3"]
    assert spec.scene == "metaworld" and spec.test == tuple(easy + hard) and len(spec.train) == 46
    assert spec.test_groups == {"easy": tuple(easy), "hard": tuple(hard)}
    assert spec.replan_groups == ("hard",) and spec.replanned_tasks() == tuple(
        hard
    )  # the paper re-plans on hard
    assert sorted(spec.train + spec.test) == sorted(list_tasks("metaworld"))
    assert set(raw["twins"]) == set(spec.test) and set(raw["twins"].values()) <= set(spec.train)
    ablation = load_split("metaworld_ablation")
    assert ablation.scene == "metaworld" and ablation.test == spec.test
    assert ablation.replanned_tasks() == spec.replanned_tasks()
    assert load_split("pick_place").replanned_tasks() == ()
    assert set(spec.train) - set(ablation.train) == {"metaworld/window-close-v3"}
    assert set(ablation.train) < set(spec.train)


def test_the_meta_world_protocol_is_the_papers_and_the_tabletop_scenes_have_none():
    """The paper re-plans every 500 steps for up to 2,000 on the hard tasks only: three re-plans, each plan at most
    500 control ticks; the easy tasks get one attempt. What the protocol says nothing of gets None."""
    from studio.eval.evaluation import PAPER_PLAN_TICKS

    for name in ("metaworld", "metaworld_ablation"):
        spec = load_split(name)
        assert spec.plan_ticks == PAPER_PLAN_TICKS == 500 and spec.replan_budget == 3
        assert [spec.protocol_replans(t) for t in spec.test] == [0, 0, 3, 3]
        assert spec.protocol_replans("metaworld/assembly-v3") is None  # a training task
    for name in ("pick_place", "push"):
        spec = load_split(name)
        assert spec.plan_ticks is None and spec.replan_budget == 0
        assert {spec.protocol_replans(t) for t in spec.test + spec.train} == {None}


def test_split_from_file_and_errors(tmp_path):
    path = tmp_path / "mine.json"
    path.write_text(json.dumps({"scene": "pick_place", "train": ["pick_place/cube->red"], "test": []}))
    assert load_split(path).train == ("pick_place/cube->red",)
    with pytest.raises(ValueError, match="both in train and test"):
        SplitSpec("x", train=("a/b",), test=("a/b",))
    with pytest.raises(ValueError, match="names non-test tasks"):
        SplitSpec("x", train=("a/b",), test=("a/c",), test_groups={"easy": ("a/b",)})
    with pytest.raises(ValueError, match=r"replan_groups names groups it does not define: \['hard'\]"):
        SplitSpec("x", train=("a/b",), test=("a/c",), test_groups={"easy": ("a/c",)}, replan_groups=("hard",))
    with pytest.raises(ValueError, match="replan_budget must be >= 0, got -1"):
        SplitSpec("x", train=("a/b",), test=(), replan_budget=-1)
    with pytest.raises(ValueError, match="plan_ticks must be >= 1 or absent, got 0"):
        SplitSpec.from_dict({"scene": "x", "train": ["a/b"], "plan_ticks": 0})
    with pytest.raises(ValueError, match="no split file"):
        load_split("kitchen")
    with pytest.raises(ValueError, match="split must be"):
        load_split("push").tasks("holdout")


def test_validation_ids_stable_fraction():
    ids = [f"ep{i}" for i in range(40)]
    held = validation_ids(ids, 0.1)
    assert len(held) == 4 and held <= set(ids)
    assert validation_ids(reversed(ids), 0.1) == held  # independent of order
    grown = validation_ids([*ids, *(f"new{i}" for i in range(10))], 0.1)
    assert len(grown) == 5
    assert validation_ids(["a"], 0.5) == set()
    assert len(validation_ids(["a", "b"], 0.9)) == 1  # never all of them
    assert validation_ids(ids, 0.0) == set()


def test_resolve_tasks_takes_split_words_and_names_as_a_string_or_a_list():
    from studio.data.splits import resolve_tasks

    held_out = ["pick_place/bar->blue", "pick_place/bar->yellow"]
    assert resolve_tasks("pick_place", "held-out") == held_out
    assert resolve_tasks("pick_place", ["test"]) == held_out
    assert resolve_tasks("pick_place", "pick_place/cube->red, pick_place/bar->blue") == [
        "pick_place/cube->red",
        "pick_place/bar->blue",
    ]
    assert resolve_tasks("pick_place", ["pick_place/cube->red,test", "pick_place/cube->red"]) == [
        "pick_place/cube->red",
        *held_out,
    ]  # each task once, in order
    assert len(resolve_tasks("pick_place", "all")) == 16
    assert len(resolve_tasks("push", "train")) == len(load_split("push").train)


def test_resolve_tasks_errors_say_what_is_wrong():
    from studio.data.splits import resolve_tasks, scene_of_task

    with pytest.raises(ValueError, match="unknown task 'pick_place/ball->red' for scene 'pick_place'"):
        resolve_tasks("pick_place", "pick_place/ball->red")
    with pytest.raises(ValueError, match="belongs to scene 'push', not 'pick_place'"):
        resolve_tasks("pick_place", "pick_place/cube->red,push/red-forward")
    with pytest.raises(ValueError, match="scene 'kitchen' has no tasks"):
        resolve_tasks("kitchen", "all")
    with pytest.raises(ValueError, match="no tasks given"):
        resolve_tasks("pick_place", " , ")
    assert scene_of_task("metaworld/button-press-v3") == "metaworld"
    with pytest.raises(ValueError, match="<scene>/<task>"):
        scene_of_task("cube->red")
