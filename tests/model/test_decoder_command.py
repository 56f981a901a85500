"""`studio train-decoder` on a stand-in dataset."""

from __future__ import annotations

import argparse

import torch
from synthetic_pairs import SyntheticPairs, tiny_run_config

from studio.model import decoder_command, train_command
from studio.model.train import train
from studio.model.train_decoder import load_decoder

torch.set_num_threads(1)


def test_trains_a_decoder_for_a_checkpoint(tmp_path, monkeypatch):
    train(
        tiny_run_config(max_steps=1, batch_size=4, val_every=100),
        SyntheticPairs(),
        None,
        tmp_path / "run",
        show_progress=False,
    )
    monkeypatch.setattr(
        train_command, "open_splits", lambda root, run, scene: (SyntheticPairs(), SyntheticPairs(split="val"))
    )
    parser = argparse.ArgumentParser()
    decoder_command.add_arguments(parser)
    args = parser.parse_args(
        [
            "--model",
            str(tmp_path / "run" / "last.pt"),
            "--data",
            "store",
            "--out",
            str(tmp_path / "dec"),
            "--steps",
            "2",
            "--batch-size",
            "2",
            "--no-progress",
        ]
    )
    assert decoder_command.run(args) == 0
    assert load_decoder(tmp_path / "dec" / "last.pt").image_size == (48, 64)


def test_missing_model_checkpoint_is_a_clear_error(tmp_path, capsys):
    parser = argparse.ArgumentParser()
    decoder_command.add_arguments(parser)
    args = parser.parse_args(
        ["--model", str(tmp_path / "nope.pt"), "--data", "x", "--out", str(tmp_path / "d")]
    )
    assert decoder_command.run(args) == 2
    assert "nope.pt" in capsys.readouterr().err
