"""Decoder training with the main model frozen: learns, stays on training tasks, loads back."""

from __future__ import annotations

import json

import pytest
import torch
from synthetic_pairs import SyntheticPairs, tiny_run_config

from studio.model.checkpoint import load_checkpoint
from studio.model.config import DecoderConfig
from studio.model.train import train
from studio.model.train_decoder import load_decoder, train_decoder

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def model_ckpt(tmp_path_factory):
    out = tmp_path_factory.mktemp("main")
    train(
        tiny_run_config(max_steps=2, batch_size=4, val_every=100),
        SyntheticPairs(),
        None,
        out,
        show_progress=False,
    )
    return out / "last.pt"


@pytest.mark.slow
def test_decoder_learns_with_the_model_frozen(model_ckpt, tmp_path):
    before = {k: v.clone() for k, v in load_checkpoint(model_ckpt)["model"].items()}
    cfg = DecoderConfig(
        base_channels=32,
        stages=3,
        batch_size=4,
        steps=25,
        lr=3e-3,
        val_every=25,
        val_batches=2,
        log_every=1,
        num_workers=0,
    )
    result = train_decoder(
        model_ckpt, SyntheticPairs(), SyntheticPairs(split="val"), tmp_path, cfg, show_progress=False
    )
    assert result.status == "finished" and result.step == 25
    recs = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    losses = [r["loss_mse"] for r in recs if "loss_mse" in r]
    assert sum(losses[-5:]) < 0.5 * sum(losses[:5])
    val = [r for r in recs if r.get("split") == "val"][-1]
    assert val["val_recon_mse"] > 0 and val["val_pred_mse"] > 0
    assert all(torch.equal(before[k], v) for k, v in load_checkpoint(model_ckpt)["model"].items())
    decoder = load_decoder(tmp_path / "best.pt")
    assert decoder.render(torch.zeros(2, 32)).shape == (2, 48, 64, 3)


def test_decoder_refuses_tasks_the_model_was_not_trained_on(model_ckpt, tmp_path):
    more_tasks = SyntheticPairs(n_tasks=4)
    more_tasks.tasks = [*more_tasks.tasks[:3], "synthetic/held-out-task"]
    with pytest.raises(ValueError, match="training tasks only"):
        train_decoder(model_ckpt, more_tasks, None, tmp_path, DecoderConfig(steps=1), show_progress=False)
