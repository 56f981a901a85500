"""`studio bench sim`: physics, control-loop and rendering speed, and scripted-expert success.

Figures are measured on the machine it runs on (wall clock, single process):

* ``physics_steps_per_s`` / ``realtime_factor`` — raw ``mj_step`` with the Panda in ``pick_place``;
* ``control_hz`` — full control ticks per second (IK solve + physics substeps), Panda, moving target;
* ``render_fps_*`` — external camera RGB at two sizes and the wrist depth camera;
* ``expert_success`` — success rate of the scripted expert per robot and task over ``--seeds`` seeds.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", type=int, default=50, help="seeds per task and robot for expert_success")
    parser.add_argument("--scenes", default="pick_place,push", help="scenes for expert_success")
    parser.add_argument("--robots", default="panda,sawyer,hand", help="robots for expert_success")


def _rate(fn, min_seconds: float = 2.0) -> float:
    fn()  # warm-up
    n, start = 0, time.perf_counter()
    while time.perf_counter() - start < min_seconds:
        fn()
        n += 1
    return n / (time.perf_counter() - start)


def measure(args: argparse.Namespace) -> dict:
    import mujoco

    from studio.sim.env import SimEnv
    from studio.sim.experts import run_expert
    from studio.sim.tasks import list_tasks

    out: dict = {
        "machine": {
            "cpus": os.cpu_count(),
            "processor": platform.processor() or platform.machine(),
            "mujoco": mujoco.__version__,
            "gl": os.environ.get("MUJOCO_GL", ""),
        }
    }
    env = SimEnv("pick_place", "panda")
    env.reset("pick_place/cube->red", 0)
    m, d = env.model, env.data
    steps = 2000
    t0 = time.perf_counter()
    mujoco.mj_step(m, d, nstep=steps)
    sps = steps / (time.perf_counter() - t0)
    out["physics_steps_per_s"] = round(sps, 1)
    out["realtime_factor"] = round(sps * m.opt.timestep, 2)

    env.reset("pick_place/cube->red", 0)
    k = [0]

    def tick() -> None:
        k[0] += 1
        t = k[0] * env.control_dt
        env.step(np.array([0.1 * np.cos(t), 0.45 + 0.1 * np.sin(t), 0.2]), 0.0)

    out["control_hz"] = round(_rate(tick), 1)
    out["control_dt_s"] = env.control_dt
    out["render_fps_rgb_240x320"] = round(_rate(lambda: env.render(size=(240, 320))), 1)
    out["render_fps_rgb_96x128"] = round(_rate(lambda: env.render(size=(96, 128))), 1)
    out["render_fps_depth"] = round(_rate(lambda: env.render_depth("wrist")), 1)
    out["render_depth_size"] = list(env.depth_size)
    env.close()

    success: dict = {}
    t0 = time.perf_counter()
    episodes = 0
    for robot in args.robots.split(","):
        success[robot] = {}
        for scene in args.scenes.split(","):
            senv = SimEnv(scene, robot)
            for task in list_tasks(scene):
                ok = 0
                for seed in range(args.seeds):
                    senv.reset(task, seed)
                    ok += run_expert(senv)
                    episodes += 1
                success[robot][task] = round(ok / args.seeds, 3)
            senv.close()
    out["expert_success"] = success
    out["expert_success_min"] = min(v for r in success.values() for v in r.values()) if success else None
    out["expert_episodes"] = episodes
    out["expert_seconds_per_episode"] = round((time.perf_counter() - t0) / max(episodes, 1), 3)
    out["seeds"] = args.seeds
    return out
