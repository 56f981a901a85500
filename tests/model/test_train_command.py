"""`studio train`: argument handling, overrides, and a run on a stand-in dataset."""

from __future__ import annotations

import argparse

import pytest
import torch
from synthetic_pairs import SyntheticPairs

from studio.cli import COMMANDS
from studio.model import train_command
from studio.model.checkpoint import load_checkpoint

torch.set_num_threads(1)
TINY = [
    "model.image_size=[48, 64]",
    "model.n_expert_frames=4",
    "model.n_agent_frames=3",
    "model.encoder_stages=2",
    "model.state_channels=16",
    "model.wm_width=32",
    "model.head_hidden=32",
    "train.batch_size=4",
    "train.num_workers=0",
    "train.val_every=2",
    "train.val_batches=1",
]


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    train_command.add_arguments(parser)
    return parser.parse_args(list(argv))


def test_registered_in_the_cli_table():
    assert COMMANDS["train"][0] == "studio.model.train_command"
    assert COMMANDS["train-decoder"][0] == "studio.model.decoder_command"


@pytest.mark.slow
def test_trains_and_resumes_through_the_command(tmp_path, monkeypatch, capsys):
    opened = []

    def fake_open(root, run, scene, progress=False):
        opened.append((root, tuple(run.model.image_size), run.model.n_expert_frames))
        return SyntheticPairs(), SyntheticPairs(split="val")

    monkeypatch.setattr(train_command, "open_splits", fake_open)
    args = _args(
        "--data",
        "store",
        "--out",
        str(tmp_path),
        "--steps",
        "2",
        "--seed",
        "3",
        "--no-progress",
        "--set",
        *TINY,
    )
    assert train_command.run(args) == 0
    assert opened == [("store", (48, 64), 4)]
    ckpt = load_checkpoint(tmp_path / "last.pt")
    assert ckpt["step"] == 2 and ckpt["config"]["train"]["seed"] == 3
    args = _args(
        "--data",
        "store",
        "--out",
        str(tmp_path),
        "--steps",
        "3",
        "--seed",
        "3",
        "--no-progress",
        "--set",
        *TINY,
    )
    assert train_command.run(args) == 0  # a longer run continues from step 2 on the lengthened schedule
    assert load_checkpoint(tmp_path / "last.pt")["step"] == 3
    capsys.readouterr()
    args = _args(
        "--data",
        "store",
        "--out",
        str(tmp_path),
        "--steps",
        "4",
        "--seed",
        "3",
        "--no-progress",
        "--set",
        *TINY,
        "train.lr_max=0.5",
    )
    assert train_command.run(args) == 2  # another optimiser setting: refused, not silently mixed
    assert "lr_max" in capsys.readouterr().err


def test_bad_override_is_a_clear_error(capsys):
    assert train_command.run(_args("--data", "x", "--out", "y", "--set", "model.nope=1")) == 2
    assert "unknown model field" in capsys.readouterr().err


def test_a_mistyped_override_exits_non_zero_with_one_line_through_the_cli(capsys):
    from studio.cli import main

    assert main(["train", "--data", "x", "--out", "y", "--set", "model.world_model=flase"]) == 2
    err = capsys.readouterr().err
    assert err == "studio train: model.world_model: expected bool (true/false/1/0), got 'flase'\n"


def test_missing_arguments_exit():
    with pytest.raises(SystemExit):
        _args("--out", "y")


@pytest.mark.slow
def test_trains_on_a_real_episode_store(tmp_path):
    """`--data` opens studio.data's PairDataset: a tiny store of synthetic recordings trains end to end."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "data"))
    from data_fixtures import make_recording

    from studio.data.store import EpisodeStore

    store = EpisodeStore(tmp_path / "store")
    seed = 0
    for task in ("pick_place/cube->red", "pick_place/cube->green"):
        for role, robot in (
            ("expert", "sawyer"),
            ("agent", "panda"),
            ("expert", "sawyer"),
            ("agent", "panda"),
            ("expert", "sawyer"),
            ("agent", "panda"),
        ):
            store.add_episode(make_recording(task=task, robot=robot, seed=seed), role=role, source="scripted")
            seed += 1
    args = _args(
        "--data",
        str(tmp_path / "store"),
        "--out",
        str(tmp_path / "run"),
        "--steps",
        "2",
        "--no-progress",
        "--set",
        *TINY,
    )
    assert train_command.run(args) == 0
    ckpt = load_checkpoint(tmp_path / "run" / "last.pt")
    assert ckpt["step"] == 2 and ckpt["tasks"][:2] == ["pick_place/cube->red", "pick_place/cube->green"]
    assert ckpt["dataset_fingerprint"]


def test_repeated_set_flags_all_apply():
    """`--set a=1 --set b=2` keeps both overrides (argparse's plain nargs would keep only the last flag's)."""
    args = _args(
        "--data", "x", "--out", "y", "--set", "train.val_every=7", "--set", "model.action_attention=cross"
    )
    assert args.set == ["train.val_every=7", "model.action_attention=cross"]


def test_open_splits_limits_the_expert_side_to_the_configured_embodiments(tmp_path):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "data"))
    from data_fixtures import make_recording

    from studio.data.store import EpisodeStore
    from studio.model.config import preset

    store = EpisodeStore(tmp_path)
    for i, (role, robot) in enumerate([("expert", "sawyer"), ("expert", "hand"), ("agent", "panda")] * 4):
        store.add_episode(make_recording(robot=robot, seed=i), role=role, source="scripted")
    run = preset("cpu").with_overrides(["model.image_size=[24, 32]", "train.expert_embodiments=human"])
    train_set, _ = train_command.open_splits(str(tmp_path), run, "pick_place")
    experts = {train_set.episodes[e].embodiment for e in train_set.pairs[:, 0]}
    assert experts == {"human"} and len(train_set) > 0
    everyone, _ = train_command.open_splits(
        str(tmp_path), preset("cpu").with_overrides(TINY[:1]), "pick_place"
    )
    assert {everyone.episodes[e].embodiment for e in everyone.pairs[:, 0]} == {"sawyer", "human"}
