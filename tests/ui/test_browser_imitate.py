"""The Train, Imitate, Compare and Workers tabs in a real browser (Debian's headless Chromium driven by Playwright):
train from the page, plan and execute held-out tasks with the oracle, a trained checkpoint (decoded latent
images) and the shipped policies (pick-and-place, push, a filmed hand demonstration imitated by the Panda), run
two checkpoints side by side, list the workers. The store starts with tiny synthetic training episodes
(``browser_stores``).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import browser_support as ui
from browser_stores import HELD_OUT, TRAIN_TASKS, training_episodes_and_a_failed_rollout
from tiny_network import TINY_BATCHED

PUSH_HELD_OUT = "push/blue-backward"

# Tests that share the app are slow one by one (marked); the fast ones stay in `-m "not slow"` runs.
pytestmark = [pytest.mark.browser, pytest.mark.timeout(420)]


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return training_episodes_and_a_failed_rollout(tmp_path_factory.mktemp("studio") / "data")


@pytest.mark.slow
def test_training_job_started_from_the_ui_shows_progress(studio, page, shots):
    tab = ui.tab(studio)
    train = tab.train
    ui.open_tab(page, "Train", "training pair")
    for task, box in train._task_boxes.items():
        box.value = task in TRAIN_TASKS
    train.overrides.value = "; ".join(TINY_BATCHED)
    train.steps.value = 4
    page.get_by_text("Start: 4 steps").filter(visible=True).first.wait_for(timeout=60_000)
    ui.wait(
        lambda: not train.start.disabled,
        60,
        "Start to be enabled",
        lambda: f"pairs {train.pairs.content!r}; plan {train.plan.content!r}; actions {tab.actions}",
    )
    ui.click(page.get_by_role("button", name="Start training"))
    page.get_by_text("step 4/4").filter(visible=True).first.wait_for(timeout=240_000)
    page.get_by_text("ended: finished").filter(visible=True).first.wait_for(timeout=60_000)
    short = train.job_id.removeprefix("train-")
    ui.wait(lambda: f"`{short}`" in train.runs_table.content, 30, "the run's row in the runs table")
    ui.drawn(page)
    ui.shot(page, shots / "train.png")
    ui.shot(page, shots / "train-curves.png", scroll_to="Learning rate")
    job = train.job_id
    run = studio.data_dir / "runs" / job
    assert (run / "last.pt").is_file() and json.loads((run / "spec.json").read_text())["steps"] == 4
    assert sorted(json.loads((run / "split.json").read_text())["train"]) == sorted(TRAIN_TASKS)
    assert any(c.run_id == job for c in studio.runs.checkpoints())
    ui.wait(
        lambda: [r for r in studio.store.catalog.runs() if r.id == job and r.status == "done"],
        10,
        "the run row",
    )
    assert train.loss_plot.data[0][-1] == 4 and np.isfinite(train.loss_plot.data[2]).all()


@pytest.mark.slow
def test_plan_and_execute_on_a_held_out_task(studio, page, shots):
    tab = ui.tab(studio)
    im = tab.imitate
    studio.runs.set_active("oracle", "pick_place")  # the execution ceiling, clearly labelled as such
    ui.open_tab(page, "Imitate", "Choose a")
    label = HELD_OUT + " (held-out)"
    assert label in im.task.options
    im.task.value = label
    page.get_by_text("oracle — execution ceiling").filter(visible=True).first.wait_for(timeout=60_000)
    ui.click(page.get_by_role("button", name="Make a scripted demonstration"))
    page.get_by_text("stored and selected").filter(visible=True).first.wait_for(timeout=90_000)
    assert "scripted" in im.demo.value
    im.seed.value = 2
    ui.click(page.get_by_role("button", name="Plan", exact=True))
    page.get_by_text("Planned in").filter(visible=True).first.wait_for(timeout=90_000)
    assert im.plan_wps.shape == (5, 4)
    overlay = tab.view._overlays["plan"]
    assert len(overlay) == 11, "a spline, 5 waypoint spheres and their labels"
    ui.shot(page, shots / "imitate-plan.png")
    im.speed.value = "0.5×"  # slow motion, so that the screenshot catches it mid-way
    ui.click(page.get_by_role("button", name="Execute", exact=True))
    ui.wait(lambda: im.rollout is not None and im.rollout.poses_seen > 10, 90, "live rollout poses")
    ui.wait(
        lambda: im.rollout.progress is not None and "waypoint" in im.rollout.progress.message,
        60,
        "a waypoint",
    )
    ui.shot(page, shots / "imitate-executing.png")
    page.get_by_text("✔ Success").or_(page.get_by_text("✘ Failed at")).filter(visible=True).first.wait_for(
        timeout=120_000
    )
    ui.shot(page, shots / "imitate-outcome.png")
    result = ui.wait(lambda: im.rollout.result, 30, "the rollout's result")
    assert result["success"] is True, result  # the oracle's plan on a held-out task succeeds
    assert im.rollout.plans and np.allclose(im.rollout.plans[0], im.plan_wps), (
        "execution follows the shown plan"
    )
    row = [r for r in studio.store.catalog.rollouts(task=HELD_OUT) if r.id == result["rollout_id"]]
    assert row and row[0].checkpoint_id is None


@pytest.mark.slow
def test_trained_checkpoint_plans_with_decoded_latent_images(studio, page, shots):
    """The run trained from the UI, with a latent decoder, as the active policy: Plan shows decoded latents."""
    tab = ui.tab(studio)
    im = tab.imitate
    run = studio.data_dir / "runs" / tab.train.job_id
    # The latent decoder, trained as a user would (its own process: this one never imports torch).
    cmd = [
        sys.executable,
        "-m",
        "studio.cli",
        "train-decoder",
        "--model",
        str(run / "last.pt"),
        "--data",
        str(studio.data_dir),
        "--out",
        str(run / "decoder"),
        "--steps",
        "2",
        "--batch-size",
        "2",
        "--scene",
        str(run / "split.json"),
        "--no-progress",
    ]
    done = subprocess.run(
        cmd, capture_output=True, text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"}
    )
    assert done.returncode == 0, done.stderr[-2000:]
    studio.runs.set_active(f"{run.name}/last")
    ui.open_tab(page, "Imitate", "Choose a")
    ui.wait(lambda: f"{run.name}/last" in im.policy.content, 20, "the trained policy to be active")
    ui.click(page.get_by_role("button", name="Plan", exact=True))
    ui.wait(lambda: im.latent_strip.visible, 120, "the decoded latent trajectory")
    ui.shot(page, shots / "imitate-plan-trained.png", scroll_to="Predicted latent trajectory")
    assert im.plan_job.result["latent_images"] > 0 and im.plan_wps.shape == (5, 4)
    assert np.isfinite(im.plan_wps).all()


@pytest.mark.slow
def test_compare_tab_runs_two_checkpoints_and_plays_a_differing_seed_side_by_side(studio, page, shots):
    """The Compare tab: the oracle (A) against a tiny untrained checkpoint (B) on two seeds of a training task —
    every episode differs (the untrained model reaches nothing) — then one seed opened: one timeline moves both
    camera frames and the scene, the shorter rollout holding its last frame."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    tab = ui.tab(studio)
    cmp = tab.compare
    run = studio.data_dir / "runs" / "tiny-run"
    tiny = Path(__file__).resolve().parents[1] / "eval" / "tiny_checkpoint.py"
    # Its own process (this one never imports torch); trained on pick-and-place tasks, as Compare offers only a
    # checkpoint of the chosen scene.
    code = (
        "import sys, torch; sys.path.insert(0, sys.argv[1]); from tiny_checkpoint import write_tiny_checkpoint; "
        "p = write_tiny_checkpoint(sys.argv[2]); c = torch.load(p, weights_only=True); c['tasks'] = sys.argv[3:]; "
        "torch.save(c, p)"
    )
    done = subprocess.run(
        [sys.executable, "-c", code, str(tiny.parent), str(run / "best.pt"), *TRAIN_TASKS],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    ui.open_tab(page, "Compare", "Run two checkpoints on the")
    ui.wait(lambda: "tiny-run/best" in cmp.ck_b.options, 20, "the new run among the checkpoints")
    cmp.ck_a.value, cmp.ck_b.value = "oracle", "tiny-run/best"
    cmp.tasks.value = TRAIN_TASKS[0]
    cmp.episodes.value = 2
    cmp.seed.value = 1
    ui.click(page.get_by_role("button", name="Start", exact=True))
    job = ui.wait(lambda: cmp.job, 30, "the compare job")
    ui.wait(
        lambda: job.progress is not None and "episode 1 of 2" in job.progress.message,
        180,
        "episode 1 of 2",
        lambda: f"status {cmp.status.content!r}, job {job.state} {job.status and job.status.reason}",
    )
    with contextlib.suppress(PlaywrightTimeout):  # the page may already show the end: a screenshot is no test
        page.get_by_text(re.compile(r"episode \d of 2")).filter(visible=True).first.wait_for(timeout=20_000)
    ui.shot(page, shots / "compare-running.png")
    ui.wait(
        lambda: "finished:" in cmp.status.content,
        180,
        "the comparison to finish",
        lambda: f"status {cmp.status.content!r}, job {job.state} {job.status and job.status.reason}",
    )
    page.get_by_text("episodes in").filter(visible=True).first.wait_for(timeout=60_000)
    assert len(cmp.rows) == 2 and all(r.difference == "A only" for r in cmp.rows), cmp.table.content
    assert (
        "**A 100.0%** (2 / 2, oracle) · **B 0.0%** (0 / 2, tiny-run/best) · A only 2 · B only 0"
        in cmp.totals.content
    )
    assert cmp.table.content.count("**A only**") == 2 and cmp.pick.value.startswith("1. cube->red #")
    assert "| A | B | difference |" in cmp.table.content and "| cube->red | " in cmp.table.content
    catalog = studio.store.catalog
    a = {(r.task, r.seed, r.expert_episode_id) for r in catalog.rollouts(eval_id=job.result["eval_ids"][0])}
    b = {(r.task, r.seed, r.expert_episode_id) for r in catalog.rollouts(eval_id=job.result["eval_ids"][1])}
    assert a == b and len(a) == 2, "A and B rolled out the identical episodes"
    ui.shot(page, shots / "compare-table.png", scroll_to="Per-seed table")

    ui.click_and_see(page, page.get_by_role("button", name="Open side by side"), "Paths: A blue")
    assert tab.mode == "compare" and {"path", "path_b", "ee_a", "ee_b"} <= set(tab.view._overlays)
    sa, sb = cmp.sides
    steps = max(sa.steps, sb.steps)
    assert sa.steps != sb.steps and int(cmp.timeline.slider.max) == steps - 1, "the timeline spans the longer"
    first = np.asarray(cmp.image.image).copy()
    half = first.shape[1] // 2
    mid = min(sa.steps, sb.steps) * 2 // 3
    cmp.timeline.slider.value = mid
    ui.wait(lambda: f"Step {mid} of {steps - 1}." in cmp.step_info.content, 30, "the shared timeline to move")
    moved = np.asarray(cmp.image.image)
    body = slice(20, None)  # below the labels drawn on the frames
    assert not np.array_equal(first[body, :half], moved[body, :half]), "A's camera frame follows the timeline"
    assert not np.array_equal(first[body, half:], moved[body, half:]), "B's camera frame follows the timeline"
    page.get_by_text(f"Step {mid} of {steps - 1}.").filter(visible=True).first.wait_for(timeout=60_000)
    ui.shot(page, shots / "compare-playback.png", scroll_to="The scene shows")
    cmp.timeline.slider.value = steps - 1  # past the shorter rollout's end: it holds its last frame
    shorter = sa if sa.steps < sb.steps else sb
    ui.wait(lambda: f"Step {steps - 1} of" in cmp.step_info.content, 30, "the timeline's end")
    held = shorter.describe(steps - 1)
    assert "holding its last frame" in held and held in cmp.step_info.content
    cmp.shows.value = "B"
    ui.wait(lambda: "The scene shows B." in cmp.step_info.content, 10, "the scene to show B")
    page.get_by_text("The scene shows B.").filter(visible=True).first.wait_for(timeout=60_000)
    ui.shot(page, shots / "compare-end-b.png", scroll_to="The scene shows")
    # The same rows again from the catalog: the comparison's two stored evaluations, compared without running.
    ran = [r.to_dict() for r in cmp.rows]
    ui.click(page.get_by_text("Stored evaluations"))
    ui.wait(
        lambda: (
            cmp.eval_a.value.startswith(job.result["eval_ids"][0] + " ")
            and cmp.eval_b.value.startswith(job.result["eval_ids"][1] + " ")
        ),
        20,
        "the comparison's evaluations",
    )
    cmp.rows = []
    ui.click_until(
        page.get_by_role("button", name="Compare stored rollouts"),
        lambda: "2 shared episodes" in cmp.status.content,
        "the stored evaluations compared",
        lambda: f"status {cmp.status.content!r}; actions {tab.actions}",
    )
    page.get_by_text("2 shared episodes").filter(visible=True).first.wait_for(timeout=60_000)
    assert [r.to_dict() for r in cmp.rows] == ran


def test_workers_panel_lists_the_embedded_workers(studio, page, shots):
    tab = ui.tab(studio)
    ui.open_tab(page, "Workers", "workers on the bus")
    for worker in studio.embedded.workers:
        page.get_by_text(worker).filter(visible=True).first.wait_for(timeout=60_000)
    text = tab.workers.describe()
    assert "| sim |" in text and "| train |" in text and "rollout" in text
    (sim,) = studio.hub.directory.workers("sim")
    assert sim.status.sessions == 1, "this tab's teleop session runs on the embedded sim worker"
    ui.shot(page, shots / "workers.png")


@pytest.mark.slow
def test_plan_and_execute_with_the_shipped_policy(studio, page, shots):
    """The policy shipped with the studio, on a held-out task: Plan shows waypoints and decoded latent images,
    Execute finishes with an outcome recorded against it."""
    tab = ui.tab(studio)
    im = tab.imitate
    policy = studio.runs.shipped_for("pick_place")
    assert policy is not None, "no shipped pick-and-place policy"
    studio.runs.set_active(policy.id)
    ui.open_tab(page, "Imitate", "Choose a")
    im.task.value = HELD_OUT + " (held-out)"
    ui.wait(lambda: policy.id in im.policy.content, 20, "the shipped policy to be active")
    assert policy.summary and policy.summary in im.policy_details.content, (
        "its measured results are one fold away"
    )
    ui.click(page.get_by_role("button", name="Make a scripted demonstration"))
    page.get_by_text("stored and selected").filter(visible=True).first.wait_for(timeout=90_000)
    before = im.plan_job
    ui.click(page.get_by_role("button", name="Plan", exact=True))
    job = ui.wait(lambda: im.plan_job is not before and im.plan_job, 30, "a new plan job")
    assert job.spec["checkpoint"] == policy.path
    ui.wait(lambda: job.result is not None and im.latent_strip.visible, 120, "the decoded latent trajectory")
    page.get_by_text("Planned in").filter(visible=True).first.wait_for(timeout=60_000)
    assert job.result["latent_images"] == 5  # r_2 … r_6 of the shipped policy, decoded
    assert im.plan_wps.shape == (5, 4) and np.isfinite(im.plan_wps).all()
    ui.drawn(page)
    ui.shot(page, shots / "imitate-plan-shipped.png", scroll_to="Predicted latent trajectory")
    im.speed.value = "as fast as possible"
    ui.click(page.get_by_role("button", name="Execute", exact=True))
    page.get_by_text("✔ Success").or_(page.get_by_text("✘ Failed at")).filter(visible=True).first.wait_for(
        timeout=180_000
    )
    result = ui.wait(lambda: im.rollout.result, 30, "the rollout's result")
    ui.shot(page, shots / "imitate-outcome-shipped.png")
    row = [r for r in studio.store.catalog.rollouts(task=HELD_OUT) if r.id == result["rollout_id"]]
    assert row and row[0].checkpoint_id == policy.id


@pytest.mark.slow
def test_push_is_imitated_with_the_shipped_push_policy(studio, page, shots):
    """A held-out push task in Imitate is planned and executed by the push policy shipped with the studio (its
    scene's), whatever pick-and-place policy is active; in Train, choosing the pick-and-place policy for push is
    refused with the reason and push keeps its policy."""
    import re

    tab = ui.tab(studio)
    im, train = tab.imitate, tab.train
    push = studio.runs.shipped_for("push")
    assert push is not None and push.id == "default/push-cpu" and push.scene == "push"
    assert "push" not in studio.runs.chosen_ids(), "no push policy was chosen: the shipped one plans push"
    pick = studio.runs.shipped_for("pick_place")
    studio.runs.set_active(pick.id)  # the pick-and-place choice must not leak into push

    # Train: the active-policy choice is for the scene chosen there; another scene's policy is refused.
    ui.open_tab(page, "Train", "Held out (never trained on)")
    ui.choose(
        page,
        "Scene",
        "push",
        lambda: train.scene.value == "push" and "plans **push** tasks" in train.active_note.content,
        "the push policy in Train",
        lambda: train.active_note.content,
    )
    assert train.active.value == push.label and "(shipped)" in train.active_note.content
    ui.choose(
        page,
        "Active policy",
        re.compile(r"^shipped policy pick-place-cpu"),
        lambda: "✘" in train.active_note.content,
        "the refusal",
        lambda: train.active_note.content,
    )
    assert "`default/pick-place-cpu` was trained on pick_place tasks: it does not plan push tasks" in (
        train.active_note.content
    )
    assert studio.runs.active("push").id == push.id and train.active.value == push.label, (
        "push keeps its policy"
    )
    page.get_by_text("it does not plan push tasks").filter(visible=True).first.wait_for(timeout=30_000)
    ui.shot(page, shots / "train-push-refused.png", scroll_to="it does not plan push tasks")

    # Imitate: the policy line follows the selected task's scene.
    ui.open_tab(page, "Imitate", "Choose a")
    im.task.value = HELD_OUT + " (held-out)"
    ui.wait(
        lambda: f"**pick_place** tasks: `{pick.id}`" in im.policy.content,
        20,
        "the pick-and-place policy line",
        lambda: im.policy.content,
    )
    im.task.value = PUSH_HELD_OUT + " (held-out)"
    ui.wait(
        lambda: f"**push** tasks: `{push.id}`" in im.policy.content,
        20,
        "the push policy line",
        lambda: im.policy.content,
    )
    ui.wait(
        lambda: push.summary and push.summary in im.policy_details.content,
        20,
        "its measured results one fold away",
        lambda: im.policy_details.content,
    )
    page.get_by_text("default/push-cpu").filter(visible=True).first.wait_for(timeout=30_000)
    im.seed.value = 3
    before_demo = im.expert_job
    ui.click(page.get_by_role("button", name="Make a scripted demonstration"))
    ui.wait(lambda: im.expert_job is not before_demo and im.expert_job, 30, "the scripted demonstration job")
    page.get_by_text("stored and selected").filter(visible=True).first.wait_for(timeout=90_000)
    demo = studio.store.get(im.demo_id())
    assert (demo.task, demo.embodiment, demo.source) == (PUSH_HELD_OUT, "sawyer", "scripted")
    before = im.plan_job
    ui.click(page.get_by_role("button", name="Plan", exact=True))
    job = ui.wait(lambda: im.plan_job is not before and im.plan_job, 30, "a new plan job")
    assert job.spec["checkpoint"] == push.path and job.spec["task"] == PUSH_HELD_OUT
    ui.wait(
        lambda: job.result is not None and im.latent_strip.visible,
        120,
        "the decoded latent trajectory",
        lambda: im.status.content,
    )
    page.get_by_text("Planned in").filter(visible=True).first.wait_for(timeout=60_000)
    assert job.result["latent_images"] > 0 and im.plan_wps.shape == (5, 4) and np.isfinite(im.plan_wps).all()
    assert im.plan_wps[2, 1] - im.plan_wps[1, 1] < -0.1, f"a backward push: {im.plan_wps}"
    ui.drawn(page)
    ui.shot(page, shots / "imitate-push-plan.png", scroll_to="Policy for")
    ui.shot(page, shots / "imitate-push-latents.png", scroll_to="Predicted latent trajectory")
    im.speed.value = "as fast as possible"
    ui.click(page.get_by_role("button", name="Execute", exact=True))
    page.get_by_text("✔ Success").or_(page.get_by_text("✘ Failed at")).filter(visible=True).first.wait_for(
        timeout=180_000
    )
    result = ui.wait(lambda: im.rollout.result, 30, "the rollout's result")
    assert im.rollout.spec["checkpoint"] == push.path and im.rollout.spec["checkpoint_id"] == push.id
    ui.drawn(page)
    ui.shot(page, shots / "imitate-push-outcome.png", scroll_to="Policy for")
    assert result["success"] is True, result  # seeded: this scene and demonstration succeed
    assert "✔ Success" in im.outcome.content
    row = [r for r in studio.store.catalog.rollouts(task=PUSH_HELD_OUT) if r.id == result["rollout_id"]]
    assert row and row[0].checkpoint_id == push.id


@pytest.mark.slow
def test_a_filmed_hand_demonstration_uploaded_in_the_browser_is_imitated_by_the_panda(
    studio, page, shots, tmp_path
):
    """The upload path end to end: the simulated hand demonstrates the held-out push task, its episode is exported
    as an MP4 at another size and frame rate (as a camera would film it), uploaded in *Upload*, saved as a
    demonstration of the task, then planned and executed in *Imitate* by the shipped push policy that learnt from
    human demonstrations (measured at 100 % on this task), which must succeed."""
    from studio.data.video import probe_video
    from studio.data.video_export import export_episode_video

    tab = ui.tab(studio)
    im, upload = tab.imitate, tab.upload
    push = studio.runs.active("push", "human")
    assert push.id == "default/push-human-demos", (
        "a human demonstration is planned by the human-trained policy"
    )
    assert studio.runs.active("push").id == "default/push-cpu", "the scene's default policy is unchanged"

    # The simulated hand's scripted demonstration (an `expert` job on the sim worker, as Imitate's button makes).
    job = studio.jobs.submit("expert", {"task": PUSH_HELD_OUT, "seed": 1003, "robot": "hand"})
    ui.wait(lambda: job.terminal and job.result, 120, "the hand's demonstration", lambda: job.status)
    hand = studio.store.get(job.result["episode_id"])
    assert (hand.task, hand.embodiment, hand.role, hand.height, hand.width) == (
        PUSH_HELD_OUT,
        "human",
        "expert",
        240,
        320,
    )
    video = tmp_path / "hand-push.mp4"
    export_episode_video(studio.store, hand.id, video, size=(180, 240), fps=24.0)
    info = probe_video(video)
    assert (
        (info.height, info.width) == (180, 240)
        and abs(info.fps - 24.0) < 1e-6
        and abs(info.fps - hand.fps) > 5
    )

    # Upload it as a user does: the task shown, the file, the filmstrip, Save.
    ui.open_tab(page, "Upload", "Upload a video")
    ui.choose(
        page,
        "Task shown",
        PUSH_HELD_OUT,
        lambda: upload.task.value == PUSH_HELD_OUT,
        "the task shown",
        lambda: upload.task.value,
    )
    before = {m.id for m in studio.store.episodes(source="upload")}
    page.locator("input[type=file]").first.set_input_files(str(video))
    ui.wait(lambda: upload.pending is not None, 90, "the upload to be decoded", lambda: upload.status.content)
    page.get_by_text("Check the task above").filter(visible=True).first.wait_for(timeout=60_000)
    assert "hand-push.mp4" in upload.status.content and upload.strip.visible
    ui.drawn(page)
    ui.shot(page, shots / "upload-hand-filmstrip.png", scroll_to="The 10 frames the model will see")
    ui.click(page.get_by_role("button", name="Save as expert demonstration"))
    page.get_by_text("as an expert demonstration of").filter(visible=True).first.wait_for(timeout=60_000)
    (up,) = [m for m in studio.store.episodes(source="upload") if m.id not in before]
    assert (up.task, up.embodiment, up.role, up.source) == (PUSH_HELD_OUT, "human", "expert", "upload")
    assert up.extra["source_size"] == [180, 240] and up.extra["original_name"] == "hand-push.mp4"

    # Imitate: the uploaded demonstration, planned and executed by the push policy that learnt from people.
    ui.open_tab(page, "Imitate", "Choose a")
    im.task.value = PUSH_HELD_OUT + " (held-out)"
    option = f"{up.id} · upload · human"
    ui.wait(
        lambda: option in im.demo.options, 30, "the upload among the demonstrations", lambda: im.demo.options
    )
    ui.choose(
        page,
        "Demonstration",
        option,
        lambda: im.demo_id() == up.id,
        "the upload to be selected",
        lambda: im.demo.value,
    )
    ui.wait(
        lambda: (
            f"**push** tasks: `{push.id}` (learnt from human demonstrations, like this one)"
            in im.policy.content
        ),
        20,
        "the policy line of a human demonstration",
        lambda: im.policy.content,
    )
    page.get_by_text("default/push-human-demos").filter(visible=True).first.wait_for(timeout=30_000)
    im.seed.value = 3
    before_plan = im.plan_job
    ui.click(page.get_by_role("button", name="Plan", exact=True))
    plan = ui.wait(lambda: im.plan_job is not before_plan and im.plan_job, 30, "a new plan job")
    assert plan.spec["expert_episode_id"] == up.id and plan.spec["checkpoint"] == push.path
    assert plan.spec["task"] == PUSH_HELD_OUT
    ui.wait(lambda: plan.terminal and plan.result is not None, 120, "the plan", lambda: im.status.content)
    page.get_by_text("Planned in").filter(visible=True).first.wait_for(timeout=60_000)
    assert im.plan_wps.shape == (5, 4) and np.isfinite(im.plan_wps).all()
    ui.drawn(page)
    ui.shot(page, shots / "imitate-upload-plan.png", scroll_to="Policy for")
    ui.shot(page, shots / "imitate-upload-expert-frames.png", scroll_to="Expert frames the model sees")
    im.speed.value = "as fast as possible"
    ui.click(page.get_by_role("button", name="Execute", exact=True))
    rollout = ui.wait(
        lambda: im.rollout is not None and im.rollout.spec.get("expert_episode_id") == up.id and im.rollout,
        30,
        "the rollout of the upload",
    )
    assert rollout.spec["checkpoint_id"] == push.id
    page.get_by_text("✔ Success").or_(page.get_by_text("✘ Failed at")).filter(visible=True).first.wait_for(
        timeout=180_000
    )
    result = ui.wait(lambda: rollout.result, 30, "the rollout's result")
    ui.drawn(page)
    ui.shot(page, shots / "imitate-upload-outcome.png", scroll_to="re-plan(s); rollout")
    outcome = "success" if result["success"] else f"failed at {result['failure_stage']}"
    print(f"\nthe Panda imitating the uploaded hand video of {PUSH_HELD_OUT}: {outcome}")
    assert result["success"], result
    assert "✔ Success" in im.outcome.content
    row = [r for r in studio.store.catalog.rollouts(task=PUSH_HELD_OUT) if r.id == result["rollout_id"]]
    assert row and row[0].checkpoint_id == push.id
