"""`studio export-policy`: turn a training checkpoint (and its latent decoder) into a small inference file.

    studio export-policy RUN_DIR/best.pt OUT.pt [--decoder DECODER_DIR/best.pt] [--fp32] [--guidance G]
        [--guidance-gate GAIN | --gate-percentile P --data DATA_DIR] [--guided-from CHECKPOINT]
        [--surprise-gate S | --surprise-percentile P --data DATA_DIR] [--surprise-guidance G]

The policy file keeps everything planning needs — the checkpoint format, full configuration, dataset
fingerprint, trained tasks, step — and drops the optimiser and scheduler state (two thirds of a training
checkpoint). Weights are stored as float16 by default, halving the file again; they are cast back to
float32 when loaded (``Planner.load`` copies them into float32 parameters), which moves planned waypoints
by well under a millimetre (``tests/model/test_policy_export.py`` measures it). The decoder, when given, is
written next to it as ``OUT.decoder.pt``, where the studio looks for it (``studio.eval.latents.find_decoder``).
This is how ``studio/policies/`` is produced.

``--gate-percentile P`` sets the guidance gate from the training data instead of by hand: the P-th percentile of
the demonstration gains of every stored expert demonstration of the checkpoint's training tasks, so that a
held-out demonstration is guided only when its scene explains it less than P % of the training demonstrations
are explained by theirs (``studio.model.guidance``).

``--guided-from CHECKPOINT`` gives a gated policy a guided branch: CHECKPOINT's π, world model and waypoint head
(it must share the policy's architecture and encoder weights, e.g. an earlier stage trained with the encoder
fixed) compute each demonstration's gain and plan, with guidance, the demonstrations that reach the gate; the
policy's own weights plan the rest. With ``--gate-percentile`` the gate is then read off the branch's gains,
which are the ones it is compared with. Why a policy may want two: a fine-tune that makes the plans that need no
guidance more precise can cost the guided ones (docs/experiments.md, Meta-World).

``--surprise-percentile P`` (or ``--surprise-gate S`` by hand) adds the surprise gate (``studio.model.guidance``):
the policy's own weights also guide the demonstrations below the gate whose surprise — how badly the world model
predicts the demonstration's video even with it — reaches the P-th percentile of the training demonstrations'
surprises, read by the policy's own weights. ``--surprise-guidance G`` plans those at their own scale: they come from
other weights than the gate's (the shipped Meta-World policy guides them at 3, its gate's at 5).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from studio.model.run_files import atomic_save, read_torch_file

#: Training-only entries a policy file does not carry.
TRAINING_ONLY = ("optimizer", "scheduler")


def _weights(state: dict[str, torch.Tensor], half: bool) -> dict[str, torch.Tensor]:
    return {k: v.half() if half and v.is_floating_point() else v for k, v in state.items()}


def export_policy(
    checkpoint: str | Path,
    out: str | Path,
    *,
    decoder: str | Path | None = None,
    half: bool = True,
    guidance: float | None = None,
    guidance_gate: float | None = None,
    guided_from: str | Path | None = None,
    surprise_gate: float | None = None,
    surprise_guidance: float | None = None,
) -> dict[str, int]:
    """Write the policy (and decoder) files; returns their sizes in bytes. ``guidance`` and ``guidance_gate``
    set the policy's demonstration guidance and its gate, ``surprise_gate`` its surprise gate and
    ``surprise_guidance`` that gate's scale (``ModelConfig``; None keeps the checkpoint's);
    ``guided_from`` the checkpoint of its guided branch (module docstring)."""
    from studio.model.checkpoint import (
        GUIDED_WEIGHTS,
        check_guided_branch,
        guided_model_from_checkpoint,
        load_checkpoint,
        model_from_checkpoint,
    )
    from studio.model.config import RunConfig
    from studio.model.train_decoder import DECODER_FORMAT

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    ckpt: dict[str, Any] = load_checkpoint(checkpoint)
    policy = {k: v for k, v in ckpt.items() if k not in TRAINING_ONLY}
    policy["model"] = _weights(ckpt["model"], half)
    policy["exported_from"] = str(checkpoint)
    overrides = [
        f"model.{k}={v}"
        for k, v in (
            ("guidance", guidance),
            ("guidance_gate", guidance_gate),
            ("surprise_gate", surprise_gate),
            ("surprise_guidance", surprise_guidance),
        )
        if v is not None
    ]
    if overrides:
        run = RunConfig.from_dict(ckpt["config"]).with_overrides(overrides)
        if run.model.guidance != 1.0 and run.train.demo_dropout == 0.0:
            raise ValueError(
                f"{checkpoint} was trained without train.demo_dropout: it has never planned from the null "
                "demonstration, so guidance would extrapolate from an untrained plan"
            )
        if run.model.guidance_gate > 0.0 and run.model.guidance == 1.0:
            raise ValueError("a guidance gate without guidance does nothing: give --guidance too")
        if run.model.surprise_gate > 0.0 and run.model.guidance == 1.0:
            raise ValueError("a surprise gate without guidance does nothing: give --guidance too")
        policy["config"] = run.to_dict()
    if guided_from is not None:
        branch = load_checkpoint(guided_from)
        if branch.get(GUIDED_WEIGHTS) is not None:
            raise ValueError(
                f"{guided_from} has a guided branch of its own: name the checkpoint it came from"
            )
        if RunConfig.from_dict(branch["config"]).train.demo_dropout == 0.0:
            raise ValueError(
                f"{guided_from} was trained without train.demo_dropout: it has never planned from the null "
                "demonstration, so its guided plans would extrapolate from an untrained plan"
            )
        # the full-precision weights: the branch's encoder is compared before either is rounded to float16
        check_guided_branch(
            model_from_checkpoint({**ckpt, "config": policy["config"]}), model_from_checkpoint(branch)
        )
        policy[GUIDED_WEIGHTS] = _weights(
            {k: v for k, v in branch["model"].items() if not k.startswith("encoder.")}, half
        )
        policy["guided_from"] = str(guided_from)
    elif policy.get(GUIDED_WEIGHTS) is not None:
        # a policy file's branch, carried: its new settings must keep it
        branch_model = guided_model_from_checkpoint(policy)
        assert branch_model is not None
        check_guided_branch(model_from_checkpoint(policy), branch_model)
    atomic_save(policy, out)
    sizes = {"policy_bytes": out.stat().st_size}
    if decoder is not None:
        dec = read_torch_file(decoder)
        if not isinstance(dec, dict) or dec.get("format") != DECODER_FORMAT:
            raise ValueError(f"{decoder} is not a latent-decoder checkpoint (format {DECODER_FORMAT})")
        small = {k: v for k, v in dec.items() if k not in TRAINING_ONLY}
        small["decoder"] = _weights(dec["decoder"], half)
        dec_out = out.with_name(f"{out.stem}.decoder.pt")
        atomic_save(small, dec_out)
        sizes["decoder_bytes"] = dec_out.stat().st_size
    return sizes


def gate_from_training_demonstrations(
    checkpoint: str | Path, data_dir: str | Path, percentile: float
) -> tuple[float, int]:
    """The ``percentile``-th percentile of the demonstration gains of the stored expert demonstrations of the
    checkpoint's training tasks, and how many there were."""
    return _training_percentile(checkpoint, data_dir, percentile, "gain")


