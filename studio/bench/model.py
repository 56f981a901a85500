"""`studio bench model`: training throughput, planning latency and size of OSVI-WM for a preset.

Measured on random inputs with the real code paths: one training step = augmentation + mixup, forward with
world-model targets, both losses, backward, gradient clipping and an AdamW step (``train_*``); ``fwd_bwd_*`` is
forward + losses + backward only, the protocol of the reference study's figures; one plan = ``Planner.plan`` at
batch 1 (measured first, in a fresh process state) from uint8 frames at the model's resolution (cold: the expert video is encoded; ``replan_ms``: the same
demonstration again, whose context is reused). Defaults reproduce the reference study's CPU setting — batch 2,
N = 10, M = 6, fp32, 2 threads, random init — whose figures are reported alongside: the authors' model takes
7.8 s per forward+backward at 240×320 (0.26 samples/s) and 0.79 s at 96×128 (2.5 samples/s), and 1.3 s / 0.14 s
per plan. ``pairs_per_expert = 2`` additionally measures a batch whose two pairs share one demonstration, the
grouping the training loop uses. The median of ``--reps`` repetitions after ``--warmup`` is reported; the machine
load average is included because shared machines make these numbers noisy.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np
import torch

from studio.model.augment import augment_batch
from studio.model.batching import Batch
from studio.model.config import PRESETS, preset
from studio.model.osvi_wm import OSVIWM, count_parameters
from studio.model.planner import Planner
from studio.model.train import compute_losses

# The reference study's CPU anchors (2 vCPU, fp32, batch 2, N = 10, M = 6, random init), keyed by input size:
# forward+backward median and min over 5 repetitions and its CPU seconds, and the median of one plan.
REFERENCE = {
    (240, 320): {
        "fwd_bwd_s": 7.78,
        "fwd_bwd_s_min": 7.39,
        "fwd_bwd_cpu_s": 13.4,
        "train_samples_per_s": 0.26,
        "plan_latency_ms": 1300.0,
    },
    (96, 128): {
        "fwd_bwd_s": 0.79,
        "fwd_bwd_s_min": 0.62,
        "fwd_bwd_cpu_s": 1.5,
        "train_samples_per_s": 2.5,
        "plan_latency_ms": 140.0,
    },
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", choices=PRESETS, default="cpu", help="model/train preset (default: cpu)")
    parser.add_argument("--image-size", default=None, help="override the input size, e.g. 96x128")
    parser.add_argument(
        "--batch", type=int, default=2, help="pairs per training step (default 2, the reference's)"
    )
    parser.add_argument("--reps", type=int, default=5, help="timed repetitions (median reported)")
    parser.add_argument("--warmup", type=int, default=2, help="untimed repetitions first")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument("--precision", choices=("fp32", "bf16"), default="fp32")
    parser.add_argument("--device", default="cpu")


def _batch(b: int, u: int, n: int, m: int, size: tuple[int, int], g: torch.Generator) -> Batch:
    h, w = size
    f = 0.9 * w
    K = torch.tensor([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]], dtype=torch.float32)
    path = torch.rand(b, 50, 4, generator=g) * torch.tensor([0.4, 0.3, 0.3, 1.0]) + torch.tensor(
        [-0.2, -0.15, 0.9, 0]
    )
    return Batch(
        expert_frames=torch.randint(0, 256, (u, n, 3, h, w), generator=g, dtype=torch.uint8),
        agent_frames=torch.randint(0, 256, (b, m, 3, h, w), generator=g, dtype=torch.uint8),
        path=path,
        K=K.expand(b, 3, 3).clone(),
        T_world_cam=torch.eye(4).expand(b, 4, 4).clone(),
        expert_ids=torch.arange(b) * u // b,
        expert_tasks=torch.arange(u),
        agent_tasks=torch.arange(b) * u // b,
    )


def _time(fn, warmup: int, reps: int, cpu: list[float] | None = None) -> list[float]:
    """Wall-clock seconds of ``reps`` calls after ``warmup``; process CPU seconds appended to ``cpu``."""
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(reps):
        t, c = time.perf_counter(), time.process_time()
        fn()
        out.append(time.perf_counter() - t)
        if cpu is not None:
            cpu.append(time.process_time() - c)
    return out


def _forward_backward_times(model, run, batch, warmup, reps, device, cpu: list[float]) -> list[float]:
    """The reference study's protocol: forward (with world-model targets) + losses + backward only."""
    model.train()
    batch = batch.to(device)

    def step() -> None:
        loss, _ = compute_losses(model, model, batch, run, 0, 1000, None)
        loss.backward()
        model.zero_grad(set_to_none=True)

    return _time(step, warmup, reps, cpu)


