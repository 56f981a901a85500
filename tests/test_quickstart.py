"""`studio quickstart` end to end at a tiny budget: every stage runs, is timed, and the summary is written."""

from __future__ import annotations

import argparse
import json

import pytest
import torch

from studio.cli import main
from studio.model.checkpoint import load_checkpoint
from studio.model.precision import resolve_precision
from studio.model.recipes import recipe
from studio.quickstart import VARIANT_RECIPES, add_arguments, early_overrides, schedule

pytestmark = pytest.mark.timeout(900)


@pytest.mark.slow
def test_quickstart_collects_trains_evaluates_and_reports_stage_times(tmp_path, capsys):
    args = [
        "quickstart",
        "--data-dir",
        str(tmp_path / "data"),
        "--out",
        str(tmp_path / "run"),
        "--episodes",
        "2",
        "--steps",
        "2",
        "--refine-steps",
        "1",
        "--grow-steps",
        "1",
        "--eval-episodes",
        "1",
        "--workers",
        "1",
        "--set",
        "train.batch_size=4",
    ]
    assert main(args) == 0
    summary = json.loads((tmp_path / "run" / "quickstart.json").read_text())
    assert set(summary["stage_wall_s"]) == {"collect", "train", "refine", "grow", "eval"}
    # The refine stage starts from the first stage's weights, the grow stage from the refine stage's
    # lowest-validation-loss checkpoint, and the grow stage's is evaluated.
    assert summary["checkpoint"] == str(tmp_path / "run" / "grow" / "best.pt")
    base = load_checkpoint(tmp_path / "run" / "base" / "last.pt")
    refined = load_checkpoint(tmp_path / "run" / "refine" / "best.pt")
    grown = load_checkpoint(summary["checkpoint"])
    assert base["step"] == 2 and refined["step"] == 1
    refine_run = json.loads((tmp_path / "run" / "refine" / "config.json").read_text())
    assert refine_run["init"] == str(tmp_path / "run" / "base" / "last.pt")
    assert base["config"]["train"]["expert_hflip"] == 0.5 and refined["config"]["train"]["alpha_warmup"] == 0
    assert refined["config"]["train"]["demo_task_weight"] == 1.0 and refined["config"]["train"]["seed"] == 1
    # OSVI-WM is trained without its world model first, then grown: 𝒲 is added to the refined weights.
    assert (
        base["config"]["model"]["world_model"] is False and refined["config"]["model"]["world_model"] is False
    )
    assert grown["config"]["model"]["world_model"] is True and grown["config"]["train"]["seed"] == 2
    # Pairs are mirrored in every stage; the grow stage keeps the encoder it inherits.
    assert base["config"]["train"]["hflip"] == 0.5 and grown["config"]["train"]["hflip"] == 0.5
    assert tuple(grown["config"]["train"]["freeze"]) == ("encoder",) and not base["config"]["train"]["freeze"]
    assert all(
        torch.equal(refined["model"][k], grown["model"][k])
        for k in refined["model"]
        if k.startswith("encoder.")
    )
    grow_run = json.loads((tmp_path / "run" / "grow" / "config.json").read_text())
    assert grow_run["init"] == str(tmp_path / "run" / "refine" / "best.pt")
    assert summary["variant"] == "osvi-wm"
    # Every stage trains in the precision ``auto`` chose for this machine.
    assert summary["precision"] == resolve_precision("auto")
    for ckpt in (base, refined, grown):
        assert ckpt["config"]["train"]["precision"] == summary["precision"]
    assert summary["rollouts"] == 2 and set(summary["tasks"]) == {
        "pick_place/bar->blue",
        "pick_place/bar->yellow",
    }
    assert 0.0 <= summary["held_out_success"] <= 1.0
    out = capsys.readouterr().out
    assert "held-out success" in out and "total" in out
    # Re-running resumes: collection and training find their work done.
    assert main(args) == 0
    again = json.loads((tmp_path / "run" / "quickstart.json").read_text())
    assert again["stage_wall_s"]["collect"] < summary["stage_wall_s"]["collect"]


def test_quickstart_trains_the_full_model_unless_told_otherwise():
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    assert parser.parse_args([]).variant == "osvi-wm" and parser.parse_args([]).precision == "auto"
    assert VARIANT_RECIPES["osvi-wm"] == "pick-place-quick"
    # Each variant brings its own schedule unless the steps are given.
    assert schedule("osvi-wm", None, None) == (1300, 900, 600)
    assert schedule("no-world-model", None, None) == (1600, 1100, 0)
    assert schedule("no-world-model", 5, 0) == (5, 0, 0) and schedule("osvi-wm", 5, 0, 0) == (5, 0, 0)
    with pytest.raises(ValueError, match="no-world-model variant has none"):
        schedule("no-world-model", None, None, 100)
    # OSVI-WM grows 𝒲 onto stages trained without it, or, with no grow steps, trains it whole from the start.
    assert early_overrides("osvi-wm", 700) == () and early_overrides("no-world-model", 0) == ()
    assert early_overrides("osvi-wm", 0) == ("model.world_model=true",)
    osvi_wm, ablation = (recipe(VARIANT_RECIPES[v]) for v in ("osvi-wm", "no-world-model"))
    assert [s.name for s in osvi_wm.stages] == ["base", "refine", "grow"]
    assert [s.name for s in ablation.stages] == ["base", "refine"]
    assert (
        osvi_wm.stage("base").model["world_model"] is False
        and "world_model" not in osvi_wm.stage("grow").model
    )
    with pytest.raises(SystemExit):
        parser.parse_args(["--variant", "no-such-model"])
