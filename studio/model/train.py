"""The OSVI-WM training loop: one function, ``train``, used by `studio train`, the job worker and the tests.

Per optimiser step: a deterministic batch of pairs (``BatchPlan``) → augmentation and mixup on the model side
(``augment``) → forward with world-model targets → 𝓛 = 𝓛_sdtw + α(τ)·𝓛_wm → backward, gradient-norm clipping,
AdamW, one-cycle learning rate (2e-4 → 2e-7). Every random choice of step τ derives from (seed, τ, rank), so a
run killed at any point and resumed from its last checkpoint continues exactly where it stopped.

Outputs in the run directory:

* ``config.json`` — the full ``RunConfig``, the dataset fingerprint and its task list;
* ``last.pt`` — the latest checkpoint (model, optimiser, scheduler, step, config, dataset fingerprint), written
  atomically every ``checkpoint_every`` steps, on cancellation and at the end; ``best.pt`` — the checkpoint with the
  lowest validation waypoint loss;
* ``metrics.jsonl`` — one JSON object per line: training records (step, epoch, loss, loss_sdtw, loss_wm, alpha,
  lr, grad_norm, samples_per_s), validation records (``"split": "val"``) and events (start, resume, end).

Validation runs on *held-out episodes of the training tasks* (the dataset's validation split), without augmentation
or mixup, in eval mode — never on test tasks, unlike the reference code's model selection.

Long-running use: ``progress`` is called after every step with a dict (step, total_steps, epoch, loss, lr,
samples_per_s, eta_s); ``cancel`` (a callable returning bool, or anything with ``is_set()``) is polled every
step and stops the run after a checkpoint. A tqdm bar is shown on the terminal unless disabled.

The step loop itself — resume, step seeds, metrics, validation cadence, ``best.pt`` / ``last.pt``,
cancellation, progress — is :class:`studio.model.training_loop.TrainingLoop`, shared with the decoder's
training; this module gives it the OSVI-WM step, validation and checkpoint contents.

Distributed data parallel: started under ``torchrun`` (``WORLD_SIZE`` > 1 in the environment) the loop joins a
process group (gloo on CPU, NCCL on CUDA), each rank takes a contiguous slice of every global batch, DDP averages
the gradients, and rank 0 alone writes files and validates.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist

from studio.model.augment import augment_batch
from studio.model.batching import Batch, BatchPlan, PairSource, collate_pairs, expert_indices_of
from studio.model.checkpoint import CHECKPOINT_FORMAT, load_checkpoint
from studio.model.config import PLANNING_FIELDS, ModelConfig, RunConfig, TrainConfig, steps_for
from studio.model.demo_task import demo_task_loss, label_table
from studio.model.guidance import drop_demonstrations
from studio.model.losses import alpha as alpha_at
from studio.model.losses import endpoint_loss, waypoint_errors, waypoint_loss, world_model_loss
from studio.model.osvi_wm import OSVIWM
from studio.model.pretrain_encoder import is_pretrained_encoder, load_pretrained_encoder
from studio.model.reversal import reverse_pairs
from studio.model.run_files import read_torch_file, write_json
from studio.model.training_loop import StepOutput, TrainingLoop, TrainResult, plan_batches

# TrainConfig fields that may change when a run is resumed: bookkeeping, which does not change what is computed,
# and ``max_steps`` — another --steps lengthens or shortens the run, its learning-rate schedule recomputed for the
# new length from the step reached.
_RESUMABLE_CHANGES = {"val_every", "val_batches", "checkpoint_every", "log_every", "num_workers", "max_steps"}


class CheckpointMismatch(RuntimeError):
    """The run directory holds a checkpoint of a different configuration or dataset."""


# ---------------------------------------------------------------------------------------------- helpers
def learning_rate_factor(step: int, total: int, warmup: float, lr_max: float, lr_final: float) -> float:
    """One-cycle schedule as a multiple of lr_max: optional linear warm-up from 1/25, then cosine to lr_final."""
    warm = round(warmup * total)
    if step < warm:
        return 1 / 25 + (1 - 1 / 25) * step / max(warm, 1)
    progress = min((step - warm) / max(total - warm - 1, 1), 1.0)
    final = lr_final / lr_max
    return final + (1 - final) * 0.5 * (1 + math.cos(math.pi * progress))


def _dist_info() -> tuple[int, int]:
    if dist.is_available() and dist.is_initialized():
        return dist.get_world_size(), dist.get_rank()
    return int(os.environ.get("WORLD_SIZE", "1")), int(os.environ.get("RANK", "0"))


def _config_differences(saved: dict[str, Any], current: dict[str, Any]) -> list[str]:
    """Settings that differ; a setting a checkpoint predates counts as its default (what it trained with)."""
    diffs = []
    defaults = {"model": asdict(ModelConfig()), "train": asdict(TrainConfig())}
    for section in ("model", "train"):
        for key in sorted(set(saved.get(section, {})) | set(current[section])):
            a = saved.get(section, {}).get(key, defaults[section].get(key))
            b = current[section].get(key)
            a, b = _as_lists(a), _as_lists(b)  # JSON gives lists where the dataclass holds tuples
            if a != b and not (section == "train" and key in _RESUMABLE_CHANGES):
                diffs.append(f"{section}.{key}: checkpoint {a!r} vs now {b!r}")
    return diffs


def _as_lists(value: Any) -> Any:
    return [_as_lists(v) for v in value] if isinstance(value, list | tuple) else value


def median_path_depth(source: PairSource, samples: int = 64) -> float:
    """Median camera depth of the ground-truth paths of up to ``samples`` evenly spread pairs."""
    idx = np.unique(np.linspace(0, len(source) - 1, min(samples, len(source))).round().astype(int))
    depths = np.concatenate([np.asarray(source[int(i)]["path"])[:, 2] for i in idx])
    return float(np.median(depths))


# ---------------------------------------------------------------------------------------------- one step
def compute_losses(
    model: torch.nn.Module,
    core: OSVIWM,
    batch: Batch,
    run: RunConfig,
    step: int,
    total: int,
    generator: torch.Generator | None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Forward one batch and return the total loss and its parts; augmented when ``generator`` is given and
    ``step`` is past the clean warm-up (``TrainConfig.aug_warmup``)."""
    cfg = run.train
    if generator is not None and step >= cfg.aug_warmup * total:
        if cfg.reverse > 0:
            batch, _ = reverse_pairs(batch, cfg.reverse, generator)
        with torch.no_grad():
            aug = augment_batch(
                batch.expert_frames,
                batch.agent_frames,
                batch.K,
                batch.expert_ids,
                batch.expert_tasks,
                batch.agent_tasks,
                cfg,
                generator,
            )
        expert, agent, K = aug.expert_frames, aug.agent_frames, aug.K
        if cfg.demo_dropout > 0:
            expert, _ = drop_demonstrations(expert, cfg.demo_dropout, generator)
    else:
        expert, agent, K = batch.expert_frames, batch.agent_frames, batch.K
    a = alpha_at(step, total, cfg)
    use_wm = cfg.wm_loss and core.world_model is not None and a > 0.0
    mode = ("detached" if cfg.stop_gradient else "grad") if use_wm else "none"
    dtype = torch.bfloat16 if cfg.precision == "bf16" else None
    with torch.autocast(device_type=agent.device.type, dtype=dtype, enabled=dtype is not None):
        out = model(expert, agent, batch.expert_ids, targets=mode)
    decoded = core.decode_waypoints(out.waypoints.float(), K)
    loss_sdtw, per_set = waypoint_loss(
        decoded["position"], decoded["gripper"], batch.path, cfg, core.cfg.max_waypoints
    )
    loss = loss_sdtw
    parts = {"loss_sdtw": float(loss_sdtw.detach()), "alpha": a}
    if cfg.endpoint_weight > 0:
        loss_end = endpoint_loss(decoded["position"], batch.path, core.cfg.max_waypoints)
        loss = loss + cfg.endpoint_weight * loss_end
        parts["loss_endpoint"] = float(loss_end.detach())
    if out.demo_task_logits is not None and cfg.demo_task_weight > 0:
        loss_task, right = demo_task_loss(
            out.demo_task_logits, batch.expert_tasks, core.cfg.demo_task_groups, core.cfg.demo_task_table
        )
        loss = loss + cfg.demo_task_weight * loss_task
        parts["loss_task"] = float(loss_task.detach())
        parts["task_acc"] = float(right.float().mean())
    if out.target_pooled is not None:
        loss_wm = world_model_loss(out.pooled, out.target_pooled)
        loss = loss + a * loss_wm
        parts["loss_wm"] = float(loss_wm.detach())
    parts["loss"] = float(loss.detach())
    for n, v in enumerate(per_set.tolist(), start=1):
        parts[f"loss_set{n}"] = v
    errors = waypoint_errors(decoded["position"].detach(), batch.path, core.cfg.max_waypoints)
    parts["final_err_m"] = float(errors["final"].mean())
    parts["path_err_m"] = float(errors["path"].mean())
    return loss, parts


