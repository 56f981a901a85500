"""The `expert` and `plan` jobs on a real sim worker: a scripted demonstration stored, then planned from."""

from __future__ import annotations

import numpy as np
import pytest
from eval.tiny_checkpoint import write_tiny_checkpoint

from studio.backend.job_client import JobClient
from studio.backend.plan_job import expert_indices
from studio.data.store import EpisodeStore

from .conftest import wait_worker

pytestmark = pytest.mark.timeout(300)
TASK = "pick_place/bar->blue"


def test_expert_indices_keep_first_and_last():
    assert expert_indices(31, 10).tolist() == [0, 3, 7, 10, 13, 17, 20, 23, 27, 30]
    assert expert_indices(1, 3).tolist() == [0, 0, 0]
    with pytest.raises(ValueError, match="no frames"):
        expert_indices(0)


def _succeeded(client: JobClient, kind: str, spec: dict) -> dict:
    """Submit a job, wait for it to succeed, return its result."""
    job = client.submit(kind, spec)
    with client.watch(job.job) as w:
        final = w.wait(timeout=120)
        assert final.state == "succeeded", final.reason
        w.wait(lambda w: w.result is not None, 10)
    return w.result.result


def test_scripted_demo_then_oracle_plan(hub, workers, tmp_path):
    root = tmp_path / "data"
    workers.start("sim", "sim-p", "--data-dir", str(root), handlers=(), only_handlers=False)
    wait_worker(hub.directory, "sim-p")
    status = hub.directory.get("sim", "sim-p").status
    assert {"plan", "expert"} <= set(status.job_kinds), status.unavailable
    client = JobClient(hub.session)
    episode = _succeeded(client, "expert", {"task": TASK, "seed": 0})["episode_id"]
    with EpisodeStore(root) as store:
        meta = store.get(episode)
        assert meta.role == "expert" and meta.source == "scripted" and meta.task == TASK and meta.success

    result = _succeeded(
        client, "plan", {"checkpoint": "oracle", "expert_episode_id": episode, "task": TASK, "seed": 3}
    )
    plan = np.load(root / result["path"])
    assert plan["waypoints_world"].shape == (5, 4) and plan["agent_frame"].shape == (240, 320, 3)
    assert plan["expert_indices"][0] == 0 and plan["expert_indices"][-1] == meta.num_frames - 1
    assert "latent_images" not in plan and result["latent_images"] == 0
    assert result["gripper_closed"] == [bool(g > 0.5) for g in plan["waypoints_world"][:, 3]]
    assert result["guidance"] is None and "null_waypoints_world" not in plan

    # A guided policy's plan comes with its plan from the scene alone and says whether (and why) it was guided.
    guided = write_tiny_checkpoint(root / "runs" / "guided" / "best.pt", guidance=3.0)  # in the data dir
    guided_result = _succeeded(
        client, "plan", {"checkpoint": str(guided), "expert_episode_id": episode, "task": TASK, "seed": 3}
    )
    guided_plan = np.load(root / guided_result["path"])
    assert guided_plan["null_waypoints_world"].shape == guided_plan["waypoints_world"].shape == (5, 4)
    info = guided_result["guidance"]
    assert (info["scale"], info["gate"], info["guided"]) == (3.0, 0.0, True) and info["gain"] > 0
    # one the surprise gate guided reports that gate's own scale
    surprised = write_tiny_checkpoint(
        root / "runs" / "surprised" / "best.pt",
        guidance=3.0,
        planning=("model.guidance_gate=100", "model.surprise_gate=1e-6", "model.surprise_guidance=2"),
    )
    info = _succeeded(
        client, "plan", {"checkpoint": str(surprised), "expert_episode_id": episode, "task": TASK, "seed": 3}
    )["guidance"]
    assert (info["scale"], info["guided"], info["surprise_gate"]) == (2.0, True, 1e-6) and info[
        "surprise"
    ] > 0

    bad = client.submit(
        "plan",
        {"checkpoint": str(root / "missing.pt"), "expert_episode_id": episode, "task": TASK, "seed": 3},
    )
    with client.watch(
        bad.job
    ) as w:  # the worker's first torch import happens here: cold, it can take a while
        final = w.wait(timeout=120)
    assert final.state == "failed" and "does not exist" in final.reason

    # The rollout of the same spec starts with that very plan, paced at real time for viewers, and
    # announces every plan's waypoints in its progress stream.
    import time

    from studio.backend import keys

    planned: list = []
    poses: list = []
    job = client.submit(
        "rollout",
        {
            "checkpoint": "oracle",
            "expert_episode_id": episode,
            "task": TASK,
            "seed": 3,
            "speed": 1.0,
            "checkpoint_id": "oracle-ceiling",
        },
    )
    sub = hub.session.declare_subscriber(keys.job_key(job.job, "poses"), lambda s: poses.append(s))
    t0 = time.monotonic()
    try:
        with client.watch(
            job.job, on_progress=lambda p: planned.append(p) if "wp0_x" in p.metrics else None
        ) as w:
            final = w.wait(timeout=120)
            assert final.state == "succeeded", final.reason
            w.wait(lambda w: w.result is not None, 10)
    finally:
        sub.undeclare()
    wall = time.monotonic() - t0
    assert planned and planned[0].message == "planned (1)"
    first = np.array([[planned[0].metrics[f"wp{i}_{c}"] for c in "xyzg"] for i in range(5)])
    np.testing.assert_allclose(first, plan["waypoints_world"], atol=1e-9)
    with EpisodeStore(root) as store:
        (row,) = store.catalog.rollouts(task=TASK)
        sim_seconds = row.num_steps * store.get(row.episode_id).control_dt
    # Paced at real time: it takes at least the simulated time, and poses go out at 25 Hz of simulated time
    # (every second 20 ms control tick) however busy the machine is.
    assert wall >= 0.9 * sim_seconds and len(poses) >= 20 * sim_seconds
    assert row.checkpoint_id is None and row.extra["checkpoint"] == "oracle"


def test_a_sim_worker_survives_loading_the_model_after_rendering(hub, workers):
    """Importing triton after Mesa's EGL is up segfaults; sim workers import it first (studio.sim.rendering.preload_llvm_users)."""
    workers.start("sim", "sim-llvm", handlers=("rtm=render_then_model:run",))
    wait_worker(hub.directory, "sim-llvm")
    client = JobClient(hub.session)
    job = client.submit("rtm", {}, worker_kind="sim")
    with client.watch(job.job) as w:
        final = w.wait(timeout=120)
        assert final.state == "succeeded", final.reason
        w.wait(lambda w: w.result is not None, 10)
    assert w.result.result["mean"] > 0