def surprise_gate_from_training_demonstrations(
    checkpoint: str | Path, data_dir: str | Path, percentile: float
) -> tuple[float, int]:
    """The ``percentile``-th percentile of the surprises (``guidance.demonstration_surprise``) of the stored expert
    demonstrations of the checkpoint's training tasks, read by its own weights, and how many there were."""
    return _training_percentile(checkpoint, data_dir, percentile, "surprise")


def _training_percentile(
    checkpoint: str | Path, data_dir: str | Path, percentile: float, measure: Literal["gain", "surprise"]
) -> tuple[float, int]:
    from studio.data.store import EpisodeStore
    from studio.model.planner import Planner

    if not 0.0 < percentile <= 100.0:
        raise ValueError(f"the {measure} gate percentile must be in (0, 100], got {percentile}")
    planner = Planner.load(checkpoint)
    if planner.model.world_model is None:
        raise ValueError(
            f"{checkpoint} has no world model: the demonstration {measure} is read from its predictions"
        )
    if not planner.tasks:
        raise ValueError(f"{checkpoint} does not name its training tasks")
    read = planner.demonstration_gain if measure == "gain" else planner.demonstration_surprise
    with EpisodeStore(data_dir) as store:
        demos = [m.id for m in store.episodes(role="expert", tasks=sorted(set(planner.tasks)))]
        if not demos:
            raise ValueError(f"no expert demonstration of {checkpoint}'s training tasks in {data_dir}")
        values = [read(store.load_frames(d)) for d in demos]
    return float(np.percentile(values, percentile)), len(values)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("checkpoint", help="training checkpoint (RUN_DIR/best.pt or last.pt)")
    parser.add_argument("out", help="policy file to write, e.g. studio/policies/pick_place.pt")
    parser.add_argument("--decoder", help="the model's latent decoder checkpoint (DECODER_DIR/best.pt)")
    parser.add_argument("--fp32", action="store_true", help="keep float32 weights (twice the size)")
    parser.add_argument(
        "--guidance",
        type=float,
        help="plan with this demonstration guidance (ModelConfig.guidance; for models trained with "
        "train.demo_dropout; default: the checkpoint's)",
    )
    parser.add_argument(
        "--guidance-gate",
        type=float,
        help="guide only demonstrations whose gain (how much better the world model predicts the demonstration "
        "with it than from its scene alone) reaches this (ModelConfig.guidance_gate; default: the checkpoint's)",
    )
    parser.add_argument(
        "--gate-percentile",
        type=float,
        help="set the gate to this percentile of the gains of the training tasks' stored demonstrations "
        "(needs --data; instead of --guidance-gate)",
    )
    parser.add_argument("--data", help="dataset root whose demonstrations --gate-percentile reads")
    parser.add_argument(
        "--guided-from",
        help="a checkpoint of the same network and encoder whose other weights plan (guided) the demonstrations "
        "that reach the gate, and compute their gains; the policy's own weights plan the rest",
    )
    parser.add_argument(
        "--surprise-gate",
        type=float,
        help="also guide, with the policy's own weights, demonstrations whose surprise (how badly the world model "
        "predicts the demonstration even with it) reaches this (ModelConfig.surprise_gate; 0: off)",
    )
    parser.add_argument(
        "--surprise-percentile",
        type=float,
        help="set the surprise gate to this percentile of the surprises of the training tasks' stored "
        "demonstrations, read by the policy's own weights (needs --data; instead of --surprise-gate)",
    )
    parser.add_argument(
        "--surprise-guidance",
        type=float,
        help="the guidance of the plans the surprise gate guides (ModelConfig.surprise_guidance; 0: --guidance's)",
    )


