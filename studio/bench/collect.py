"""``studio bench collect``: scripted collection throughput and the training data loader's sample rate.

Collection is measured end to end, as a user runs it (worker start-up included): one episode per task
of the scene's training split for each robot (Sawyer experts, Panda agents), once with one worker and
once with two, into fresh temporary stores. ``projected_full_set_min`` extrapolates the faster rate to
the full pick-and-place training set (14 tasks × 100 episodes × 2 robots). The data loader is then
measured alone (no model): a :class:`~studio.data.training_view.PairDataset` over the collected episodes
behind a torch ``DataLoader``, in samples per second after its first batch (the one-off frame cache
build is reported separately as ``cache_build_s``).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

from studio.data.collect import CollectConfig, collect
from studio.data.splits import resolve_tasks

FULL_SET_EPISODES = 14 * 100 * 2


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", default="pick_place")
    parser.add_argument("--episodes-per-task", type=int, default=1, help="per robot and worker setting")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="worker counts to measure")
    parser.add_argument("--image-size", type=int, nargs=2, default=(240, 320), metavar=("H", "W"))
    parser.add_argument("--train-size", type=int, nargs=2, default=(240, 320), metavar=("H", "W"))
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--loader-workers", type=int, default=2)
    parser.add_argument("--loader-batches", type=int, default=20, help="timed batches after the first")
    parser.add_argument("--seed", type=int, default=0)


def _collect_rate(root: str, args: argparse.Namespace, workers: int, tasks: list[str]) -> dict:
    made, seconds, failed = 0, 0.0, 0
    for robot in ("sawyer", "panda"):
        result = collect(
            CollectConfig(
                scene=args.scene,
                robot=robot,
                tasks=tasks,
                episodes=args.episodes_per_task,
                workers=workers,
                seed=args.seed,
                image_size=tuple(args.image_size),
                data_dir=root,
                progress=False,
            )
        )
        if result.errors:
            raise RuntimeError(f"collection failed: {result.errors[0]}")
        made += result.made
        seconds += result.seconds
        failed += result.failed_attempts
    return {
        "episodes": made,
        "seconds": round(seconds, 2),
        "episodes_per_min": round(60 * made / seconds, 1),
        "failed_attempts": failed,
    }


def _loader_rate(root: str, args: argparse.Namespace) -> dict:
    import torch

    from studio.data.training_view import PairDataset

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    dataset = PairDataset(
        root, split="train", scene=args.scene, image_size=tuple(args.train_size), seed=args.seed
    )
    cache_s = time.perf_counter() - t0
    loader: torch.utils.data.DataLoader = torch.utils.data.DataLoader(
        dataset,  # type: ignore[arg-type]  # a map-style dataset by protocol (__len__, __getitem__), not a subclass
        batch_size=args.batch_size,
        sampler=torch.utils.data.RandomSampler(dataset, replacement=True, num_samples=10**9),
        num_workers=args.loader_workers,
        persistent_workers=args.loader_workers > 0,
    )
    it = iter(loader)
    next(it)
    t0 = time.perf_counter()
    for _ in range(args.loader_batches):
        next(it)
    seconds = time.perf_counter() - t0
    del it
    return {
        "train_samples_per_s": round(args.loader_batches * args.batch_size / seconds, 1),
        "cache_build_s": round(cache_s, 2),
        "pairs": len(dataset),
        "loader_workers": args.loader_workers,
        "batch_size": args.batch_size,
        "train_size": list(args.train_size),
    }


def measure(args: argparse.Namespace) -> dict:
    tasks = resolve_tasks(args.scene, ["train"])
    out: dict = {
        "scene": args.scene,
        "tasks": len(tasks),
        "image_size": list(args.image_size),
        "cpu_count": os.cpu_count(),
    }
    with tempfile.TemporaryDirectory(prefix="studio-bench-collect-") as tmp:
        rates = {}
        for workers in args.workers:
            root = os.path.join(tmp, f"w{workers}")
            rates[workers] = _collect_rate(root, args, workers, tasks)
            out[f"workers_{workers}"] = rates[workers]
        out["episodes_per_min"] = {str(w): r["episodes_per_min"] for w, r in rates.items()}
        best = max(r["episodes_per_min"] for r in rates.values())
        out["projected_full_set_min"] = round(FULL_SET_EPISODES / best, 1)
        out.update(_loader_rate(os.path.join(tmp, f"w{args.workers[0]}"), args))
    return out
