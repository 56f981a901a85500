"""The ``train`` job handler: :func:`studio.model.train.train` run by a trainer worker for a job on the bus.

The job's spec (:class:`TrainJobSpec`) says what ``studio train`` takes on its command line. Progress
(step, loss, learning rate, samples/s, ETA) goes to the job's progress stream after every step;
checkpoints are announced as artifacts once written; cancelling the job stops training after a
checkpoint. A re-queued job (its trainer died) resumes from ``run_dir/last.pt`` — the training loop
resumes by itself from the run directory, with the same configuration and data.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import msgspec

from studio.backend.job_runner import JobContext


class TrainJobSpec(msgspec.Struct, forbid_unknown_fields=True):
    """What a ``train`` job runs (the options of ``studio train``).

    Attributes:
        data_dir: dataset root (the episode store) the trainer reads.
        run_dir: run directory: checkpoints, metrics and config; resuming continues there.
        config: preset name (``cpu``, ``paper``, ``paper-metaworld``).
        overrides: ``section.field=value`` assignments applied to the preset.
        steps: optimiser steps (None: the preset's epochs).
        seed: seed of every random choice (None: the preset's).
        scene: scene (or split file) selecting the training and validation tasks.
        device: torch device.
        threads: torch CPU threads (None: torch's default).
    """

    data_dir: str
    run_dir: str
    config: str = "cpu"
    overrides: list[str] = []
    steps: int | None = None
    seed: int | None = None
    scene: str = "pick_place"
    device: str = "cpu"
    threads: int | None = None


def parse_spec(spec: dict[str, Any]) -> TrainJobSpec:
    try:
        return msgspec.convert(spec, TrainJobSpec)
    except msgspec.ValidationError as e:
        raise ValueError(f"invalid train job spec: {e}") from None


def run_training_job(ctx: JobContext) -> dict[str, Any]:
    """Train as the spec says; returns how the run ended (status, step, run directory, best validation loss)."""
    spec = parse_spec(ctx.spec)
    import torch

    from studio.model.config import preset
    from studio.model.train import train
    from studio.model.train_command import open_splits, scene_of

    overrides = list(spec.overrides)
    if spec.steps is not None:
        overrides.append(f"train.max_steps={spec.steps}")
    if spec.seed is not None:
        overrides.append(f"train.seed={spec.seed}")
    cfg = preset(spec.config, scene_of(spec.scene)).with_overrides(overrides)
    if spec.threads:
        torch.set_num_threads(spec.threads)
    ctx.progress(0, message="preparing the training data")
    train_set, val_set = open_splits(spec.data_dir, cfg, spec.scene)
    if len(train_set) == 0:
        raise ValueError(f"no training pairs in {spec.data_dir} (record or collect episodes first)")
    out = Path(spec.run_dir)
    watched = {name: out / name for name in ("last.pt", "best.pt")}
    seen = {name: _mtime(path) for name, path in watched.items()}
    previous_step = 0

    def announce_new_checkpoints(step_of: dict[str, int]) -> None:
        for name, path in watched.items():
            stamp = _mtime(path)
            if stamp is not None and stamp != seen[name]:
                seen[name] = stamp
                ctx.artifact(f"checkpoint:{name}", path, step=step_of[name])

    def on_progress(info: dict[str, Any]) -> None:
        nonlocal previous_step
        step = int(info["step"])
        # best.pt is written before this call in the same step, last.pt after the previous call.
        announce_new_checkpoints({"best.pt": step, "last.pt": previous_step})
        previous_step = step
        ctx.progress(
            step, int(info["total_steps"]), eta_s=float(info["eta_s"]),
            loss=float(info["loss"]), lr=float(info["lr"]), samples_per_s=float(info["samples_per_s"]),
            epoch=float(info["epoch"]),
        )  # fmt: skip

    result = train(
        cfg, train_set, val_set if len(val_set) else None, out, device=spec.device, progress=on_progress,
        cancel=lambda: ctx.cancelled, show_progress=False, resume=True,
    )  # fmt: skip
    announce_new_checkpoints({"best.pt": result.step, "last.pt": result.step})
    return {
        "status": result.status,
        "step": result.step,
        "total_steps": result.total_steps,
        "run_dir": str(result.out_dir),
        "best_val_loss": result.best_val_loss,
        "resumed": ctx.attempt > 1,
    }


def _mtime(path: Path) -> int | None:
    try:
        return path.stat().st_mtime_ns
    except FileNotFoundError:
        return None
