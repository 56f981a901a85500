"""The ``train`` job handler: :func:`studio.model.train.train` run by a trainer worker for a job on the bus.

The job's spec (:class:`TrainJobSpec`) says what ``studio train`` takes on its command line. Progress
(step, loss, learning rate, samples/s, ETA) goes to the job's progress stream after every step;
checkpoints are announced as artifacts once written; cancelling the job stops training after a
checkpoint. Every path the spec names must lie in the trainer's ``--data-dir`` (a relative one is taken from
there; ``init`` may also be a shipped policy, :mod:`studio.backend.spec_paths`), else the job fails with one line
before anything is created. A re-queued job (its trainer died) resumes from ``run_dir/last.pt`` — the training loop
resumes by itself from the run directory, with the same configuration and data. The configuration and data come
from :func:`studio.model.train_command.prepare_run`, as for ``studio train``: a batch larger than the training pairs
is lowered to them (said in the progress message and the result), a store without a pair fails the job with what
to record, and ``fine_tune`` continues ``init`` with the fine-tuning schedule.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec

from studio.backend.job_runner import JobContext
from studio.backend.messages import ContentId
from studio.backend.spec_paths import checkpoint_path, inside_data_dir
from studio.model.recipes import recipe

_Path = Annotated[str, msgspec.Meta(min_length=1, max_length=4096)]
_Override = Annotated[str, msgspec.Meta(min_length=3, max_length=512)]
_Name = Annotated[str, msgspec.Meta(min_length=1, max_length=64)]


class TrainJobSpec(msgspec.Struct, forbid_unknown_fields=True):
    """What a ``train`` job runs (the options of ``studio train``).

    Attributes:
        data_dir: dataset root (the episode store) the trainer reads.
        run_dir: run directory: checkpoints, metrics and config; resuming continues there.
        config: preset name (``cpu``, ``paper``, ``paper-metaworld``); not used when fine-tuning.
        overrides: ``section.field=value`` assignments applied to the preset (or the fine-tuning schedule).
        steps: optimiser steps (None: the preset's epochs, or the fine-tuning schedule's length).
        seed: seed of every random choice (None: the preset's).
        scene: scene (or split file) selecting the training and validation tasks (None: the recipe's, else
            pick-and-place).
        recipe, stage: train one stage of a named recipe (``studio train --recipe --stage``;
            :mod:`studio.model.recipes`) instead of the preset ``config``.
        device: torch device.
        threads: torch CPU threads (None: torch's default).
        init: a checkpoint or policy file whose weights the run starts from (``studio train --init``).
        fine_tune: continue ``init`` with the fine-tuning schedule (``studio train --fine-tune``).
        inputs: content id of the job's inputs (:class:`~studio.backend.artifact_transfer.InputManifest`), which
            a worker with its own data dir fetches before the job runs (set by the hub's job client).
    """

    data_dir: _Path
    run_dir: _Path
    config: Literal["paper", "paper-metaworld", "cpu"] = "cpu"
    overrides: Annotated[list[_Override], msgspec.Meta(max_length=64)] = []
    steps: Annotated[int, msgspec.Meta(ge=1, le=10_000_000)] | None = None
    seed: Annotated[int, msgspec.Meta(ge=0, le=2**31 - 1)] | None = None
    scene: _Path | None = None
    recipe: _Name | None = None
    stage: _Name | None = None
    device: Annotated[str, msgspec.Meta(min_length=1, max_length=32)] = "cpu"
    threads: Annotated[int, msgspec.Meta(ge=1, le=1024)] | None = None
    init: _Path | None = None
    fine_tune: bool = False
    inputs: ContentId | None = None

    def __post_init__(self) -> None:
        if self.fine_tune and self.init is None:
            raise ValueError("a fine-tuning job names the policy it starts from (init)")
        if self.recipe is not None:
            recipe(self.recipe).stage(self.stage)  # raises naming the recipes or stages there are
        elif self.stage is not None:
            raise ValueError("a stage names a stage of a recipe: give the recipe too")


def parse_spec(spec: dict[str, Any]) -> TrainJobSpec:
    try:
        return msgspec.convert(spec, TrainJobSpec)
    except (msgspec.ValidationError, ValueError) as e:
        raise ValueError(f"invalid train job spec: {e}") from None


def run_training_job(ctx: JobContext) -> dict[str, Any]:
    """Train as the spec says; returns how the run ended (status, step, run directory, best validation loss,
    the batch size used and what was adjusted to the data)."""
    spec = parse_spec(ctx.spec)
    data_dir = inside_data_dir(ctx.data_dir, spec.data_dir, "data_dir", "train")
    out = inside_data_dir(ctx.data_dir, spec.run_dir, "run_dir", "train")
    scene = spec.scene
    if scene is not None and ("/" in scene or scene.endswith(".json")):  # a split file, not a scene name
        scene = str(inside_data_dir(ctx.data_dir, scene, "split file (scene)", "train"))
    init = None if spec.init is None else checkpoint_path(ctx.data_dir, spec.init, "init", "train")
    import torch

    from studio.model.train import train
    from studio.model.train_command import prepare_run

    if spec.threads:
        torch.set_num_threads(spec.threads)
    ctx.progress(0, message="preparing the training data")
    prepared = prepare_run(
        str(data_dir),
        config=spec.config,
        scene=scene,
        overrides=list(spec.overrides),
        steps=spec.steps,
        seed=spec.seed,
        init=init,
        fine_tune=spec.fine_tune,
        recipe=spec.recipe,
        stage=spec.stage,
    )
    cfg, train_set, val_set = prepared.run, prepared.train_set, prepared.val_set
    if prepared.notes:
        ctx.progress(0, message="; ".join(prepared.notes))
    watched = {name: out / name for name in ("last.pt", "best.pt")}
    seen = {name: _mtime(path) for name, path in watched.items()}
    previous_step = 0

    def announce_new_checkpoints(step_of: dict[str, int]) -> None:
        for name, path in watched.items():
            stamp = _mtime(path)
            if stamp is not None and stamp != seen[name]:
                seen[name] = stamp
                ctx.artifact(f"checkpoint:{name}", path, step=step_of[name])
                if (out / "metrics.jsonl").is_file():  # the curves so far, for a hub not sharing this disk
                    ctx.output(out / "metrics.jsonl")

    def on_progress(info: dict[str, Any]) -> None:
        nonlocal previous_step
        step = int(info["step"])
        # best.pt is written before this call in the same step, last.pt after the previous call.
        announce_new_checkpoints({"best.pt": step, "last.pt": previous_step})
        previous_step = step
        ctx.progress(
            step,
            int(info["total_steps"]),
            eta_s=float(info["eta_s"]),
            loss=float(info["loss"]),
            lr=float(info["lr"]),
            samples_per_s=float(info["samples_per_s"]),
            epoch=float(info["epoch"]),
        )

    result = train(
        cfg,
        train_set,
        val_set if len(val_set) else None,
        out,
        device=spec.device,
        progress=on_progress,
        cancel=lambda: ctx.cancelled,
        show_progress=False,
        resume=True,
        init=init,
    )
    announce_new_checkpoints({"best.pt": result.step, "last.pt": result.step})
    ctx.output(out)  # the whole run directory, for a hub that does not share this disk
    return {
        "status": result.status,
        "step": result.step,
        "total_steps": result.total_steps,
        "run_dir": str(result.out_dir),
        "best_val_loss": result.best_val_loss,
        "resumed": ctx.attempt > 1,
        "pairs": len(train_set),
        "batch_size": cfg.train.batch_size,
        "notes": prepared.notes,
    }


def _mtime(path: Path) -> int | None:
    try:
        return path.stat().st_mtime_ns
    except FileNotFoundError:
        return None
