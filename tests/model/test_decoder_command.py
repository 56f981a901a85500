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


def test_the_scene_defaults_to_the_one_the_model_was_trained_on(tmp_path, monkeypatch):
    """A model trained on another scene than pick-and-place (here the synthetic one; push in practice) trains its
    decoder without --scene: the tasks come from the model's own scene. Defaulting to pick_place failed with
    "this dataset has other tasks"."""
    train(
        tiny_run_config(max_steps=1, batch_size=4, val_every=100),
        SyntheticPairs(),
        None,
        tmp_path / "run",
        show_progress=False,
    )
    asked: list[str] = []

    def open_splits(root, run, scene):
        asked.append(scene)
        if scene != "synthetic":  # what the store holds for another scene: tasks the model never saw
            other = SyntheticPairs()
            other.tasks = [f"{scene}/cube->red"]
            return other, SyntheticPairs(split="val")
        return SyntheticPairs(), SyntheticPairs(split="val")

    monkeypatch.setattr(train_command, "open_splits", open_splits)
    parser = argparse.ArgumentParser()
    decoder_command.add_arguments(parser)
    common = [
        "--model",
        str(tmp_path / "run" / "last.pt"),
        "--data",
        "store",
        "--steps",
        "1",
        "--batch-size",
        "2",
        "--no-progress",
    ]
    assert decoder_command.run(parser.parse_args([*common, "--out", str(tmp_path / "dec")])) == 0
    assert asked == ["synthetic"]
    assert (tmp_path / "dec" / "last.pt").is_file()
    # An explicit --scene still wins, and the model's tasks still guard it.
    explicit = parser.parse_args([*common, "--out", str(tmp_path / "d2"), "--scene", "pick_place"])
    assert decoder_command.run(explicit) == 2
    assert asked == ["synthetic", "pick_place"]


def test_missing_model_checkpoint_is_a_clear_error(tmp_path, capsys):
    parser = argparse.ArgumentParser()
    decoder_command.add_arguments(parser)
    args = parser.parse_args(
        ["--model", str(tmp_path / "nope.pt"), "--data", "x", "--out", str(tmp_path / "d")]
    )
    assert decoder_command.run(args) == 2
    assert "nope.pt" in capsys.readouterr().err