def _train_step_times(model, run, batch, warmup, reps, device) -> list[float]:
    opt = torch.optim.AdamW(model.parameters(), lr=run.train.lr_max, fused=True)
    g = torch.Generator().manual_seed(0)
    model.train()

    def step() -> None:
        loss, _ = compute_losses(model, model, batch.to(device), run, 0, 1000, g)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), run.train.grad_clip)
        opt.step()

    return _time(step, warmup, reps)


def _step_profile(model, run, batch, warmup, reps, device) -> dict[str, float]:
    """Where one training step's time goes (median milliseconds of each part, measured on its own).

    ``encoder_fwd_bwd``: the encoder's forward and backward over the expert videos and the agents' first frames;
    ``targets_fwd``: encoding the future agent frames as world-model targets (no gradient); ``step_fwd_bwd``: the
    whole forward, losses and backward; ``rest_fwd_bwd``: what of it is neither (π, 𝒲, pooling, head, losses);
    ``augment``: the batch's augmentation; ``optimizer``: gradient clipping and the AdamW step."""
    model.train()
    batch = batch.to(device)
    cfg = run.train
    g = torch.Generator().manual_seed(0)
    u, n = batch.expert_frames.shape[:2]
    first = torch.cat(
        [batch.expert_frames.reshape(u * n, *batch.expert_frames.shape[2:]), batch.agent_frames[:, 0]]
    )
    target_idx = model.target_frame_indices() if model.world_model is not None else []
    future = batch.agent_frames[:, target_idx].flatten(0, 1) if target_idx else None
    trained = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(trained, lr=cfg.lr_max, fused=True)

    dtype = torch.bfloat16 if cfg.precision == "bf16" else None

    def autocast():  # the precision compute_losses runs the model in
        return torch.autocast(device_type=device.type, dtype=dtype, enabled=dtype is not None)

    def encoder() -> None:
        with autocast():
            states = model.encode(first)
        states.float().sum().backward()
        model.zero_grad(set_to_none=True)

    def targets() -> None:
        if future is not None:
            with torch.no_grad(), autocast():
                model.encode(future)

    def whole() -> None:
        loss, _ = compute_losses(model, model, batch, run, 0, 1000, None)
        loss.backward()

    def whole_then_clear() -> None:
        whole()
        model.zero_grad(set_to_none=True)

    def augment() -> None:
        augment_batch(
            batch.expert_frames,
            batch.agent_frames,
            batch.K,
            batch.expert_ids,
            batch.expert_tasks,
            batch.agent_tasks,
            cfg,
            g,
        )

    def optimizer() -> None:
        torch.nn.utils.clip_grad_norm_(trained, cfg.grad_clip)
        opt.step()

    def median_ms(fn) -> float:
        return 1e3 * statistics.median(_time(fn, warmup, reps))

    out = {
        "augment": median_ms(augment),
        "encoder_fwd_bwd": median_ms(encoder),
        "targets_fwd": median_ms(targets),
        "step_fwd_bwd": median_ms(whole_then_clear),
    }
    whole()  # gradients for the optimiser's step
    out["optimizer"] = median_ms(optimizer)
    model.zero_grad(set_to_none=True)
    out["rest_fwd_bwd"] = max(0.0, out["step_fwd_bwd"] - out["encoder_fwd_bwd"] - out["targets_fwd"])
    return {k: round(v, 1) for k, v in out.items()}


