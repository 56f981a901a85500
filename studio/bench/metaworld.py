"""``studio bench metaworld``: how fast the Meta-World scenes simulate, render and collect on this machine.

* ``ticks_per_s`` — control ticks of :meth:`MetaWorldEnv.step` (5 physics steps + the env's success
  computation each); ``reset_ms`` — one seeded reset (Meta-World's 50 hand-settling ticks included) and
  ``task_load_ms`` — building a task's env and model on top of that, once per task and worker;
* ``render_fps`` — external-camera frames per second at each ``--render-sizes`` entry;
* ``policy`` (with ``--policy-seeds N``) — the scripted policies' success rate and mean ticks to first
  success over N seeds per task, without rendering;
* ``collect`` — ``studio collect --scene metaworld`` end to end (worker start-up, rendering, video
  encoding, store) with one episode per task for each ``--workers`` setting, in episodes per minute,
  into throw-away stores; ``projected_min`` extrapolates the faster rate to ``--project`` demonstrations
  per task for all 50 tasks.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--tasks", nargs="+", default=["all"], help="'all', 'train', 'test' or task names")
    parser.add_argument("--image-size", type=int, nargs=2, default=(224, 224), metavar=("H", "W"))
    parser.add_argument(
        "--render-sizes", type=int, nargs="+", default=[224, 128, 112, 96], help="square render sizes to time"
    )
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="collection worker counts")
    parser.add_argument(
        "--policy-seeds", type=int, default=0, help="seeds per task for the policy success rate"
    )
    parser.add_argument("--project", type=int, nargs="+", default=[100, 20], help="demos per task to project")
    parser.add_argument("--no-collect", action="store_true", help="skip the end-to-end collection")
    parser.add_argument("--seed", type=int, default=0)


def _sim_rates(tasks: list[str], render_sizes: list[int]) -> dict:
    from studio.sim.metaworld_env import MetaWorldEnv

    env = MetaWorldEnv()
    try:
        loads, resets, ticks, tick_s = [], [], 0, 0.0
        for i, task in enumerate(tasks):
            t0 = time.perf_counter()
            env.reset(task, i)  # builds the task's Meta-World env and model
            t1 = time.perf_counter()
            env.reset(task, i + 1)
            loads.append(t1 - t0)
            resets.append(time.perf_counter() - t1)
            start = env.ee_pos.copy()
            t0 = time.perf_counter()
            for k in range(100):
                env.step(start + np.array([0.1 * np.sin(k / 15), 0.0, 0.05 * np.cos(k / 15)]), 0.0)
            tick_s += time.perf_counter() - t0
            ticks += 100
        env.reset(tasks[0], 0)
        fps = {}
        for size in render_sizes:
            env.render(size=(size, size))  # renderer creation outside the timing
            t0 = time.perf_counter()
            for _ in range(50):
                env.render(size=(size, size))
            fps[f"{size}x{size}"] = round(50 / (time.perf_counter() - t0), 1)
    finally:
        env.close()
    return {
        "ticks_per_s": round(ticks / tick_s, 1),
        "reset_ms": round(1000 * float(np.mean(resets)), 1),
        "task_load_ms": round(1000 * (float(np.mean(loads)) - float(np.mean(resets))), 1),
        "render_fps": fps,
    }


def _policy_rates(tasks: list[str], seeds: int) -> dict:
    from studio.sim.metaworld_env import MetaWorldEnv
    from studio.sim.metaworld_experts import run_expert

    env = MetaWorldEnv()
    per_task, t0 = {}, time.perf_counter()
    try:
        for task in tasks:
            firsts = []
            for s in range(seeds):
                env.reset(task, 10_000 + s)
                firsts.append(run_expert(env, after_success=0))
            ok = [f for f in firsts if f is not None]
            per_task[task] = {
                "success": round(len(ok) / seeds, 3),
                "mean_ticks": round(float(np.mean(ok)), 1) if ok else None,
            }
    finally:
        env.close()
    seconds = time.perf_counter() - t0
    rates = {t: float(v["success"] or 0.0) for t, v in per_task.items()}  # success is always a number
    ticks = [float(v["mean_ticks"]) for v in per_task.values() if v["mean_ticks"]]
    return {
        "seeds": seeds,
        "mean_success": round(float(np.mean(list(rates.values()))), 3),
        "below_100": {t: r for t, r in rates.items() if r < 1.0},
        "mean_ticks": round(float(np.mean(ticks)), 1),
        "episodes_per_min_unrecorded": round(60 * seeds * len(tasks) / seconds, 1),
        "per_task": per_task,
    }


def _collect_rate(tasks: list[str], args: argparse.Namespace, workers: int) -> dict:
    from studio.data.collect import CollectConfig, collect

    with tempfile.TemporaryDirectory(prefix="studio-bench-metaworld-") as root:
        result = collect(
            CollectConfig(
                scene="metaworld",
                robot="sawyer",
                tasks=tasks,
                episodes=1,
                workers=workers,
                seed=args.seed,
                image_size=tuple(args.image_size),
                data_dir=root,
                progress=False,
            )
        )
    if result.errors:
        raise RuntimeError(f"collection failed: {result.errors[0]}")
    return {
        "episodes": result.made,
        "seconds": round(result.seconds, 2),
        "episodes_per_min": round(result.episodes_per_min, 1),
        "failed_attempts": result.failed_attempts,
    }


def measure(args: argparse.Namespace) -> dict:
    from studio.data.splits import resolve_tasks

    tasks = resolve_tasks("metaworld", list(args.tasks))
    out: dict = {"tasks": len(tasks), "image_size": list(args.image_size), "cpu_count": os.cpu_count()}
    out.update(_sim_rates(tasks, list(args.render_sizes)))
    if args.policy_seeds > 0:
        out["policy"] = _policy_rates(tasks, args.policy_seeds)
    if not args.no_collect:
        rates = {w: _collect_rate(tasks, args, w) for w in args.workers}
        out["collect"] = {f"workers_{w}": r for w, r in rates.items()}
        best = max(r["episodes_per_min"] for r in rates.values())
        out["collect"]["projected_min"] = {f"{n}_per_task": round(50 * n / best, 1) for n in args.project}
    return out
