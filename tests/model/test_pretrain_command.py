"""`studio pretrain-encoder`: which tasks' frames it reads, what it refuses, a run through the command."""

from __future__ import annotations

import argparse

import torch
from synthetic_pairs import SyntheticPairs

from studio.cli import COMMANDS
from studio.data.splits import load_split
from studio.model import pretrain_command

torch.set_num_threads(1)
TINY = [
    "model.image_size=[48, 64]",
    "model.n_expert_frames=4",
    "model.n_agent_frames=3",
    "model.state_channels=16",
]


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    pretrain_command.add_arguments(parser)
    return parser.parse_args(list(argv))


def test_registered_in_the_cli_table():
    assert COMMANDS["pretrain-encoder"][0] == "studio.model.pretrain_command"


def test_all_tasks_adds_the_held_out_tasks_and_train_keeps_them_out():
    split = load_split("metaworld")
    assert pretrain_command.pretraining_split("metaworld", "train").train == split.train
    every = pretrain_command.pretraining_split("metaworld", "all")
    assert set(every.train) == set(split.train) | set(split.test) and len(every.train) == 50
    assert every.test == ()


def test_training_fields_are_refused(tmp_path, capsys):
    code = pretrain_command.run(_args("--data", "x", "--out", str(tmp_path), "--set", "train.lr_max=1"))
    assert code == 2
    assert "only model fields" in capsys.readouterr().err


def test_pretrains_through_the_command(tmp_path, monkeypatch, capsys):
    opened = []

    def fake_open(root, run_cfg, spec, seed, progress=False):
        opened.append((root, tuple(run_cfg.model.image_size), spec.scene, len(spec.train)))
        return SyntheticPairs(), SyntheticPairs(split="val")

    monkeypatch.setattr(pretrain_command, "open_frames", fake_open)
    args = _args(
        "--data",
        "store",
        "--out",
        str(tmp_path),
        "--scene",
        "metaworld",
        "--tasks",
        "all",
        "--steps",
        "2",
        "--batch-size",
        "2",
        "--no-progress",
        "--set",
        *TINY,
    )
    assert pretrain_command.run(args) == 0
    assert opened == [("store", (48, 64), "metaworld", 50)]
    assert "finished at step 2/2" in capsys.readouterr().out
    assert (tmp_path / "best.pt").is_file() and (tmp_path / "pretrain_config.json").is_file()