def measure(args: argparse.Namespace) -> dict:
    torch.set_num_threads(args.threads)
    overrides = [f"train.precision={args.precision}"]
    if args.image_size:
        h, w = (int(v) for v in args.image_size.lower().split("x"))
        overrides.append(f"model.image_size=[{h}, {w}]")
    run = preset(args.config).with_overrides(overrides)
    mc = run.model
    device = torch.device(args.device)
    torch.manual_seed(0)
    model = OSVIWM(mc).to(device)
    g = torch.Generator().manual_seed(0)
    n, m = mc.n_expert_frames, mc.n_agent_frames
    size = (int(mc.image_size[0]), int(mc.image_size[1]))
    planner = Planner(model, device, args.precision)
    expert = np.random.default_rng(0).integers(0, 256, (n, *size, 3), dtype=np.uint8)
    K = np.array([[0.9 * size[1], 0, size[1] / 2], [0, 0.9 * size[1], size[0] / 2], [0, 0, 1]])

    def cold_plan() -> None:
        planner.clear_cache()
        planner.plan(expert, expert[0], K, np.eye(4))

    plan_times = _time(cold_plan, args.warmup, args.reps)
    planner.plan(expert, expert[0], K, np.eye(4))
    replan_times = _time(lambda: planner.plan(expert, expert[-1], K, np.eye(4)), 1, args.reps)

    batch = _batch(args.batch, args.batch, n, m, size, g)
    fb_cpu: list[float] = []
    fb_times = _forward_backward_times(model, run, batch, args.warmup, args.reps, device, fb_cpu)
    train_times = _train_step_times(model, run, batch, args.warmup, args.reps, device)
    shared_u = max(1, args.batch // 2)
    shared_times = _train_step_times(
        model, run, _batch(args.batch, shared_u, n, m, size, g), args.warmup, args.reps, device
    )

    profile = _step_profile(model, run, batch, args.warmup, args.reps, device)
    step_s = statistics.median(train_times)
    result = {
        "target": "model",
        "config": args.config,
        "image_size": list(size),
        "state_shape": list(model.state_shape),
        "params": count_parameters(model),
        "batch": args.batch,
        "n_expert": n,
        "n_agent": m,
        "threads": args.threads,
        "precision": args.precision,
        "train_step_s": round(step_s, 4),
        "train_step_s_min": round(min(train_times), 4),
        "train_samples_per_s": round(args.batch / step_s, 3),
        "train_samples_per_s_shared_expert": round(args.batch / statistics.median(shared_times), 3),
        "train_step_shared_expert_s_min": round(min(shared_times), 4),
        "fwd_bwd_s": round(statistics.median(fb_times), 4),
        "fwd_bwd_s_min": round(min(fb_times), 4),
        "fwd_bwd_cpu_s": round(statistics.median(fb_cpu), 3),
        "fwd_bwd_samples_per_s": round(args.batch / statistics.median(fb_times), 3),
        "plan_latency_ms": round(1e3 * statistics.median(plan_times), 2),
        "plan_latency_ms_min": round(1e3 * min(plan_times), 2),
        "replan_ms": round(1e3 * statistics.median(replan_times), 2),
        "step_profile_ms": profile,
        "load_average": [round(v, 2) for v in os.getloadavg()],
        "torch": torch.__version__,
    }
    ref = REFERENCE.get(size)
    if ref is not None:
        result["reference"] = ref
        # Shared machines are noisy: the min/min ratio is the steadier comparison of intrinsic cost.
        result["fwd_bwd_speedup_vs_reference"] = round(ref["fwd_bwd_s"] / result["fwd_bwd_s"], 2)
        result["fwd_bwd_speedup_vs_reference_min"] = round(ref["fwd_bwd_s_min"] / result["fwd_bwd_s_min"], 2)
        # CPU seconds of work per forward+backward hardly depend on what else runs on the machine.
        result["fwd_bwd_cpu_speedup_vs_reference"] = round(ref["fwd_bwd_cpu_s"] / result["fwd_bwd_cpu_s"], 2)
        result["train_step_speedup_vs_reference"] = round(ref["fwd_bwd_s"] / result["train_step_s"], 2)
        result["plan_speedup_vs_reference"] = round(ref["plan_latency_ms"] / result["plan_latency_ms"], 2)
    return result
