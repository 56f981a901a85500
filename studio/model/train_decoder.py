"""Training of the latent image decoder with the main OSVI-WM model frozen.

Each step encodes every expert and agent frame of a batch of training pairs with the frozen model (no gradient),
pools them to keypoints, adds Gaussian noise (``noise_std``) and trains the decoder to reproduce the frames
(mean squared error in [0, 1] RGB). Only the main model's *training tasks* are used: the dataset's task list must
be a subset of the tasks stored in the model checkpoint, otherwise training refuses to start (the reference
trained its decoder on a test task). Validation, on held-out episodes of the same tasks, reports two errors:
``val_recon_mse`` (decoding the encodings of real frames) and ``val_pred_mse`` (decoding the world model's
predicted states against the real future agent frames) — the second is what the UI shows.

Run directory: ``decoder_config.json``, ``metrics.jsonl``, ``last.pt`` (resumable, same step seeding as the main
loop) and ``best.pt`` (lowest ``val_pred_mse``); ``load_decoder`` reads either. The step loop and its bookkeeping
are :class:`studio.model.training_loop.TrainingLoop`, shared with the main model's training.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.nn import functional as F

from studio.model.batching import Batch, BatchPlan, PairSource, collate_pairs, validation_batches
from studio.model.checkpoint import load_checkpoint, model_from_checkpoint
from studio.model.config import DecoderConfig
from studio.model.decoder import LatentDecoder
from studio.model.osvi_wm import OSVIWM
from studio.model.run_files import read_torch_file, write_json
from studio.model.training_loop import StepOutput, TrainingLoop, TrainResult, cosine_schedule, plan_batches

DECODER_FORMAT = "osvi-wm-decoder/1"


def load_decoder(path: str | Path, device: str | torch.device = "cpu") -> LatentDecoder:
    """A trained decoder in eval mode."""
    ckpt = read_torch_file(path)
    if not isinstance(ckpt, dict) or ckpt.get("format") != DECODER_FORMAT:
        raise ValueError(f"{path} is not a latent-decoder checkpoint (format {DECODER_FORMAT})")
    decoder = LatentDecoder(ckpt["in_dim"], tuple(ckpt["image_size"]), DecoderConfig(**ckpt["config"]))
    decoder.load_state_dict(ckpt["decoder"])
    return decoder.to(device).eval()


def _model_id(ckpt: dict[str, Any]) -> str:
    h = hashlib.sha1(repr((ckpt["config"], ckpt["dataset_fingerprint"], ckpt["step"])).encode())
    return h.hexdigest()[:16]


@torch.no_grad()
def _keypoints(model: OSVIWM, frames: torch.Tensor) -> torch.Tensor:
    return model.pool(model.encode(frames)).float()


@torch.no_grad()
def validate_decoder(
    decoder: LatentDecoder, model: OSVIWM, source: PairSource, cfg: DecoderConfig, device: torch.device
) -> dict[str, float]:
    m = model.cfg
    batches = validation_batches(
        source, cfg.batch_size, cfg.val_batches, m.image_size, m.n_expert_frames, m.n_agent_frames
    )
    decoder.eval()
    recon, pred = [], []
    try:
        for batch in batches:
            batch = batch.to(device)
            frames = batch.all_frames()
            recon.append(float(F.mse_loss(decoder(_keypoints(model, frames)), frames.float() / 255)))
            out = model(batch.expert_frames, batch.agent_frames, batch.expert_ids)
            future = batch.agent_frames[:, model.target_frame_indices()][:, : out.pooled.shape[1]]
            pred.append(float(F.mse_loss(decoder(out.pooled.float()), future.float() / 255)))
    finally:
        decoder.train()
    return {"val_recon_mse": float(np.mean(recon)), "val_pred_mse": float(np.mean(pred))}


def train_decoder(
    model_checkpoint: str | Path,
    train_set: PairSource,
    val_set: PairSource | None,
    out_dir: str | Path,
    cfg: DecoderConfig,
    *,
    device: str | torch.device = "cpu",
    progress: Callable[[dict[str, Any]], None] | None = None,
    cancel: Any = None,
    show_progress: bool = True,
    resume: bool = True,
) -> TrainResult:
    """Train a ``LatentDecoder`` for the frozen model in ``model_checkpoint`` (see the module docstring)."""
    device = torch.device(device)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    main_ckpt = load_checkpoint(model_checkpoint)
    unknown = sorted(set(train_set.tasks) - set(main_ckpt["tasks"]))
    if unknown:
        raise ValueError(
            f"the decoder trains on the model's training tasks only; this dataset has other tasks: {', '.join(unknown)}"
        )
    model = model_from_checkpoint(main_ckpt, device).eval()
    model.requires_grad_(False)
    torch.manual_seed(cfg.seed)
    decoder = LatentDecoder(model.pooled_dim, model.cfg.image_size, cfg).to(device)
    optimizer = torch.optim.AdamW(decoder.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay, fused=True)
    total = cfg.steps
    scheduler = cosine_schedule(optimizer, total)
    model_id = _model_id(main_ckpt)
    fingerprint = train_set.fingerprint()
    config = dataclasses.asdict(cfg)
    loop = TrainingLoop(
        out,
        total,
        cfg.seed,
        log_every=cfg.log_every,
        val_every=cfg.val_every,
        checkpoint_every=cfg.checkpoint_every,
        best_metric="val_pred_mse",
        best_key="best_val_pred_mse",
        loss_key="loss_mse",
        name="train-decoder",
    )

    def restore(ckpt: dict[str, Any]) -> None:
        if ckpt.get("model_id") != model_id or ckpt.get("dataset_fingerprint") != fingerprint:
            raise ValueError(
                f"{loop.last_path} belongs to another model or dataset; use another --out or --restart"
            )
        decoder.load_state_dict(ckpt["decoder"])
        optimizer.load_state_dict(ckpt["optimizer"])
        scheduler.load_state_dict(ckpt["scheduler"])

    if resume:
        loop.resume(lambda path: read_torch_file(path, device), restore)
    write_json(
        out / "decoder_config.json",
        {
            "config": config,
            "model_checkpoint": str(model_checkpoint),
            "model_id": model_id,
            "dataset_fingerprint": fingerprint,
        },
    )

    def state() -> dict[str, Any]:
        return {
            "format": DECODER_FORMAT,
            "config": config,
            "in_dim": model.pooled_dim,
            "image_size": list(model.cfg.image_size),
            "model_id": model_id,
            "dataset_fingerprint": fingerprint,
            "decoder": decoder.state_dict(),
            "optimizer": optimizer.state_dict(),
            "scheduler": scheduler.state_dict(),
        }

    def one_step(step: int, batch: Batch, seed: int) -> StepOutput:
        g = torch.Generator(device="cpu").manual_seed(seed)
        frames = batch.to(device).all_frames()
        keys = _keypoints(model, frames)
        noise = torch.randn(keys.shape, generator=g).to(device) * cfg.noise_std
        loss = F.mse_loss(decoder(keys + noise), frames.float() / 255)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        lr = optimizer.param_groups[0]["lr"]
        scheduler.step()
        return StepOutput({"loss_mse": float(loss.detach())}, lr)

    def validate_at(step: int) -> dict[str, float]:
        assert val_set is not None
        return validate_decoder(decoder, model, val_set, cfg, device)

    plan = BatchPlan(len(train_set), min(cfg.batch_size, len(train_set)), cfg.seed)
    collate = functools.partial(collate_pairs, image_size=model.cfg.image_size)
    decoder.train()
    return loop.run(
        plan_batches(train_set, plan, total, collate, cfg.num_workers),
        one_step,
        state,
        validate=validate_at if val_set is not None else None,
        progress=progress,
        cancel=cancel,
        show_progress=show_progress,
    )