@torch.no_grad()
def demonstration_effect(core: OSVIWM, batch: Batch, other: Batch) -> tuple[float, int]:
    """How far the predicted waypoints move when each pair's demonstration is swapped for another task's.

    Every pair of ``batch`` is planned twice: with its own demonstration and with one of ``other``'s whose task
    differs. Returns the mean displacement of the n-waypoint set (metres, over the pairs that had a
    different-task demonstration to swap in) and that number of pairs. A model that imitates needs this to be
    about as large as the distance between the tasks' paths; near 0 means the plan ignores the demonstration
    (the failure that a validation error stuck at the mean path hides). Eval mode, no augmentation.
    """
    b = batch.agent_frames.shape[0]
    ids = torch.arange(b, device=batch.agent_frames.device) % other.expert_frames.shape[0]
    keep = other.expert_tasks.to(ids.device)[ids] != batch.agent_tasks.to(ids.device)
    if not bool(keep.any()):
        return 0.0, 0
    n = core.cfg.max_waypoints
    own = core(batch.expert_frames, batch.agent_frames, batch.expert_ids).waypoints
    swapped = core(other.expert_frames, batch.agent_frames, ids).waypoints
    p_own = core.decode_waypoints(own.float(), batch.K)["position"][:, -n:]
    p_swapped = core.decode_waypoints(swapped.float(), batch.K)["position"][:, -n:]
    moved = (p_own - p_swapped).norm(dim=-1).mean(dim=-1)[keep]
    return float(moved.mean()), int(keep.sum())


