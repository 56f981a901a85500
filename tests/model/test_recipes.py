"""The training recipes: each is the shipped policy's own commands, and ``studio train --recipe`` trains its stages."""

from __future__ import annotations

import argparse
import json
import shlex
from pathlib import Path

import pytest
from synthetic_pairs import SyntheticPairs

from studio.model import train_command
from studio.model.config import PLANNING_FIELDS, ModelConfig, preset
from studio.model.recipes import RECIPES, recipe, stage_config

POLICIES = Path(train_command.__file__).resolve().parents[1] / "policies"
#: recipe -> the shipped policy it trained, whose JSON file lists the ``studio train`` commands.
SHIPPED = {"pick-place": "pick-place-cpu", "push": "push-cpu", "metaworld": "metaworld-cpu"}


def _parse(command: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    train_command.add_arguments(parser)
    words = shlex.split(command.split(" (")[0])  # the timing note after the command
    assert words[:2] == ["studio", "train"], command
    return parser.parse_args(words[2:])


@pytest.mark.parametrize("name", sorted(SHIPPED))
def test_each_stage_is_the_command_the_shipped_policy_was_trained_with(name):
    commands = json.loads((POLICIES / f"{SHIPPED[name]}.json").read_text())["trained_with"]
    stages = recipe(name).stages
    assert len(commands) == len(stages)
    stage_of_run_dir: dict[str, str] = {}
    for command, stage in zip(commands, stages, strict=True):
        args = _parse(command)
        scene = args.scene or "pick_place"
        shipped = preset(args.config, scene).with_overrides(args.set)
        # How a guided policy file it started from is planned is set at export, not by the training command.
        planning = {k: getattr(ModelConfig(), k) for k in PLANNING_FIELDS}
        shipped = shipped.with_changes(model=planning, train={"max_steps": args.steps, "seed": args.seed})
        run, same = stage_config(name, stage.name)
        assert same == stage and recipe(name).scene == scene
        assert run.with_changes(train={"max_steps": stage.steps, "seed": stage.seed_offset}) == shipped, stage
        if stage.init_from is None:
            assert args.init is None
        else:  # RUN/best.pt, RUN/last.pt, or RUN.pt exported from RUN/best.pt
            start = Path(args.init)
            assert stage_of_run_dir[start.parent.name or start.stem] == stage.init_from
            assert start.parent.name == "" or start.stem == stage.init_checkpoint
        stage_of_run_dir[args.out] = stage.name


def test_stages_start_only_from_earlier_stages_and_the_ablation_has_no_world_model():
    for r in RECIPES.values():
        names = [s.name for s in r.stages]
        assert len(set(names)) == len(names)
        for i, stage in enumerate(r.stages):
            assert stage.init_from is None or stage.init_from in names[:i]
            assert stage.init_checkpoint in ("best", "last")
    ablation = [
        stage_config("pick-place-no-world-model", s.name)[0]
        for s in recipe("pick-place-no-world-model").stages
    ]
    assert ablation and not any(run.model.world_model for run in ablation)
    assert stage_config("pick-place", "grow")[0].model.world_model is True


def test_unknown_recipes_and_stages_are_named():
    with pytest.raises(ValueError, match="unknown recipe 'pick'; choose from pick-place, "):
        recipe("pick")
    with pytest.raises(ValueError, match="no stage 'polish'; its stages: base, refine, grow"):
        stage_config("pick-place", "polish")


def test_a_recipe_stage_reaches_the_run_with_its_steps_seed_and_scene(monkeypatch):
    opened = []

    def fake_open(root, run, scene, progress=False):
        opened.append(scene)
        return SyntheticPairs(), SyntheticPairs(split="val")

    monkeypatch.setattr(train_command, "open_splits", fake_open)
    prepared = train_command.prepare_run("store", recipe="push", stage="grow", init="base/best.pt", seed=10)
    grow = recipe("push").stage("grow")
    assert opened == ["push"]
    assert (prepared.run.train.max_steps, prepared.run.train.seed) == (grow.steps, 10 + grow.seed_offset)
    assert prepared.run.train.freeze == ("encoder",) and prepared.run.train.pair_hue == 0.5
    given = train_command.prepare_run("store", recipe="push", steps=3, overrides=["train.val_every=1"])
    assert (given.run.train.max_steps, given.run.train.val_every, given.run.model.world_model) == (
        3,
        1,
        False,
    )


def test_the_command_line_refuses_a_stage_without_its_start_or_its_recipe(capsys):
    from studio.cli import main

    assert main(["train", "--data", "x", "--out", "y", "--recipe", "push", "--stage", "grow"]) == 2
    assert capsys.readouterr().err == (
        "studio train: stage 'grow' of recipe 'push' starts from stage 'base''s best checkpoint: name it with --init\n"
    )
    assert main(["train", "--data", "x", "--out", "y", "--stage", "grow"]) == 2
    assert "give the recipe too" in capsys.readouterr().err
    assert main(["train", "--data", "x", "--out", "y", "--recipe", "push", "--stage", "polish"]) == 2
    assert "its stages: base, grow" in capsys.readouterr().err


def test_the_quick_recipe_is_pick_place_at_48_by_64_on_a_shorter_schedule():
    quick, full = recipe("pick-place-quick"), recipe("pick-place")
    assert quick.scene == full.scene and [s.steps for s in quick.stages] == [1300, 900, 600]
    for q, f in zip(quick.stages, full.stages, strict=True):
        assert dict(q.model) == {**f.model, "image_size": (48, 64)} and q.train == f.train
        assert (q.name, q.seed_offset, q.init_from, q.init_checkpoint) == (
            f.name,
            f.seed_offset,
            f.init_from,
            f.init_checkpoint,
        )
        assert stage_config("pick-place-quick", q.name)[0].model.image_size == (48, 64)
