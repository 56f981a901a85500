"""`studio pretrain-encoder`: self-supervised pretraining of the encoder on a scene's stored frames.

    studio pretrain-encoder --data DIR --out DIR [--config cpu] [--scene S] [--tasks train|all]
                            [--set model.field=value ...] [--steps N] [--seed S] [--threads N]

The encoder is the one ``studio train`` would build with the same ``--config``, ``--scene`` and ``--set``
model fields; ``studio train --init DIR/best.pt`` (same model fields) then starts from it. ``--tasks all``
also reads the held-out tasks' frames (images only). Re-running resumes from ``DIR/last.pt``. See
``studio.model.pretrain_encoder`` for the objective.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

from studio.model.config import PRESETS, preset

TASK_CHOICES = ("train", "all")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", choices=PRESETS, default="cpu", help="preset whose encoder is pretrained")
    parser.add_argument("--data", required=True, help="dataset root (the episode store)")
    parser.add_argument("--out", required=True, help="run directory")
    parser.add_argument(
        "--scene", default="pick_place", help="scene (or split JSON path) that selects the tasks"
    )
    parser.add_argument(
        "--tasks",
        choices=TASK_CHOICES,
        default="train",
        help="the split's training tasks (default), or every task of the split including the held-out ones",
    )
    parser.add_argument(
        "--set", nargs="*", action="extend", default=[], metavar="model.FIELD=VALUE", help="model overrides"
    )
    parser.add_argument("--steps", type=int, default=None, help="optimiser steps (default 1000)")
    parser.add_argument("--seed", type=int, default=None)
    parser.add_argument(
        "--batch-size", type=int, default=None, help="pairs per step (all their frames are used)"
    )
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    parser.add_argument("--restart", action="store_true")
    parser.add_argument("--no-progress", action="store_true")


def pretraining_split(scene: str, tasks: str):
    """The split whose ``train`` tasks are pretrained on: the scene's training tasks, or all of its tasks."""
    from studio.data.splits import load_split

    if tasks not in TASK_CHOICES:
        raise ValueError(f"--tasks must be one of {', '.join(TASK_CHOICES)}, got {tasks!r}")
    spec = load_split(scene)
    if tasks == "all":
        spec = dataclasses.replace(
            spec, train=spec.train + spec.test, test=(), test_groups={}, replan_groups=()
        )
    return spec


def open_frames(root: str, run_cfg, spec, seed: int, progress: bool = False):
    """Training and validation pairs of ``spec``'s training tasks at the model's input size."""
    from studio.data.training_view import PairDataset

    kw = dict(
        image_size=tuple(run_cfg.model.image_size),
        n_expert=run_cfg.model.n_expert_frames,
        n_agent=run_cfg.model.n_agent_frames,
        seed=seed,
        scene=spec.scene,
        split_spec=spec,
        progress=progress,
    )
    return PairDataset(root, "train", **kw), PairDataset(root, "val", **kw)


def run(args: argparse.Namespace) -> int:
    import torch

    from studio.model.pretrain_encoder import PRETRAIN_DEFAULTS, pretrain_encoder
    from studio.model.train_command import scene_of

    try:
        stray = [s for s in args.set if not s.startswith("model.")]
        if stray:
            raise ValueError(f"only model fields can be set here, not {', '.join(stray)}")
        run_cfg = preset(args.config, scene_of(args.scene)).with_overrides(list(args.set))
        changes = {
            k: v
            for k, v in (("steps", args.steps), ("seed", args.seed), ("batch_size", args.batch_size))
            if v
        }
        cfg = dataclasses.replace(PRETRAIN_DEFAULTS, **changes)
        spec = pretraining_split(args.scene, args.tasks)
        if args.threads:
            torch.set_num_threads(args.threads)
        train_set, val_set = open_frames(args.data, run_cfg, spec, cfg.seed, progress=not args.no_progress)
        if len(train_set) == 0:
            raise ValueError(f"no stored episodes of these tasks in {args.data}")
        result = pretrain_encoder(
            run_cfg,
            train_set,
            val_set if len(val_set) else None,
            args.out,
            cfg,
            tasks=args.tasks,
            device=args.device,
            show_progress=not args.no_progress,
            resume=not args.restart,
        )
    except (ValueError, FileNotFoundError) as exc:
        print(f"studio pretrain-encoder: {exc}", file=sys.stderr)
        return 2
    print(f"{result.status} at step {result.step}/{result.total_steps}; encoder {result.out_dir / 'best.pt'}")
    return 0
