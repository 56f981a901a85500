"""`studio train`: train OSVI-WM on the episode store (the training and validation splits of ``studio.data``).

    studio train --config cpu|paper|paper-metaworld --data DIR --out RUN_DIR [--steps N] [--seed S]
                 [--set model.field=value train.field=value ...] [--restart] [--init CKPT [--fine-tune]]
                 [--recipe NAME [--stage STAGE]] [--device cpu]

``--recipe NAME --stage STAGE`` trains one stage of a named recipe (:mod:`studio.model.recipes`: ``pick-place``,
``pick-place-no-world-model``, ``push``, ``metaworld``) instead of a bare preset: the stage's settings, scene, steps
and seed offset, with ``--init`` naming the checkpoint of the stage it starts from. Each ``--set`` value is read as
its field's type (``model.world_model=flase`` is refused with one line, not taken as a true string).

Re-running the same command after an interruption resumes from ``RUN_DIR/last.pt`` at the step it reached; a
different ``--steps`` lengthens or shortens the resumed run (its learning-rate schedule follows the new length),
any other change of configuration is refused. ``--restart`` starts over. ``--init CKPT`` starts a new run from
another checkpoint's weights (fine-tuning a shipped policy on your own episodes, a second stage of a
curriculum over task sets, or growing the full model from a ``model.world_model=false`` checkpoint: 𝒲 is added
untrained, the way ``studio quickstart`` trains OSVI-WM). ``--set train.expert_embodiments=human`` pairs the
Panda's agent episodes with the simulated hand's demonstrations only (``panda``: the Panda's own demonstrations;
default: every stored demonstration). Under ``torchrun --nproc_per_node K -m studio.cli
train ...`` it trains with K data-parallel processes.

``--fine-tune --init POLICY`` continues a trained policy on the store's episodes with the short schedule of
:func:`studio.model.config.fine_tune_config` (the policy's own network and settings; ``--config`` is not used): the
studio's *Fine-tune the active policy on my episodes* runs the same :func:`prepare_run`. A batch larger than the
training pairs is lowered to them, and said; a store without a training pair is refused, with what to record.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field
from typing import Any

from studio.model.config import PRESETS, RunConfig, fine_tune_config, fit_batch, preset
from studio.model.recipes import RECIPES, stage_config


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", choices=PRESETS, default="cpu", help="preset (default: cpu)")
    parser.add_argument("--data", required=True, help="dataset root (the episode store)")
    parser.add_argument("--out", required=True, help="run directory (checkpoints, metrics, config)")
    parser.add_argument(
        "--steps", type=int, default=None, help="optimiser steps (default: the preset's epochs)"
    )
    parser.add_argument("--seed", type=int, default=None, help="seed of every random choice")
    parser.add_argument(
        "--scene",
        default=None,
        help="scene (or split JSON path) that selects the tasks (default: the recipe's, else pick_place)",
    )
    parser.add_argument(
        "--recipe",
        choices=tuple(RECIPES),
        default=None,
        help="train one stage of a recipe (studio.model.recipes): its settings over the cpu preset, its steps "
        "and seed offset (--steps, --seed and --set still apply)",
    )
    parser.add_argument(
        "--stage", default=None, help="with --recipe: the stage to train (default: the first)"
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
    parser.add_argument(
        "--fine-tune",
        action="store_true",
        help="with --init: continue that policy on these episodes with the short fine-tuning schedule (its own "
        "network and settings; --config is not used)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def scene_of(scene_or_split: str) -> str:
    """The scene a ``--scene`` value names (a scene, or a split JSON file's scene)."""
    if scene_or_split.endswith(".json"):
        from studio.data.splits import load_split

        return load_split(scene_or_split).scene
    return scene_or_split


def _pair_selection(run: RunConfig, scene: str) -> dict[str, Any]:
    """What selects a run's pairs besides the store: its scene or split file, and whose demonstrations."""
    return {"scene": scene, "expert_embodiments": run.train.expert_embodiments or None}


def count_training_pairs(root, run: RunConfig, scene: str, split_spec=None):
    """The :class:`~studio.data.training_view.PairCount` of the training pairs ``open_splits`` gives ``run`` (same
    selection), without decoding a frame; ``split_spec`` (a ``SplitSpec``) replaces the scene's split file."""
    from studio.data.training_view import count_pairs

    return count_pairs(root, split_spec=split_spec, **_pair_selection(run, scene))


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
        progress=progress,
        gripper_labels=run.train.gripper_labels,
        **_pair_selection(run, scene),
    )
    return PairDataset(root, "train", **kw), PairDataset(root, "val", **kw)


class NoTrainingPairs(ValueError):
    """The store gives the run's tasks no training pair; the message says what to record."""


