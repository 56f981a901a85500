"""Training on what a user has: batches no larger than the pairs, the steps a run takes, the fine-tuning schedule,
and `studio train` on a store of one to three pairs (clamped, said, trained; refused with what to record)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pytest
import torch

from studio.data.store import EpisodeStore
from studio.model import train_command
from studio.model.checkpoint import load_checkpoint
from studio.model.config import (
    FINE_TUNE_BATCH,
    FINE_TUNE_LR,
    FINE_TUNE_STEPS,
    fine_tune_config,
    fine_tune_steps,
    fit_batch,
    preset,
    steps_for,
)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "data"))
from data_fixtures import make_recording
from tiny_network import TINY

torch.set_num_threads(1)
RED = "pick_place/cube->red"


def test_a_batch_larger_than_the_pairs_is_lowered_to_them_and_said():
    run = preset("cpu")
    assert run.train.batch_size == 16
    fitted, note = fit_batch(run, 3)
    assert fitted.train.batch_size == 3 and run.train.batch_size == 16  # a copy; the preset is untouched
    assert note == "batch size 16 lowered to 3: there are only 3 training pairs"
    assert fit_batch(run, 1)[1] == "batch size 16 lowered to 1: there is only 1 training pair"
    same, none = fit_batch(run, 16)
    assert same is run and none is None
    with pytest.raises(ValueError, match="no training pairs"):
        fit_batch(run, 0)


def test_steps_are_the_epochs_over_the_pairs_unless_set():
    train = preset("cpu").train  # 10 epochs, batch 16
    assert steps_for(train, 160) == 100 and steps_for(train, 33) == 20
    assert steps_for(fit_batch(preset("cpu"), 1)[0].train, 1) == 10  # one pair, batch 1: 10 epochs of 1 step
    assert steps_for(preset("cpu").with_overrides(["train.max_steps=7"]).train, 160) == 7


def test_the_fine_tuning_schedule_is_short_and_bounded():
    lo, hi = FINE_TUNE_STEPS
    assert fine_tune_steps(1) == lo and fine_tune_steps(10_000) == hi
    assert lo <= fine_tune_steps(81) == 40 <= hi  # 10 batches of 8 per pass, four passes
    saved = preset("cpu").with_overrides(["train.freeze=encoder", "train.expert_hflip=0.5"]).to_dict()
    run = fine_tune_config(saved, 81)
    t = run.train
    assert (t.batch_size, t.max_steps, t.lr_max) == (FINE_TUNE_BATCH, 40, FINE_TUNE_LR)
    assert t.freeze == ("encoder",) and t.expert_hflip == 0.5  # the policy's own settings are kept
    assert (t.alpha_warmup, t.aug_warmup, t.num_workers) == (0.0, 0.0, 0)
    assert t.val_every == 40 and run.model == preset("cpu").model
    assert fine_tune_config(saved, 3).train.batch_size == 3
    longer = fine_tune_config(saved, 81, ["train.max_steps=100"]).train
    assert longer.max_steps == 100 and longer.val_every == 100
    with pytest.raises(ValueError, match="no training pairs"):
        fine_tune_config(saved, 0)


def _store(root: Path, experts: int, agents: int, failed: int = 0) -> Path:
    with EpisodeStore(root) as store:
        seed = 0
        for robot, role, n in (("sawyer", "expert", experts), ("panda", "agent", agents)):
            for _ in range(n):
                store.add_episode(
                    make_recording(task=RED, robot=robot, seed=seed), role=role, source="teleop"
                )
                seed += 1
        for _ in range(failed):
            rec = make_recording(task=RED, robot="sawyer", seed=seed, success=False)
            store.add_episode(rec, role="expert", source="teleop")
            seed += 1
    return root


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    train_command.add_arguments(parser)
    return parser.parse_args(list(argv))


def test_a_store_without_pairs_is_refused_with_what_to_record(tmp_path):
    root = _store(tmp_path / "data", experts=0, agents=0, failed=1)
    with pytest.raises(train_command.NoTrainingPairs, match="record a successful demonstration"):
        train_command.prepare_run(str(root), overrides=TINY)
    root = _store(tmp_path / "one-side", experts=1, agents=0)
    with pytest.raises(train_command.NoTrainingPairs, match="agent \\(Panda\\) episode of cube->red"):
        train_command.prepare_run(str(root), overrides=TINY)


@pytest.mark.slow
def test_one_pair_trains_with_the_preset_batch_lowered_and_fine_tunes(tmp_path, capsys):
    """One demonstration and one agent episode: `studio train` says the batch was lowered and trains; then
    `--fine-tune --init` continues that checkpoint on the same pair with the fine-tuning schedule."""
    root = _store(tmp_path / "data", experts=1, agents=1, failed=1)
    prepared = train_command.prepare_run(str(root), overrides=TINY)
    assert len(prepared.train_set) == 1 and prepared.run.train.batch_size == 1
    assert prepared.notes == ["batch size 16 lowered to 1: there is only 1 training pair"]
    base = tmp_path / "base"
    args = _args("--data", str(root), "--out", str(base), "--steps", "3", "--no-progress", "--set", *TINY)
    assert train_command.run(args) == 0
    assert "lowered to 1" in capsys.readouterr().err
    assert load_checkpoint(base / "last.pt")["step"] == 3

    tuned = tmp_path / "tuned"
    args = _args(
        "--data",
        str(root),
        "--out",
        str(tuned),
        "--init",
        str(base / "last.pt"),
        "--fine-tune",
        "--no-progress",
    )
    assert train_command.run(args) == 0
    ckpt = load_checkpoint(tuned / "last.pt")
    lo, _ = FINE_TUNE_STEPS
    assert ckpt["step"] == lo and ckpt["config"]["train"]["lr_max"] == FINE_TUNE_LR
    # the initial checkpoint's network, not the preset's
    assert tuple(ckpt["config"]["model"]["image_size"]) == (48, 64)
    start = load_checkpoint(base / "last.pt")["model"]
    assert any(not torch.equal(start[k], v) for k, v in ckpt["model"].items() if v.is_floating_point())


def test_fine_tuning_needs_a_policy_file(tmp_path, capsys):
    root = _store(tmp_path / "data", experts=1, agents=1)
    assert train_command.run(_args("--data", str(root), "--out", str(tmp_path / "r"), "--fine-tune")) == 2
    assert "name its checkpoint or policy file" in capsys.readouterr().err
    (tmp_path / "not-a-policy.pt").write_bytes(b"plain bytes")
    args = _args(
        "--data",
        str(root),
        "--out",
        str(tmp_path / "r"),
        "--fine-tune",
        "--init",
        str(tmp_path / "not-a-policy.pt"),
    )
    assert train_command.run(args) == 2
    assert "cannot fine-tune from" in capsys.readouterr().err