def run(args: argparse.Namespace) -> int:
    try:
        if args.gate_percentile is not None:
            if args.guidance_gate is not None or not args.data:
                raise ValueError("--gate-percentile needs --data and replaces --guidance-gate")
            args.guidance_gate, n = gate_from_training_demonstrations(
                args.guided_from or args.checkpoint, args.data, args.gate_percentile
            )
            print(
                f"guidance gate {args.guidance_gate:.4f}: the {args.gate_percentile:g}th percentile of {n} "
                "training demonstrations' gains"
            )
        if args.surprise_percentile is not None:
            if args.surprise_gate is not None or not args.data:
                raise ValueError("--surprise-percentile needs --data and replaces --surprise-gate")
            args.surprise_gate, n = surprise_gate_from_training_demonstrations(
                args.checkpoint, args.data, args.surprise_percentile
            )
            print(
                f"surprise gate {args.surprise_gate:.4f}: the {args.surprise_percentile:g}th percentile of {n} "
                "training demonstrations' surprises"
            )
        sizes = export_policy(
            args.checkpoint,
            args.out,
            decoder=args.decoder,
            half=not args.fp32,
            guidance=args.guidance,
            guidance_gate=args.guidance_gate,
            guided_from=args.guided_from,
            surprise_gate=args.surprise_gate,
            surprise_guidance=args.surprise_guidance,
        )
    except (FileNotFoundError, ValueError) as e:
        print(f"studio export-policy: {e}", file=sys.stderr)
        return 2
    print(" ".join(f"{k}={v / 1e6:.1f}MB" for k, v in sizes.items()), f"-> {args.out}")
    return 0
