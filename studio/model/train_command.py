"""`studio train`: train OSVI-WM on the episode store (the training and validation splits of ``studio.data``).

    studio train --config cpu|paper|paper-metaworld --data DIR --out RUN_DIR [--steps N] [--seed S]
                 [--set model.field=value train.field=value ...] [--restart] [--init CKPT] [--device cpu]

Re-running the same command after an interruption resumes from ``RUN_DIR/last.pt`` at the step it reached; a
different ``--steps`` lengthens or shortens the resumed run (its learning-rate schedule follows the new length),
any other change of configuration is refused. ``--restart`` starts over. ``--init CKPT`` starts a new run from
another checkpoint's weights (fine-tuning a shipped policy on your own episodes, a second stage of a
curriculum over task sets, or growing the full model from a ``model.world_model=false`` checkpoint: 𝒲 is added
untrained, the way ``studio quickstart`` trains OSVI-WM). ``--set train.expert_embodiments=human`` pairs the
Panda's agent episodes with the simulated hand's demonstrations only (``panda``: the Panda's own demonstrations;
default: every stored demonstration). Under ``torchrun --nproc_per_node K -m studio.cli
train ...`` it trains with K data-parallel processes.
"""

from __future__ import annotations

import argparse
import sys

from studio.model.config import PRESETS, preset


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", choices=PRESETS, default="cpu", help="preset (default: cpu)")
    parser.add_argument("--data", required=True, help="dataset root (the episode store)")
    parser.add_argument("--out", required=True, help="run directory (checkpoints, metrics, config)")
    parser.add_argument(
        "--steps", type=int, default=None, help="optimiser steps (default: the preset's epochs)"
    )
    parser.add_argument("--seed", type=int, default=None, help="seed of every random choice")
    parser.add_argument(
        "--scene", default="pick_place", help="scene (or split JSON path) that selects the tasks"
    )
    parser.add_argument(
        "--set",
        nargs="*",
        action="extend",
        default=[],
        metavar="SECTION.FIELD=VALUE",
        help="config overrides",
    )
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    parser.add_argument("--restart", action="store_true", help="ignore an existing checkpoint in --out")
    parser.add_argument(
        "--init",
        default=None,
        metavar="CKPT",
        help="start from this checkpoint's or policy file's weights (same model configuration, or the same "
        "without the world model, which then starts untrained; fresh optimiser)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def scene_of(scene_or_split: str) -> str:
    """The scene a ``--scene`` value names (a scene, or a split JSON file's scene)."""
    if scene_or_split.endswith(".json"):
        from studio.data.splits import load_split

        return load_split(scene_or_split).scene
    return scene_or_split


def open_splits(root: str, run, scene: str, progress: bool = False):
    """The training and validation PairDatasets of the store at ``root`` at the model's input size, their expert
    side limited to ``train.expert_embodiments`` when it names any."""
    try:
        from studio.data.training_view import PairDataset
    except ImportError as exc:  # pragma: no cover - depends on the data package being installed
        raise SystemExit(f"studio train needs studio.data.training_view.PairDataset: {exc}") from exc
    kw = dict(
        image_size=tuple(run.model.image_size),
        n_expert=run.model.n_expert_frames,
        n_agent=run.model.n_agent_frames,
        seed=run.train.seed,
        scene=scene,
        expert_embodiments=run.train.expert_embodiments or None,
        progress=progress,
    )
    return PairDataset(root, "train", **kw), PairDataset(root, "val", **kw)


def run(args: argparse.Namespace) -> int:
    import torch

    from studio.model.train import CheckpointMismatch, train

    overrides = list(args.set)
    if args.steps is not None:
        overrides.append(f"train.max_steps={args.steps}")
    if args.seed is not None:
        overrides.append(f"train.seed={args.seed}")
    try:
        cfg = preset(args.config, scene_of(args.scene)).with_overrides(overrides)
    except ValueError as exc:
        print(f"studio train: {exc}", file=sys.stderr)
        return 2
    if args.threads:
        torch.set_num_threads(args.threads)
    train_set, val_set = open_splits(args.data, cfg, args.scene, progress=not args.no_progress)
    if len(train_set) == 0:
        print(
            f"studio train: no training pairs in {args.data} (record or collect episodes first)",
            file=sys.stderr,
        )
        return 2
    try:
        result = train(
            cfg,
            train_set,
            val_set if len(val_set) else None,
            args.out,
            device=args.device,
            show_progress=not args.no_progress,
            resume=not args.restart,
            init=args.init,
        )
    except (CheckpointMismatch, ValueError) as exc:
        print(f"studio train: {exc}", file=sys.stderr)
        return 2
    print(
        f"{result.status} at step {result.step}/{result.total_steps}; checkpoint {result.out_dir / 'last.pt'}"
    )
    return 0
