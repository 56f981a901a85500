"""`studio train-decoder`: train the latent image decoder for a trained model (which stays frozen).

    studio train-decoder --model RUN_DIR/best.pt --data DIR --out DECODER_DIR [--steps N] [--seed S] [--scene S]

Uses the store's training split of the model's scene (held-out episodes for validation) and refuses tasks the
model was not trained on. ``--scene`` (a scene or a split JSON file) defaults to the scene the model was trained
on, read from the checkpoint's tasks. Re-running resumes from ``DECODER_DIR/last.pt``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

from studio.model.config import DecoderConfig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, help="OSVI-WM checkpoint (last.pt or best.pt of a run)")
    parser.add_argument("--data", required=True, help="dataset root (the episode store)")
    parser.add_argument("--out", required=True, help="decoder run directory")
    parser.add_argument("--steps", type=int, default=None)
    parser.add_argument("--seed", type=int, default=None)
    parser.add_argument("--batch-size", type=int, default=None)
    parser.add_argument(
        "--scene",
        default=None,
        help="scene (or split JSON path) that selects the tasks (default: the scene the model was trained on)",
    )
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--restart", action="store_true")
    parser.add_argument("--no-progress", action="store_true")


def run(args: argparse.Namespace) -> int:
    from studio.model.checkpoint import load_checkpoint
    from studio.model.checkpoint_info import scene_of_tasks
    from studio.model.config import RunConfig
    from studio.model.train_command import open_splits
    from studio.model.train_decoder import train_decoder

    changes = {
        k: v for k, v in (("steps", args.steps), ("seed", args.seed), ("batch_size", args.batch_size)) if v
    }
    cfg = dataclasses.replace(DecoderConfig(), **changes)
    try:
        ckpt = load_checkpoint(args.model)
        run_cfg = RunConfig.from_dict(ckpt["config"])
        scene = args.scene or scene_of_tasks(ckpt.get("tasks") or [])
        if scene is None:
            raise ValueError(
                f"{args.model} does not name the tasks of one scene it was trained on: pass --scene"
            )
        del ckpt
        train_set, val_set = open_splits(args.data, run_cfg, scene)
        result = train_decoder(
            args.model,
            train_set,
            val_set if len(val_set) else None,
            args.out,
            cfg,
            device=args.device,
            show_progress=not args.no_progress,
            resume=not args.restart,
        )
    except (ValueError, FileNotFoundError) as exc:
        print(f"studio train-decoder: {exc}", file=sys.stderr)
        return 2
    print(f"{result.status} at step {result.step}/{result.total_steps}; decoder {result.out_dir / 'best.pt'}")
    return 0
