"""Encoder pretraining as a spatial autoencoder: learns, resumes, and starts a training run's encoder."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch
from synthetic_pairs import SyntheticPairs, tiny_run_config

from studio.model.checkpoint import load_checkpoint
from studio.model.config import DecoderConfig
from studio.model.osvi_wm import OSVIWM
from studio.model.pretrain_encoder import ENCODER_FORMAT, SpatialAutoencoder, pretrain_encoder
from studio.model.train import CheckpointMismatch, _load_init, train

torch.set_num_threads(1)
CFG = DecoderConfig(
    base_channels=32,
    stages=2,
    batch_size=4,
    steps=30,
    lr=3e-3,
    val_every=30,
    val_batches=2,
    checkpoint_every=10,
    log_every=1,
    num_workers=0,
)


def _records(run_dir):
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def pretrained(tmp_path_factory):
    out = tmp_path_factory.mktemp("pretrain")
    result = pretrain_encoder(
        tiny_run_config(), SyntheticPairs(), SyntheticPairs(split="val"), out, CFG, show_progress=False
    )
    return out, result


@pytest.mark.slow
def test_the_autoencoder_learns_to_redraw_the_frames_from_keypoints(pretrained):
    out, result = pretrained
    assert result.status == "finished" and result.step == CFG.steps
    losses = [r["loss_mse"] for r in _records(out) if "loss_mse" in r]
    assert sum(losses[-5:]) < 0.5 * sum(losses[:5])
    val = [r for r in _records(out) if r.get("split") == "val"]
    assert val and val[-1]["val_recon_mse"] < 0.5 * losses[0]
    ckpt = torch.load(out / "best.pt", weights_only=False)
    assert ckpt["format"] == ENCODER_FORMAT and ckpt["config"]["tasks"] == "train"
    assert ckpt["config"]["task_names"] == list(SyntheticPairs().tasks)


def test_the_decoder_draws_half_size_frames_from_the_keypoints_only():
    net = SpatialAutoencoder(tiny_run_config().model, CFG)
    frames = torch.randint(0, 256, (2, 3, 48, 64), dtype=torch.uint8)
    assert net(frames).shape == (2, 3, 24, 32) == net.target(frames).shape
    assert net.keypoints(frames).shape == (2, 2 * tiny_run_config().model.state_channels)


def test_init_from_a_pretrained_encoder_sets_the_encoder_and_nothing_else(pretrained):
    out, _ = pretrained
    run = tiny_run_config()
    torch.manual_seed(5)
    model = OSVIWM(run.model)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    _load_init(model, run, out / "best.pt", torch.device("cpu"))
    saved = torch.load(out / "best.pt", weights_only=False)["encoder"]
    after = model.state_dict()
    assert all(torch.equal(after[f"encoder.{k}"], v) for k, v in saved.items())
    changed = {k for k in after if not torch.equal(after[k], before[k])}
    assert changed and all(k.startswith("encoder.") for k in changed)


def test_a_pretrained_encoder_for_another_input_size_is_refused(pretrained):
    out, _ = pretrained
    run = tiny_run_config()
    run = dataclasses.replace(run, model=dataclasses.replace(run.model, image_size=(64, 64)))
    with pytest.raises(CheckpointMismatch, match="image_size"):
        _load_init(OSVIWM(run.model), run, out / "best.pt", torch.device("cpu"))


@pytest.mark.slow
def test_studio_train_starts_from_the_pretrained_encoder(pretrained, tmp_path):
    out, _ = pretrained
    run = tiny_run_config(max_steps=1, batch_size=4, val_every=100, lr_max=1e-9)
    train(run, SyntheticPairs(), None, tmp_path, show_progress=False, init=out / "best.pt")
    saved = torch.load(out / "best.pt", weights_only=False)["encoder"]
    trained = load_checkpoint(tmp_path / "last.pt")["model"]
    weight = "trunk.0.weight"  # the stem convolution: moved by at most one step at lr 1e-9
    assert torch.allclose(trained[f"encoder.{weight}"], saved[weight], atol=1e-6)


def test_an_interrupted_pretraining_resumes_where_it_stopped(tmp_path):
    short = dataclasses.replace(CFG, steps=4, checkpoint_every=2, val_every=100)
    pretrain_encoder(tiny_run_config(), SyntheticPairs(), None, tmp_path, short, show_progress=False)
    longer = dataclasses.replace(short, steps=6)
    result = pretrain_encoder(
        tiny_run_config(), SyntheticPairs(), None, tmp_path, longer, show_progress=False
    )
    assert result.step == 6
    steps = [r["step"] for r in _records(tmp_path) if "loss_mse" in r]
    assert steps == [1, 2, 3, 4, 5, 6]
    other = dataclasses.replace(longer, lr=1e-2)
    with pytest.raises(ValueError, match="another configuration or dataset"):
        pretrain_encoder(tiny_run_config(), SyntheticPairs(), None, tmp_path, other, show_progress=False)


def test_init_from_a_file_that_is_neither_checkpoint_nor_encoder_is_refused(tmp_path):
    run = tiny_run_config()
    bogus = tmp_path / "bogus.pt"
    torch.save({"format": "something-else/1", "weights": torch.zeros(2)}, bogus)
    with pytest.raises(ValueError, match="nor a pretrained encoder"):
        _load_init(OSVIWM(run.model), run, bogus, torch.device("cpu"))