@dataclass
class PreparedRun:
    """A run ready for :func:`studio.model.train.train`: its configuration, data and what was adjusted."""

    run: RunConfig
    train_set: Any
    val_set: Any
    notes: list[str] = field(default_factory=list)


def init_config(init: str) -> dict[str, Any]:
    """The configuration stored in the checkpoint or policy file ``init`` (read without unpickling any code)."""
    from studio.model.checkpoint_info import read_checkpoint_info

    try:
        info = read_checkpoint_info(init)
    except (OSError, ValueError) as exc:
        raise ValueError(f"cannot fine-tune from {init}: {exc}") from None
    saved = info.get("config")
    if not isinstance(saved, dict) or not isinstance(saved.get("model"), dict):
        raise ValueError(f"cannot fine-tune from {init}: it is not an OSVI-WM checkpoint or policy file")
    return saved


def prepare_run(
    root: str,
    *,
    config: str = "cpu",
    scene: str | None = None,
    overrides: list[str] | None = None,
    steps: int | None = None,
    seed: int | None = None,
    init: str | None = None,
    fine_tune: bool = False,
    progress: bool = False,
    recipe: str | None = None,
    stage: str | None = None,
) -> PreparedRun:
    """The configuration and data of a ``studio train`` run (the CLI and the ``train`` job both start here).

    ``fine_tune`` takes the configuration of ``init`` with the fine-tuning schedule for the pairs found
    (:func:`~studio.model.config.fine_tune_config`), otherwise the preset ``config`` for the scene; then
    ``overrides``, ``steps`` and ``seed``. A ``recipe`` replaces ``config``: its ``stage`` (default: the first)
    gives the settings, the scene (unless ``scene`` is given), the default steps and the seed offset, and a stage
    that starts from an earlier one needs ``init``. Then a batch larger than the training pairs is lowered to them (a
    note says so). Raises :class:`NoTrainingPairs` saying what to record when there is no training pair,
    ``ValueError`` for a bad override or ``init``.
    """
    extra = list(overrides or [])
    saved: dict[str, Any] | None = None
    if recipe is not None:
        if fine_tune:
            raise ValueError("fine-tuning continues a policy with its own settings; it takes no recipe")
        start, chosen = stage_config(recipe, stage)
        if chosen.init_from is not None and init is None:
            raise ValueError(
                f"stage {chosen.name!r} of recipe {recipe!r} starts from stage {chosen.init_from!r}'s "
                f"{chosen.init_checkpoint} checkpoint: name it with --init"
            )
        scene = scene or RECIPES[recipe].scene
        steps = chosen.steps if steps is None else steps
        seed = (start.train.seed if seed is None else seed) + chosen.seed_offset
    elif stage is not None:
        raise ValueError("--stage names a stage of a recipe: give the recipe too (--recipe)")
    elif fine_tune:
        if init is None:
            raise ValueError("fine-tuning starts from a policy: name its checkpoint or policy file (--init)")
        saved = init_config(init)
        start = RunConfig.from_dict(saved)  # the data side: image size, frames, embodiments
    else:
        start = preset(config, scene_of(scene or "pick_place"))
    scene = scene or "pick_place"
    typed: dict[str, Any] = {}
    if steps is not None:
        typed["max_steps"] = steps
    if seed is not None:
        typed["seed"] = seed
    cfg = start.with_overrides(extra).with_changes(train=typed)
    train_set, val_set = open_splits(root, cfg, scene, progress=progress)
    if len(train_set) == 0:
        sentence = count_training_pairs(root, cfg, scene).what_to_record()
        raise NoTrainingPairs(sentence or f"No training pairs in {root}: record or collect episodes first.")
    if saved is not None:
        cfg = fine_tune_config(saved, len(train_set), extra, typed)
    cfg, note = fit_batch(cfg, len(train_set))
    return PreparedRun(cfg, train_set, val_set, [note] if note else [])


def run(args: argparse.Namespace) -> int:
    import torch

    from studio.model.train import CheckpointMismatch, train

    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        prepared = prepare_run(
            args.data,
            config=args.config,
            scene=args.scene,
            overrides=list(args.set),
            steps=args.steps,
            seed=args.seed,
            init=args.init,
            fine_tune=args.fine_tune,
            progress=not args.no_progress,
            recipe=args.recipe,
            stage=args.stage,
        )
    except ValueError as exc:
        print(f"studio train: {exc}", file=sys.stderr)
        return 2
    for note in prepared.notes:
        print(f"studio train: {note}", file=sys.stderr)
    try:
        result = train(
            prepared.run,
            prepared.train_set,
            prepared.val_set if len(prepared.val_set) else None,
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
