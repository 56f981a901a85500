"""Reading checkpoints back: the format check, the network rebuilt with its weights, and no trainer imported."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch
from synthetic_pairs import tiny_run_config

from studio.model.checkpoint import CHECKPOINT_FORMAT, load_checkpoint, model_from_checkpoint
from studio.model.osvi_wm import OSVIWM


def test_a_checkpoint_loads_into_the_network_it_was_saved_from(tmp_path):
    torch.manual_seed(0)
    run = tiny_run_config()
    saved = OSVIWM(run.model)
    torch.save(
        {"format": CHECKPOINT_FORMAT, "config": run.to_dict(), "model": saved.state_dict()}, tmp_path / "a.pt"
    )
    ckpt = load_checkpoint(tmp_path / "a.pt")
    loaded = model_from_checkpoint(ckpt)
    assert all(torch.equal(v, loaded.state_dict()[k]) for k, v in saved.state_dict().items())


def test_a_file_of_another_format_is_refused(tmp_path):
    torch.save({"format": "something-else/1", "model": {}}, tmp_path / "b.pt")
    with pytest.raises(ValueError, match="not an OSVI-WM checkpoint"):
        load_checkpoint(tmp_path / "b.pt")


def test_a_file_that_would_run_code_is_refused(tmp_path):
    torch.save({"format": CHECKPOINT_FORMAT, "hook": OSVIWM}, tmp_path / "c.pt")
    with pytest.raises(Exception, match=r"[Ww]eights only"):
        load_checkpoint(tmp_path / "c.pt")


def test_planning_and_evaluation_read_checkpoints_without_importing_the_trainer():
    code = (
        "import sys, studio.model.checkpoint, studio.model.planner, studio.eval.evaluation; "
        "assert 'studio.model.train' not in sys.modules, 'the trainer was imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
