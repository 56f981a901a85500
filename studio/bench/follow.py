"""`studio bench follow`: does an architecture learn to follow the demonstration? (synthetic task, seconds)

Trains the tiny test-size model on ``synthetic_task`` (four targets; only the demonstration tells which) once per
layout variant and reports, at a few validation points, the final-point and path errors and the demonstration
effect (how far the plan moves when the demonstration is swapped for another task's; ``train``). Predicting the
mean target gives a final error of about 0.18 m and an effect of 0. The variants are the π attention layout and
the world model's token layout and residual form (``config``); docs/experiments.md holds a measured table.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

VARIANTS: dict[str, dict] = {
    "paper": {},
    "joint+residual": {"wm_residual": True},
    "joint+no-wm": {"world_model": False},
    "divided+no-wm": {"world_model": False, "action_attention": "divided"},
    "divided+map": {"action_attention": "divided"},
    "divided+cells+residual": {"action_attention": "divided", "wm_tokens": "cells", "wm_residual": True},
    "divided+cells (cpu)": {"action_attention": "divided", "wm_tokens": "cells"},
    "divided+cells 2 blocks": {"action_attention": "divided", "wm_tokens": "cells", "action_blocks": 2},
    "cross+cells": {"action_attention": "cross", "wm_tokens": "cells"},
    "cross+cells 2 blocks": {"action_attention": "cross", "wm_tokens": "cells", "action_blocks": 2},
    "cross+cells 2 blocks wide": {
        "action_attention": "cross",
        "wm_tokens": "cells",
        "action_blocks": 2,
        "state_channels": 32,
        "action_attn_dim": 32,
        "action_mlp_dim": 64,
    },
    "joint+cells 2 blocks": {"wm_tokens": "cells", "action_blocks": 2},
}
NO_AUGMENTATION = dict(
    crop=0.0,
    translate=0.0,
    scale=(1.0, 1.0),
    hflip=0.0,
    brightness=0.0,
    contrast=0.0,
    saturation=0.0,
    hue=0.0,
    mixup=False,
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--steps", type=int, default=300, help="training steps per variant")
    parser.add_argument("--val-points", type=int, default=3, help="validations spread over the run")
    parser.add_argument(
        "--variants", default=",".join(VARIANTS), help=f"comma-separated, from: {', '.join(VARIANTS)}"
    )
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--lr", type=float, default=3e-3, help="peak learning rate of the one-cycle schedule")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--task",
        choices=("follow", "match"),
        default="follow",
        help="follow: fixed markers, the demonstration names the target; match: markers shuffled per "
        "episode, the agent must find the demonstrated colour in its own frame",
    )
    parser.add_argument(
        "--demo-task-weight",
        type=float,
        default=0.0,
        help="weight of the auxiliary demonstration-task loss (TrainConfig.demo_task_weight)",
    )
    parser.add_argument(
        "--episodes",
        type=int,
        default=0,
        help="episodes per task and role (default 3 for follow, 12 for match)",
    )


def measure(args: argparse.Namespace) -> dict:
    import json

    import torch

    from studio.bench.synthetic_task import SyntheticPairs, tiny_run_config
    from studio.model.train import train

    names = [v.strip() for v in args.variants.split(",") if v.strip()]
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        raise SystemExit(f"studio bench follow: unknown variant(s) {unknown}; choose from {list(VARIANTS)}")
    torch.set_num_threads(args.threads)
    every = max(1, args.steps // max(1, args.val_points))
    match = args.task == "match"
    episodes = args.episodes or (12 if match else 3)
    result: dict = {
        "task": args.task,
        "episodes_per_task": episodes,
        "steps": args.steps,
        "lr": args.lr,
        "demo_task_weight": args.demo_task_weight,
        "threads": args.threads,
        "seed": args.seed,
        "mean_target_final_err_m": None,
        "variants": {},
    }
    for name in names:
        run = tiny_run_config(
            max_steps=args.steps,
            lr_max=args.lr,
            val_every=every,
            val_batches=0,
            seed=args.seed,
            demo_task_weight=args.demo_task_weight,
            **NO_AUGMENTATION,
        )
        for field, value in VARIANTS[name].items():
            setattr(run.model, field, value)
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory() as out:
            train(
                run,
                SyntheticPairs(n_tasks=4, episodes_per_task=episodes, shuffle_targets=match),
                SyntheticPairs(n_tasks=4, episodes_per_task=3, split="val", shuffle_targets=match),
                out,
                show_progress=False,
            )
            lines = (Path(out) / "metrics.jsonl").read_text().splitlines()
        vals = [r for r in map(json.loads, lines) if r.get("split") == "val"]
        points = [
            {
                "step": r["step"],
                "final_err_m": round(r["val_final_err_m"], 4),
                "path_err_m": round(r["val_path_err_m"], 4),
                "demo_effect_m": round(r.get("val_demo_effect_m", 0.0), 4),
                **({"task_acc": round(r["val_task_acc"], 3)} if "val_task_acc" in r else {}),
            }
            for r in vals
        ]
        result["variants"][name] = {"wall_s": round(time.perf_counter() - t0, 1), "val": points}
    result["mean_target_final_err_m"] = _mean_target_error()
    return result


def _mean_target_error() -> float:
    """Final-point error of always predicting the mean of the four targets (validation episodes)."""
    import numpy as np

    from studio.bench.synthetic_task import TARGETS_CAM

    return round(float(np.mean(np.linalg.norm(TARGETS_CAM - TARGETS_CAM.mean(0), axis=1))), 4)