@torch.no_grad()
def validate(
    core: OSVIWM, source: PairSource, run: RunConfig, step: int, total: int, device: torch.device
) -> dict:
    """Mean losses and errors over ``val_batches`` evenly spread batches of ``source`` (eval mode, no augment),
    plus ``demo_effect_m`` (``demonstration_effect`` against the batch half the set away)."""
    cfg = run.train
    bs = min(cfg.batch_size, len(source))
    n_batches = len(source) // bs
    if cfg.val_batches > 0:
        n_batches = min(n_batches, cfg.val_batches)
    starts = np.linspace(0, len(source) - bs, n_batches).round().astype(int)
    was_training = core.training
    core.eval()
    totals: dict[str, float] = {}
    effect_sum, effect_pairs = 0.0, 0

    def batch_at(first: int) -> Batch:
        samples = [source[int(i) % len(source)] for i in range(first, first + bs)]
        return collate_pairs(
            samples, core.cfg.image_size, core.cfg.n_expert_frames, core.cfg.n_agent_frames
        ).to(device)

    try:
        for s in starts:
            batch = batch_at(int(s))
            _, parts = compute_losses(core, core, batch, run, step, total, None)
            for k, v in parts.items():
                totals[k] = totals.get(k, 0.0) + v / len(starts)
            effect, pairs = demonstration_effect(core, batch, batch_at(int(s) + len(source) // 2))
            effect_sum, effect_pairs = effect_sum + effect * pairs, effect_pairs + pairs
    finally:
        core.train(was_training)
    out = {f"val_{k}" if k != "alpha" else k: v for k, v in totals.items()}
    if effect_pairs:
        out["val_demo_effect_m"] = effect_sum / effect_pairs
    return out


# ---------------------------------------------------------------------------------------------- training
def train(
    run: RunConfig,
    train_set: PairSource,
    val_set: PairSource | None,
    out_dir: str | Path,
    *,
    device: str | torch.device = "cpu",
    progress: Callable[[dict[str, Any]], None] | None = None,
    cancel: Any = None,
    show_progress: bool = True,
    resume: bool = True,
    init: str | Path | None = None,
) -> TrainResult:
    """Train (or resume training of) OSVI-WM on ``train_set``; see the module docstring for the outputs.

    ``init`` starts a new run from the weights of another checkpoint or policy file with the same model
    configuration (fine-tuning on new data, or a curriculum over task sets), with a fresh optimiser and schedule;
    it is ignored when the run resumes from its own ``last.pt``. Two differences are allowed: a demonstration-task
    head that is new or names other labels, and a world model the checkpoint does not have (``init`` from the
    no-world-model ablation): either starts untrained. A pretrained encoder (``studio pretrain-encoder``) starts
    the encoder only. A policy file's guided branch (``studio export-policy --guided-from``) is not carried: the
    run starts from the policy's own weights, and its gate then compares the run's own gains.

    Under ``torchrun`` the process group is joined here unless the caller already did; a group joined here is
    also left here, after a barrier, so that no rank tears its gloo connections down while a peer still talks on
    them (ranks exiting at different moments died with SIGABRT in gloo's threads otherwise).
    """
    world, _ = _dist_info()
    owns_group = world > 1 and not dist.is_initialized()
    if owns_group:
        dist.init_process_group("nccl" if torch.device(device).type == "cuda" else "gloo")
    try:
        result = _train(
            run,
            train_set,
            val_set,
            out_dir,
            device=device,
            progress=progress,
            cancel=cancel,
            show_progress=show_progress,
            resume=resume,
            init=init,
        )
    except BaseException:
        if owns_group:
            dist.destroy_process_group()  # no barrier: the peers may never get there
        raise
    if owns_group:
        dist.barrier()
        dist.destroy_process_group()
    return result


def _train(
    run: RunConfig,
    train_set: PairSource,
    val_set: PairSource | None,
    out_dir: str | Path,
    *,
    device: str | torch.device = "cpu",
    progress: Callable[[dict[str, Any]], None] | None = None,
    cancel: Any = None,
    show_progress: bool = True,
    resume: bool = True,
    init: str | Path | None = None,
) -> TrainResult:
    """Build a run's model, optimiser, schedule and batches, restore or initialise it, then run the loop."""
    cfg = run.train
    device = torch.device(device)
    out = Path(out_dir)
    world, rank = _dist_info()
    if cfg.batch_size % world:
        raise ValueError(
            f"batch_size {cfg.batch_size} is not divisible by the {world} data-parallel processes"
        )
    main = rank == 0
    if main:
        out.mkdir(parents=True, exist_ok=True)

    torch.manual_seed(cfg.seed)
    if cfg.demo_task_weight > 0:  # the head follows the training tasks and the labelling
        groups, table = label_table(train_set.tasks, cfg.demo_task_labels)
        run.model.demo_task_classes = sum(groups)
        run.model.demo_task_groups = groups if table else ()
        run.model.demo_task_table = table
    model = OSVIWM(run.model).to(device)
    plan = BatchPlan(
        len(train_set),
        cfg.batch_size,
        cfg.seed,
        expert_indices_of(train_set),
        cfg.pairs_per_expert,
    )
    per_epoch = plan.batches_per_epoch
    total = steps_for(cfg, len(train_set))
    model.freeze(cfg.freeze)
    trained = [p for p in model.parameters() if p.requires_grad]
    decay = [p for p in trained if p.ndim >= 2]
    no_decay = [p for p in trained if p.ndim < 2]
    optimizer = torch.optim.AdamW(
        [{"params": decay, "weight_decay": cfg.weight_decay}, {"params": no_decay, "weight_decay": 0.0}],
        lr=cfg.lr_max,
        fused=True,  # one kernel over all tensors: ~5x faster steps than the per-tensor loop on CPU
    )
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda s: learning_rate_factor(s, total, cfg.lr_warmup, cfg.lr_max, cfg.lr_final)
    )
    fingerprint = train_set.fingerprint()
    loop = TrainingLoop(
        out,
        total,
        cfg.seed,
        log_every=cfg.log_every,
        val_every=cfg.val_every,
        checkpoint_every=cfg.checkpoint_every,
        best_metric="val_loss_sdtw",
        best_key="best_val_loss",
        name="train",
        epoch_length=per_epoch,
        samples_per_step=cfg.batch_size,
        log_events=True,
        world=world,
        rank=rank,
    )

    def restore(ckpt: dict[str, Any]) -> None:
        diffs = _config_differences(ckpt["config"], run.to_dict())
        if diffs:
            raise CheckpointMismatch(
                f"{loop.last_path} was trained with another configuration ({'; '.join(diffs)}); use another "
                "--out directory or --restart"
            )
        if ckpt["dataset_fingerprint"] != fingerprint:
            raise CheckpointMismatch(
                f"{loop.last_path} was trained on dataset {ckpt['dataset_fingerprint']}, this dataset is "
                f"{fingerprint}; use another --out directory or --restart"
            )
        model.load_state_dict(ckpt["model"])
        optimizer.load_state_dict(ckpt["optimizer"])
        scheduler.load_state_dict(ckpt["scheduler"])

    resumed = resume and loop.resume(lambda path: load_checkpoint(path, device), restore)
    if not resumed and init is not None:
        _load_init(model, run, init, device)
    elif not resumed:
        model.set_depth_prior(median_path_depth(train_set))
    if main:
        summary = {
            "config": run.to_dict(),
            "dataset_fingerprint": fingerprint,
            "tasks": list(train_set.tasks),
        }
        if init is not None:
            summary["init"] = str(init)
        write_json(out / "config.json", summary)

    core = model
    forward: torch.nn.Module = torch.nn.parallel.DistributedDataParallel(model) if world > 1 else model

    def state() -> dict[str, Any]:
        return {
            "format": CHECKPOINT_FORMAT,
            "config": run.to_dict(),
            "dataset_fingerprint": fingerprint,
            "tasks": list(train_set.tasks),
            "total_steps": total,
            "model": core.state_dict(),
            "optimizer": optimizer.state_dict(),
            "scheduler": scheduler.state_dict(),
            "torch_version": torch.__version__,
            "time": time.time(),
        }

    def one_step(step: int, batch: Batch, seed: int) -> StepOutput:
        torch.manual_seed(seed)
        g = torch.Generator().manual_seed(seed)
        loss, parts = compute_losses(forward, core, batch.to(device), run, step, total, g)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(
            core.parameters(), cfg.grad_clip if cfg.grad_clip > 0 else float("inf")
        )
        optimizer.step()
        lr = optimizer.param_groups[0]["lr"]
        scheduler.step()
        return StepOutput({**parts, "grad_norm": float(grad_norm)}, lr)

    def validate_at(step: int) -> dict[str, float]:
        assert val_set is not None
        return validate(core, val_set, run, step, total, device)

    batches = plan_batches(train_set, plan, total, _Collate(run), cfg.num_workers, world=world, rank=rank)
    forward.train()
    return loop.run(
        batches,
        one_step,
        state,
        validate=validate_at if val_set is not None else None,
        progress=progress,
        cancel=cancel,
        show_progress=show_progress,
    )


def _load_init(model: OSVIWM, run: RunConfig, init: str | Path, device: torch.device) -> None:
    """Start ``model`` from the weights of the checkpoint or policy file ``init`` (see ``train``), or only its
    encoder from a pretrained encoder (``studio pretrain-encoder``)."""
    start = read_torch_file(init, device)
    if is_pretrained_encoder(start):
        try:
            load_pretrained_encoder(model, start, init)
        except ValueError as exc:
            raise CheckpointMismatch(str(exc)) from exc
        return
    if not isinstance(start, dict) or start.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(
            f"{init} is not an OSVI-WM checkpoint (format {CHECKPOINT_FORMAT}) nor a pretrained encoder"
        )
    saved = dict(start["config"]["model"])
    # A demonstration-task head may be added to a checkpoint trained without one, or one naming other labels
    # replaced (either starts untrained).
    head_keys = ("demo_task_classes", "demo_task_groups", "demo_task_table")
    current = run.to_dict()["model"]
    new_head = run.model.demo_task_classes > 0 and any(
        _as_lists(saved.get(k, getattr(ModelConfig(), k))) != _as_lists(current[k]) for k in head_keys
    )
    if new_head:
        saved.update({k: current[k] for k in head_keys})
    # A checkpoint of the no-world-model ablation may start the full model (a curriculum: encoder, π, pooling
    # and head carry over, 𝒲 starts untrained).
    new_wm = run.model.world_model and not saved.get("world_model", True)
    if new_wm:
        saved["world_model"] = True
    untrained = (("demo_task_head.",) if new_head else ()) + (("world_model.",) if new_wm else ())
    # How a policy file is planned (guidance, its gate) is set when it is exported, not by its weights: a run may
    # start from a guided policy without repeating them.
    saved.update({k: current[k] for k in PLANNING_FIELDS})
    diffs = _config_differences({"model": saved}, {"model": current, "train": {}})
    if diffs:
        raise CheckpointMismatch(f"{init} has another model configuration ({'; '.join(diffs)})")
    state = {
        k: v.float() if v.is_floating_point() else v
        for k, v in start["model"].items()
        if not k.startswith(untrained)
    }
    missing, unexpected = model.load_state_dict(state, strict=False)
    if unexpected or [k for k in missing if not k.startswith(untrained)]:
        raise CheckpointMismatch(
            f"{init}: weights do not match the model (missing {missing}, unexpected {unexpected})"
        )


class _Collate:
    """Picklable collate function bound to the model's input size and frame counts."""

    def __init__(self, run: RunConfig) -> None:
        height, width = run.model.image_size
        self.size = (int(height), int(width))
        self.n_expert = run.model.n_expert_frames
        self.n_agent = run.model.n_agent_frames

    def __call__(self, samples: list[dict[str, Any]]) -> Batch:
        return collate_pairs(samples, self.size, self.n_expert, self.n_agent)
