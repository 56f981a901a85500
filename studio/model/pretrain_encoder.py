"""Self-supervised pretraining of the image encoder: a deep spatial autoencoder on a scene's frames.

The paper starts its ResNet-18 from ImageNet weights. Nothing is downloaded in the default path here, so this
stage offers an in-domain start instead, learnt from the frames alone (no waypoints, no actions). The encoder
of the run's own architecture (``model.image_size``, ``model.encoder_stages``, ``model.state_channels``) maps a
frame to C maps; the same spatial-softmax pooling the waypoint head reads turns them into C keypoints; a
:class:`~studio.model.decoder.LatentDecoder` must redraw the frame from those 2C numbers alone (mean squared
error on RGB in [0, 1] at half the frame's size, Gaussian noise of ``noise_std`` on the keypoints; the half-size
target keeps the decoder cheap — the encoder's backward pass is most of a step). With 128 numbers for a frame
the keypoints have to follow what changes between frames (Finn et al. 2016, "Deep spatial autoencoders for
visuomotor learning"). Measured on Meta-World they mostly follow the arm, and a run started from them generalised
worse than one started from random weights (docs/experiments.md), so no recipe there uses this stage.

Frames are the expert and agent frames of pairs from the chosen tasks' stored episodes (``tasks="train"``: the
split's training tasks; ``"all"``: every task of the scene, held-out ones included — their frames only, which
is transductive and said so in every run's config). Validation reconstructs held-out episodes of the same tasks.

Run directory: ``pretrain_config.json``, ``metrics.jsonl``, ``last.pt`` (resumable with the main loop's step
seeding) and ``best.pt`` (lowest ``val_recon_mse``), both in :data:`ENCODER_FORMAT`: the encoder's weights and
the model configuration they fit. ``studio train --init DIR/best.pt`` starts a run's encoder from them; every
other module starts untrained (:func:`load_pretrained_encoder`).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.nn import functional as F

from studio.model.batching import Batch, BatchPlan, PairSource, collate_pairs, validation_batches
from studio.model.config import DecoderConfig, ModelConfig, RunConfig
from studio.model.decoder import LatentDecoder
from studio.model.osvi_wm import OSVIWM
from studio.model.run_files import read_torch_file, write_json
from studio.model.training_loop import StepOutput, TrainingLoop, TrainResult, cosine_schedule, plan_batches

ENCODER_FORMAT = "osvi-wm-encoder/1"
#: The decoder redraws frames at 1/RECON_DOWNSCALE of the model's input size.
RECON_DOWNSCALE = 2
#: The decoder and schedule of a pretraining run unless told otherwise (a smaller decoder than the UI's).
PRETRAIN_DEFAULTS = DecoderConfig(base_channels=128, stages=3, steps=1000, val_every=250, val_batches=10)
#: The model fields an encoder's weights depend on; ``--init`` from a pretrained encoder needs them equal.
ENCODER_FIELDS = ("image_size", "encoder_stages", "state_channels", "pool_before_wm")


def is_pretrained_encoder(ckpt: Any) -> bool:
    return isinstance(ckpt, dict) and ckpt.get("format") == ENCODER_FORMAT


def load_pretrained_encoder(model: OSVIWM, ckpt: dict[str, Any], source: str | Path) -> None:
    """Copy a pretrained encoder into ``model`` after checking that its architecture fits."""
    saved = ckpt["model_config"]
    current = dataclasses.asdict(model.cfg)
    diffs = [
        f"{k}: {saved.get(k)!r} vs {current[k]!r}"
        for k in ENCODER_FIELDS
        if _as_lists(saved.get(k)) != _as_lists(current[k])
    ]
    if diffs:
        raise ValueError(f"{source} is an encoder for another model ({'; '.join(diffs)})")
    model.encoder.load_state_dict({k: v.float() for k, v in ckpt["encoder"].items()})


def _as_lists(v: Any) -> Any:
    return [_as_lists(x) for x in v] if isinstance(v, (list, tuple)) else v


class SpatialAutoencoder(torch.nn.Module):
    """Encoder → spatial-softmax keypoints → decoder: (N, 3, H, W) frames → (N, 3, H, W) in [0, 1]."""

    def __init__(self, model_cfg: ModelConfig, cfg: DecoderConfig) -> None:
        super().__init__()
        core = OSVIWM(model_cfg)  # the run's own encoder and pooling, built the way training builds them
        self.encoder = core.encoder
        self.spatial_pool = core.spatial_pool
        h, w = model_cfg.image_size
        self.target_size = (max(h // RECON_DOWNSCALE, 1), max(w // RECON_DOWNSCALE, 1))
        self.decoder = LatentDecoder(core.pooled_dim, self.target_size, cfg)

    def target(self, frames: torch.Tensor) -> torch.Tensor:
        """The frames the decoder should draw: [0, 1] RGB averaged down to ``target_size``."""
        x = frames.float() / 255 if frames.dtype == torch.uint8 else frames.float()
        return F.interpolate(x, size=self.target_size, mode="area")

    def keypoints(self, frames: torch.Tensor) -> torch.Tensor:
        return self.spatial_pool(self.encoder(frames)).float()

    def forward(self, frames: torch.Tensor, noise: torch.Tensor | None = None) -> torch.Tensor:
        keys = self.keypoints(frames)
        return self.decoder(keys if noise is None else keys + noise)


@torch.no_grad()
def validate_autoencoder(
    net: SpatialAutoencoder,
    source: PairSource,
    model_cfg: ModelConfig,
    cfg: DecoderConfig,
    device: torch.device,
) -> dict[str, float]:
    batches = validation_batches(
        source,
        cfg.batch_size,
        cfg.val_batches,
        model_cfg.image_size,
        model_cfg.n_expert_frames,
        model_cfg.n_agent_frames,
    )
    net.eval()
    recon = []
    try:
        for batch in batches:
            frames = batch.to(device).all_frames()
            recon.append(float(F.mse_loss(net(frames), net.target(frames))))
    finally:
        net.train()
    return {"val_recon_mse": float(np.mean(recon))}


def pretrain_encoder(
    run: RunConfig,
    train_set: PairSource,
    val_set: PairSource | None,
    out_dir: str | Path,
    cfg: DecoderConfig,
    *,
    tasks: str = "train",
    device: str | torch.device = "cpu",
    progress: Callable[[dict[str, Any]], None] | None = None,
    cancel: Any = None,
    show_progress: bool = True,
    resume: bool = True,
) -> TrainResult:
    """Pretrain the encoder of ``run.model`` as a spatial autoencoder (see the module docstring)."""
    if run.model.pool_before_wm:
        raise ValueError("encoder pretraining reads the encoder's maps; model.pool_before_wm must be false")
    device = torch.device(device)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    net = SpatialAutoencoder(run.model, cfg).to(device)
    optimizer = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay, fused=True)
    total = cfg.steps
    scheduler = cosine_schedule(optimizer, total, warmup=max(1, total // 20))
    fingerprint = train_set.fingerprint()
    model_config = dataclasses.asdict(run.model)
    config = {
        "pretrain": dataclasses.asdict(cfg),
        "model": model_config,
        "tasks": tasks,
        "task_names": list(train_set.tasks),
        "dataset_fingerprint": fingerprint,
    }
    loop = TrainingLoop(
        out,
        total,
        cfg.seed,
        log_every=cfg.log_every,
        val_every=cfg.val_every,
        checkpoint_every=cfg.checkpoint_every,
        best_metric="val_recon_mse",
        best_key="best_val_recon_mse",
        loss_key="loss_mse",
        name="pretrain-encoder",
    )

    def without_steps(c: dict[str, Any]) -> dict[str, Any]:
        return {**c, "pretrain": {**c.get("pretrain", {}), "steps": None}}

    def same_run(saved: Any) -> bool:
        """Whether ``saved`` is this run's configuration, up to its length (--steps may change on resume)."""
        return isinstance(saved, dict) and without_steps(saved) == without_steps(config)

    def restore(ckpt: dict[str, Any]) -> None:
        if not is_pretrained_encoder(ckpt) or not same_run(ckpt.get("config")):
            raise ValueError(
                f"{loop.last_path} belongs to another configuration or dataset; use another --out or --restart"
            )
        net.encoder.load_state_dict(ckpt["encoder"])
        net.decoder.load_state_dict(ckpt["decoder"])
        optimizer.load_state_dict(ckpt["optimizer"])
        scheduler.load_state_dict(ckpt["scheduler"])

    if resume:
        loop.resume(lambda path: read_torch_file(path, device), restore)
    write_json(out / "pretrain_config.json", config)

    def state() -> dict[str, Any]:
        return {
            "format": ENCODER_FORMAT,
            "config": config,
            "model_config": model_config,
            "encoder": net.encoder.state_dict(),
            "decoder": net.decoder.state_dict(),
            "optimizer": optimizer.state_dict(),
            "scheduler": scheduler.state_dict(),
        }

    def one_step(step: int, batch: Batch, seed: int) -> StepOutput:
        g = torch.Generator(device="cpu").manual_seed(seed)
        frames = batch.to(device).all_frames()
        keys = net.keypoints(frames)
        noise = torch.randn(keys.shape, generator=g).to(device) * cfg.noise_std
        loss = F.mse_loss(net.decoder(keys + noise), net.target(frames))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        lr = optimizer.param_groups[0]["lr"]
        scheduler.step()
        return StepOutput({"loss_mse": float(loss.detach())}, lr)

    def validate_at(step: int) -> dict[str, float]:
        assert val_set is not None
        return validate_autoencoder(net, val_set, run.model, cfg, device)

    plan = BatchPlan(len(train_set), min(cfg.batch_size, len(train_set)), cfg.seed)
    collate = functools.partial(
        collate_pairs,
        image_size=run.model.image_size,
        n_expert=run.model.n_expert_frames,
        n_agent=run.model.n_agent_frames,
    )
    net.train()
    return loop.run(
        plan_batches(train_set, plan, total, collate, cfg.num_workers),
        one_step,
        state,
        validate=validate_at if val_set is not None else None,
        progress=progress,
        cancel=cancel,
        show_progress=show_progress,
    )
