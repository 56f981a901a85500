"""Stores the browser tests start from, built as the studio's own code would have stored them."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

HELD_OUT = "pick_place/bar->blue"
TRAIN_TASKS = ("pick_place/cube->red", "pick_place/cube->green")


def training_episodes_and_a_failed_rollout(root: Path) -> Path:
    """A store at ``root`` with tiny synthetic training episodes (3 Sawyer demonstrations and 3 Panda agent
    episodes of each of ``TRAIN_TASKS``) and one failed rollout of ``HELD_OUT`` by a registered checkpoint
    ``fixture-run/best``, stored as a guided model's would be (predicted latent images, the null plan)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "data"))
    from data_fixtures import make_recording

    from studio.data.catalog import CheckpointRecord, RunRecord
    from studio.data.store import EpisodeStore
    from studio.eval.oracle import OraclePlanner
    from studio.eval.rollout import run_rollout, store_rollout
    from studio.sim.env import SimEnv

    with EpisodeStore(root) as store:
        seed = 0
        for task in TRAIN_TASKS:
            for robot, role in (("sawyer", "expert"), ("panda", "agent")):
                for _ in range(3):
                    store.add_episode(
                        make_recording(task=task, robot=robot, seed=seed), role=role, source="scripted"
                    )
                    seed += 1

        class Misaimed(OraclePlanner):
            """The oracle's plan shifted 12 cm sideways: reaches the wrong place, grasps nothing."""

            def plan(self, *args):
                plan = super().plan(*args)
                plan.waypoints_world = plan.waypoints_world + np.array([0.12, 0.0, 0.0, 0.0])
                return plan

        with SimEnv("pick_place", "panda", image_size=(120, 160)) as env:
            frames = np.zeros((10, 120, 160, 3), np.uint8)
            out = run_rollout(env, Misaimed(env), frames, HELD_OUT, 5, n_frames=20)
        assert not out.success
        # As a model's rollout would store it: predicted latent images with the plan, a registered checkpoint.
        rng = np.random.default_rng(0)
        out.plans[0].latent_images = rng.integers(0, 255, (5, 48, 64, 3), dtype=np.uint8)
        # ... and, as a guided policy's would, the plan from the null demonstration: here the unshifted one.
        out.plans[0].null_waypoints_world = out.plans[0].waypoints_world - np.array([0.12, 0.0, 0.0, 0.0])
        out.plans[0].guidance_gain, out.plans[0].guided = 1.6, True
        out.plans[0].guidance_surprise = 8.73  # as a policy with a surprise gate stores it
        out.plans[0].guidance_scale = 3.0  # the scale that made the plan
        with store.catalog.transaction():
            store.catalog.add_run(RunRecord(id="fixture-run", status="done"))
            store.catalog.add_checkpoint(
                CheckpointRecord(
                    id="fixture-run/best", run_id="fixture-run", step=1, path=str(root / "missing.pt")
                )
            )
        store_rollout(
            store,
            out,
            expert_episode_id=None,
            checkpoint_id="fixture-run/best",
            extra={"checkpoint": str(root / "missing.pt")},
        )
    return root
