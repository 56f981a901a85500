"""The studio in a real browser: Debian's headless Chromium driven by Playwright against the studio server.

The first test runs ``studio serve`` as a user would (a subprocess that prints its URL). The others share
one in-process :class:`StudioApp` (with its embedded sim worker and trainer) and one page, so that they can
drive the gizmo through the same server-side callback a browser drag reaches and look at what the app
holds. Screenshots of every panel go to the test's temporary directory (printed at the end).

Chromium renders WebGL in software here; the page's animation frames are throttled to ~5 fps so that
the browser does not starve the simulation on a shared 2-core machine (the pose stream is unaffected:
it is counted on the websocket, not on the screen).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from studio.backend import bus
from studio.model.checkpoint_info import read_checkpoint_info

sys.path.insert(0, str(Path(__file__).resolve().parent))
import browser_support as ui
from browser_support import THROTTLE_RAF, open_page, running_studio
from tiny_network import TINY_BATCHED

HELD_OUT = "pick_place/bar->blue"
PUSH_HELD_OUT = "push/blue-backward"
TRAIN_TASKS = ("pick_place/cube->red", "pick_place/cube->green")

# Tests that share the app are slow one by one (marked); the fast ones stay in `-m "not slow"` runs.
pytestmark = [pytest.mark.browser, pytest.mark.timeout(420)]


# ---------------------------------------------------------------------------------------------- studio serve
def test_serve_prints_its_url_and_waits_for_external_workers(tmp_path):
    """`studio serve` as a user runs it (here with `--workers none`; the embedded default is what the other
    tests' in-process app starts): URL printed, page up, teleop waiting for a sim worker, clean SIGTERM."""
    from playwright.sync_api import sync_playwright

    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    bus_port = bus.free_loopback_port()
    cmd = [
        sys.executable,
        "-m",
        "studio.cli",
        "serve",
        "--port",
        str(bus.free_loopback_port()),
        "--workers",
        "none",
        "--data-dir",
        str(tmp_path / "data"),
        "--listen",
        bus.loopback_endpoint(bus_port),
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    try:
        url, line = None, ""
        deadline = time.time() + 60
        while time.time() < deadline and url is None:
            line = proc.stdout.readline()
            if "OSVI Studio running at" in line:
                url = line.split("running at")[1].split()[0]
            elif proc.poll() is not None:
                break
        assert url and url.startswith("http://127.0.0.1:"), f"no URL printed (last line: {line!r})"
        assert "no workers" in line and f"127.0.0.1:{bus_port}" in line
        with sync_playwright() as p:
            browser = ui.launch(p)
            page = browser.new_page(viewport={"width": 1100, "height": 720})
            page.add_init_script(THROTTLE_RAF)
            page.goto(url)
            page.get_by_text("Waiting for a sim worker").filter(visible=True).first.wait_for(timeout=60_000)
            assert page.locator("canvas").first.is_visible()
            ui.open_tab(page, "Workers", "No worker is connected")
            browser.close()
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
    assert proc.returncode == 0, "studio serve did not stop cleanly on SIGTERM"


# ---------------------------------------------------------------------------------------------- shared app
@pytest.fixture(scope="module")
def shots(tmp_path_factory):
    d = tmp_path_factory.mktemp("screenshots")
    yield d
    print(f"\nscreenshots: {d}")


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    """A store with tiny synthetic training episodes and one stored failed rollout."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "data"))
    from data_fixtures import make_recording

    from studio.data.catalog import CheckpointRecord, RunRecord
    from studio.data.store import EpisodeStore
    from studio.eval.oracle import OraclePlanner
    from studio.eval.rollout import run_rollout, store_rollout
    from studio.sim.env import SimEnv

    root = tmp_path_factory.mktemp("studio") / "data"
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


@pytest.fixture(scope="module")
def studio(data_dir):
    with running_studio(data_dir) as app:
        yield app


@pytest.fixture(scope="module")
def page(studio):
    with open_page(studio) as pg:
        yield pg


# ---------------------------------------------------------------------------------------------- panels
@pytest.mark.slow
def test_teleop_records_and_saves_an_episode(studio, page, shots):
    tab = ui.tab(studio)
    tp = tab.teleop
    assert tp.info.scene == "pick_place" and tp.info.robot == "sawyer"
    # A real mouse drag on the gizmo's x arrow moves the target along x (once the page has drawn the gizmo).
    ui.drawn(page, 3)
    center = np.asarray(tp.gizmo.position)
    grab = ui.screen_point(page, tab.client, center + np.array([0.09, 0.0, 0.0]))
    ahead = ui.screen_point(page, tab.client, center + np.array([0.14, 0.0, 0.0]))
    drags_before = tp.drags
    ee_before = np.asarray(tp.client.latest_pose().ee_pos)
    page.mouse.move(grab[0] - 3, grab[1])
    page.mouse.move(*grab)
    ui.drawn(page)  # hovered: the arrow under the pointer is picked
    page.mouse.down()
    for k in range(1, 11):
        page.mouse.move(grab[0] + (ahead[0] - grab[0]) * k / 10, grab[1] + (ahead[1] - grab[1]) * k / 10)
        ui.drawn(page, 1)
    page.mouse.up()
    ui.wait(lambda: tp.drags > drags_before, 20, "the browser's drag to reach the server")
    assert np.asarray(tp.gizmo.position)[0] > center[0] + 0.01, (
        "dragging the x arrow moves the gizmo along +x"
    )
    ui.wait(lambda: tp.client.latest_pose().ee_pos[0] > ee_before[0] + 0.01, 15, "the arm to follow the drag")
    before = {m.id for m in studio.store.episodes()}
    ui.click(page.get_by_role("button", name="Record"))
    ui.wait(lambda: tp._recording, 30, "recording to start")
    page.get_by_text("● REC").filter(visible=True).first.wait_for(timeout=60_000)
    start = np.asarray(ui.wait(tp.client.latest_pose, 5, "a pose").ee_pos)
    # The gizmo's drag callback, as the browser reaches it: targets along a path, latest wins.
    goal = start + np.array([0.06, 0.04, -0.08])
    version = tp.client.poses.get()[1]
    for i in range(1, 61):  # one target per pose frame of the simulation, as a hand's drag at its frame rate
        tp.move_to(start + (goal - start) * i / 60)
        version = ui.next_pose(tp.client, version)
    ui.wait(
        lambda: np.linalg.norm(np.asarray(tp.client.latest_pose().ee_pos) - goal) < 0.01,
        15,
        "the arm to follow",
    )
    assert tab.pose_pushes > 30 and studio.stats.ack_ms, "poses must reach the page and drags be acknowledged"
    ui.click(page.get_by_role("checkbox", name="Success"))  # the user's verdict overrides the task's check
    ui.wait(lambda: tp.success.value and tp._success_touched, 10, "the success box to be ticked")
    ui.shot(page, shots / "teleop-recording.png")
    assert ui.colours(shots / "teleop-recording.png") > 300, "the 3D view looks blank"
    ui.stop_and_save(page, tab)
    page.get_by_text("Saved").filter(visible=True).first.wait_for(timeout=60_000)
    ui.shot(page, shots / "teleop-saved.png")
    (new,) = [m for m in studio.store.episodes() if m.id not in before]
    assert new.source == "teleop" and new.role == "expert" and new.embodiment == "sawyer"
    assert new.success is True and new.num_steps >= 60 and new.task == "pick_place/cube->red"
    _, _, arrays = studio.store.load_arrays(new.id)
    assert np.linalg.norm(arrays["ee_pos_world"][-1] - arrays["ee_pos_world"][0]) > 0.05


@pytest.mark.slow  # fast by itself, but it opens the episode test_teleop_records_... stores
def test_upload_appears_in_the_dataset_and_a_corrupt_file_is_rejected(studio, page, shots, tmp_path):
    from studio.data.video import write_video

    tab = ui.tab(studio)
    ui.click(page.get_by_role("tab", name="Upload"))
    tab.upload.task.value = HELD_OUT
    frames = np.full((30, 120, 160, 3), 235, np.uint8)
    for i in range(30):
        frames[i, 40:80, 4 * i : 4 * i + 30] = (200, 60, 50)  # a "hand" crossing the view
    video = tmp_path / "demo.mp4"
    write_video(video, frames, fps=15)
    page.locator("input[type=file]").first.set_input_files(str(video))
    page.get_by_text("The 10 frames the model will see").filter(visible=True).first.wait_for(timeout=60_000)
    ui.shot(page, shots / "upload-filmstrip.png")
    ui.click(page.get_by_role("button", name="Save as expert demonstration"))
    page.get_by_text("as an expert demonstration of").filter(visible=True).first.wait_for(timeout=60_000)
    (up,) = studio.store.episodes(source="upload")
    assert up.task == HELD_OUT and up.embodiment == "human" and up.role == "expert"

    corrupt = tmp_path / "broken.mp4"
    corrupt.write_bytes(b"\x00\x00\x00\x18ftypmp42" + os.urandom(4000))
    page.locator("input[type=file]").first.set_input_files(str(corrupt))
    page.get_by_text("Video rejected").filter(visible=True).first.wait_for(timeout=60_000)
    ui.shot(page, shots / "upload-rejected.png")
    assert len(studio.store.episodes(source="upload")) == 1, "a rejected file must write nothing"

    ui.click(page.get_by_role("tab", name="Data"))
    page.get_by_text("1 upload").filter(visible=True).first.wait_for(timeout=60_000)
    tab.datasets.open(up.id)
    page.get_by_text(up.id).filter(visible=True).first.wait_for(timeout=60_000)
    assert (
        tab.datasets.frames.shape[0] == up.num_frames and tab.mode == "teleop"
    )  # a video, nothing to replay
    (rec,) = studio.store.episodes(source="teleop")
    tab.datasets.open(rec.id)  # a simulated episode: replayed in the scene with its end-effector path
    tab.datasets.timeline.slider.value = rec.num_frames // 2
    page.get_by_text(rec.id).filter(visible=True).first.wait_for(timeout=60_000)
    assert tab.mode == "replay" and "path" in tab.view._overlays
    ui.shot(page, shots / "data.png")


@pytest.mark.slow
def test_training_job_started_from_the_ui_shows_progress(studio, page, shots):
    tab = ui.tab(studio)
    train = tab.train
    ui.click(page.get_by_role("tab", name="Train"))
    for task, box in train._task_boxes.items():
        box.value = task in TRAIN_TASKS
    train.overrides.value = "; ".join(TINY_BATCHED)
    train.steps.value = 4
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
    ui.click(page.get_by_role("tab", name="Imitate"))
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
    ui.click(page.get_by_role("tab", name="Imitate"))
    ui.wait(lambda: f"{run.name}/last" in im.policy.content, 20, "the trained policy to be active")
    ui.click(page.get_by_role("button", name="Plan", exact=True))
    ui.wait(lambda: im.latent_strip.visible, 120, "the decoded latent trajectory")
    ui.shot(page, shots / "imitate-plan-trained.png", scroll_to="Predicted latent trajectory")
    assert im.plan_job.result["latent_images"] > 0 and im.plan_wps.shape == (5, 4)
    assert np.isfinite(im.plan_wps).all()


@pytest.mark.slow
def test_inspector_replays_a_stored_failed_rollout(studio, page, shots):
    tab = ui.tab(studio)
    ins = tab.inspector
    ui.open_tab(page, "Inspect", "Every rollout")
    ins.outcome.value = "failures"
    first = ui.wait(
        lambda: ins.rollout.options[0] if "✘" in ins.rollout.options[0] else None, 10, "failures listed"
    )
    assert all("✘" in o for o in ins.rollout.options), "only failures"
    ins.checkpoint.value = "fixture-run/best"
    failed = studio.store.catalog.rollouts(success=False, checkpoint_id="fixture-run/best")
    first = ins.rollout.options[0]
    assert first.startswith(failed[0].id) and failed[0].failure_stage in first
    ui.click_and_see(page, page.get_by_role("button", name="Open", exact=True).first, "Stages:")
    assert tab.mode == "replay"
    steps = ins.replay.num_steps
    ins.timeline.slider.value = steps // 2
    ui.wait(lambda: f"Step {steps // 2} of" in ins.plan_info.content, 30, "the timeline to move")
    ui.wait(
        lambda: "predicted latent state" in ins.plan_info.content, 20, "a predicted image beside the frame"
    )
    ui.shot(page, shots / "inspect.png")
    mid = ins.replay.poses_at(steps // 2)
    assert not np.allclose(mid, ins.replay.poses_at(0)), "the scene moves along the timeline"
    assert "plan" in tab.view._overlays
    assert ins.n_plans == 1  # the stored null plan is not counted as a plan of its own
    assert "null plan" in tab.view._overlays, "a guided rollout shows its plan from the scene alone"
    assert "guidance moved the plan up to 0.12 m from it (demonstration gain 1.600)" in ins.plan_info.content


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
    ui.click_and_see(page, page.get_by_role("button", name="Compare stored rollouts"), "2 shared episodes")
    assert [r.to_dict() for r in cmp.rows] == ran


def test_workers_panel_lists_the_embedded_workers(studio, page, shots):
    tab = ui.tab(studio)
    ui.click(page.get_by_role("tab", name="Workers"))
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
    ui.click(page.get_by_role("tab", name="Imitate"))
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


@pytest.mark.slow
def test_teleop_on_a_meta_world_scene_records_a_demonstration(studio, page, shots):
    """Meta-World in the browser: choose the scene in the Teleop tab's dropdown (the robot choice narrows to the
    Sawyer), drag the arm, record and save; the Imitate tab then offers the recording as a demonstration of its
    task, and the shipped Meta-World policy plans from it on the Meta-World scene."""
    tab = ui.tab(studio)
    tp, im = tab.teleop, tab.imitate
    ui.open_tab(page, "Teleop", "Drag the gizmo")
    ui.choose(
        page,
        "Scene",
        "metaworld",
        lambda: tp.info is not None and tp.info.scene == "metaworld",
        "the Meta-World session to open",
        timeout=120,
    )
    ui.wait(
        lambda: "ready" in tp.status.content and tp.info.task in tp.status.content, 60, "the session's status"
    )
    assert tp.robot.options == ("sawyer",) and tp.info.robot == "sawyer"
    task = tp.info.task
    assert task.startswith("metaworld/")
    # The live camera preview shows Meta-World's corner view (a black background, mean ~58), not the tabletop it
    # showed before (mean ~174), which it once kept showing for a while under the "(live)" label.
    ui.wait(
        lambda: 5 < float(np.asarray(tp.preview.image).mean()) < 120,
        30,
        "the Meta-World camera preview",
        lambda: f"preview mean {float(np.asarray(tp.preview.image).mean()):.1f}",
    )
    ui.drawn(page, 3)
    ui.shot(page, shots / "teleop-metaworld.png")
    assert ui.colours(shots / "teleop-metaworld.png") > 300, "the Meta-World scene looks blank"
    before = {m.id for m in studio.store.episodes()}
    ui.click(page.get_by_role("button", name="Record"))
    ui.wait(lambda: tp._recording and "REC" in tp.rec_status.content, 60, "recording to start")
    start = np.asarray(ui.wait(tp.client.latest_pose, 5, "a pose").ee_pos)
    goal = start + np.array([0.05, 0.05, -0.05])
    version = tp.client.poses.get()[1]
    for i in range(1, 61):  # the gizmo's drag callback, as the browser reaches it: one target per pose frame
        tp.move_to(start + (goal - start) * i / 60)
        version = ui.next_pose(tp.client, version)
    ui.wait(
        lambda: np.linalg.norm(np.asarray(tp.client.latest_pose().ee_pos) - goal) < 0.02,
        20,
        "the Sawyer to follow the drag",
    )
    ui.stop_and_save(page, tab)
    (new,) = [m for m in studio.store.episodes() if m.id not in before]
    assert (new.scene, new.task, new.source, new.role, new.embodiment) == (
        "metaworld",
        task,
        "teleop",
        "expert",
        "sawyer",
    )
    _, _, arrays = studio.store.load_arrays(new.id)
    assert np.linalg.norm(arrays["ee_pos_world"][-1] - arrays["ee_pos_world"][0]) > 0.05

    ui.open_tab(page, "Imitate", "Choose a")
    im.task.value = next(label for label, name in im.labels.items() if name == task)
    # None was chosen for Meta-World: the shipped Meta-World policy plans it, learnt from Sawyer demonstrations like
    # this recording (the pick-and-place policy chosen earlier never plans another scene's task).
    mw = studio.runs.shipped_for("metaworld")
    assert mw is not None and mw.id == "default/metaworld-cpu" and mw.scene == "metaworld"
    ui.wait(
        lambda: f"**metaworld** tasks: `{mw.id}` (learnt from sawyer demonstrations" in im.policy.content,
        20,
        "the Meta-World policy line",
        lambda: im.policy.content,
    )
    ui.wait(
        lambda: any(o.startswith(new.id) for o in im.demo.options),
        20,
        "the recording among the demonstrations",
    )
    im.demo.value = next(o for o in im.demo.options if o.startswith(new.id))
    before_job = im.plan_job
    ui.click(page.get_by_role("button", name="Plan", exact=True))
    job = ui.wait(lambda: im.plan_job is not before_job and im.plan_job, 30, "a new plan job")
    assert job.spec["expert_episode_id"] == new.id and job.spec["robot"] == "sawyer"
    assert job.spec["checkpoint"] == mw.path
    ui.wait(lambda: job.result is not None, 120, "the plan on the Meta-World scene")
    page.get_by_text("Planned in").filter(visible=True).first.wait_for(timeout=60_000)
    assert im.plan_wps.shape == (5, 4) and np.isfinite(im.plan_wps).all()
    # The shipped Meta-World policy plans with gated guidance: its plan from the scene alone is drawn in grey and
    # the status says whether this demonstration was guided, with its gain against the gate.
    assert "null plan" in tab.view._overlays
    gate = read_checkpoint_info(mw.path)["config"]["model"]["guidance_gate"]
    assert gate > 0 and "demonstration gain" in im.status.content, im.status.content
    assert f"gate {gate:g}" in im.status.content, (gate, im.status.content)
    ui.shot(page, shots / "imitate-plan-metaworld.png")


@pytest.mark.slow
def test_fork_a_failed_rollout_correct_it_and_lose_nothing_when_the_worker_dies(studio, page, shots):
    """Inspect → fork the failed rollout before its misaimed grasp → drag the correction; the sim worker is killed
    while the bar is held; the recording continues on the restarted worker → saved, linked to the rollout."""
    import signal

    from studio.data.forks import fork_source
    from studio.sim.env import SimEnv
    from studio.sim.experts import expert_waypoints

    tab = ui.tab(studio)
    ins, tp = tab.inspector, tab.teleop
    failed = studio.store.catalog.rollouts(success=False, checkpoint_id="fixture-run/best")[0]
    ui.open_tab(page, "Inspect", "Every rollout")
    ins.outcome.value = "failures"
    ins.checkpoint.value = "fixture-run/best"
    ui.wait(lambda: ins.rollout.options[0].startswith(failed.id), 10, "the failed rollout listed")
    shown = (
        ins.replay
    )  # an earlier test may have opened it: wait for this Open's replay (it resets the timeline)
    ui.click_and_wait(
        page.get_by_role("button", name="Open", exact=True).first,
        lambda: ui.wait(lambda: ins.replay is not shown and ins.record.id == failed.id, 90, "the replay"),
    )
    # A click repeated because the first open was slow opens the rollout again later, resetting the timeline to
    # step 0: wait until no open is queued before moving it.
    ui.wait(lambda: "opening the rollout" not in tab.actions, 120, "every queued Open", lambda: tab.actions)
    page.get_by_text("No episode was forked from this rollout yet").filter(visible=True).first.wait_for(
        timeout=30_000
    )
    k = 40  # the arm is on its way to the misaimed grasp
    ins.timeline.slider.value = k
    ui.wait(lambda: f"Step {k} of" in ins.plan_info.content, 30, "the timeline to move")
    before = {m.id for m in studio.store.episodes()}
    assert "opening the rollout" not in tab.actions and f"Step {k} of" in ins.plan_info.content
    ui.click_and_see(page, page.get_by_role("button", name="Fork at this step"), "Recording the fork")
    ui.wait(
        lambda: tp._recording and tab.mode == "teleop" and tp.info.robot == "panda",
        60,
        "the fork session",
        lambda: ui.teleop_state(tab),
    )
    assert (tp.info.task, tp.info.seed) == (failed.task, failed.seed)
    # A pose of the forked session. Nothing commands the arm yet, so from the restored tick it moves as the
    # rollout's physics state carries it (the arm was moving at tick k): exactly as a local restore stepped on
    # with the target held, however many ticks the session ran before this pose was seen.
    first = tp.client.poses.wait_until(lambda f: f.body_count == len(tp.info.body_names) and f.step >= k, 10)
    assert first is not None, f"no pose of the forked scene; {ui.teleop_state(tab)}"
    src = studio.store.catalog.get_rollout(failed.id)
    fs = fork_source(studio.store, src.id, k)
    with SimEnv("pick_place", "panda", control_dt=fs.control_dt) as env:
        env.restore(fs.task, fs.seed, fs.states, fs.gripper)
        # The arm the replay showed at tick k (it moves under a millimetre a tick).
        np.testing.assert_allclose(env.ee_pos, ins.replay.arrays["ee_pos_world"][k], atol=2e-3)
        for _ in range(first.step - k):
            env.step(env.target, env.gripper_cmd)
        np.testing.assert_allclose(
            first.ee_pos, env.ee_pos, atol=1e-6, err_msg=f"step {first.step}; {ui.teleop_state(tab)}"
        )
    ui.shot(page, shots / "fork-restored.png")

    # The correction a person would drag: above the bar, down, grasp, up, over the blue target, down, release.
    with SimEnv("pick_place", "panda") as env:
        env.restore(fs.task, fs.seed, fs.states, fs.gripper)
        grasp, lift, carry, place, _ = expert_waypoints(env)

    def drag(goal, seconds: float = 1.5) -> None:
        """The gizmo dragged to ``goal``: it moves, and its callback sends each position (latest wins)."""
        start = np.asarray(tp.client.latest_pose().ee_pos)
        n = int(seconds * 60)
        version = tp.client.poses.get()[1]
        for i in range(1, n + 1):  # one target per pose frame of the simulation
            p = start + (np.asarray(goal) - start) * i / n
            tp.gizmo.position = p
            tp.move_to(p)
            version = ui.next_pose(tp.client, version)
        ui.wait(
            lambda: np.linalg.norm(np.asarray(tp.client.latest_pose().ee_pos) - goal) < 0.01,
            20,
            f"the arm to reach {np.round(goal, 3)}",
            lambda: ui.teleop_state(tab),
        )

    drag(grasp[:3] + np.array([0.0, 0.0, 0.1]))
    drag(grasp[:3], 1.0)
    ui.click(page.get_by_role("button", name="Close", exact=True))
    ui.wait(lambda: tp.client.latest_pose().gripper == 1.0, 10, "the gripper to close")
    ui.sim_ticks(tp.client, 40)  # the fingers close on the bar
    drag(lift[:3])
    # The recording gains a tick with every control tick: its length is the pose's step plus a fixed offset (read
    # from one state message, which carries both, as the states are re-published only twice a second).
    dying = tp.client
    state = dying.state.wait_until(lambda s: s.recorded_steps > 0, 10)
    offset = state.recorded_steps - state.step
    # The sim worker dies while the bar is held.
    (sim,) = [p for p in studio.embedded.processes if p.kind == "sim"]
    sim.process.send_signal(signal.SIGKILL)
    ui.wait(
        lambda: "The sim worker was lost mid-recording" in tp.status.content or tp.client is None,
        60,
        "the loss to be noticed",
        lambda: ui.teleop_state(tab),
    )
    held_steps = dying.latest_pose().step + offset  # recorded when the worker's last pose left it
    ui.wait(
        lambda: (
            tp._recording
            and tp.client is not None
            and tp.client.worker != sim.worker
            and tp.status.content.startswith("Continuing the interrupted recording")
        ),
        180,
        "the recording to continue on the restarted worker",
        lambda: ui.teleop_state(tab),
    )
    resumed = tp.client.state.wait_until(lambda s: s.recorded_steps > 0, 10).recorded_steps
    # Draft chunks leave every 0.1 s (5 ticks): at most that and the chunk in flight are lost, and a tick the dead
    # worker published no pose of can only be one sent in the same instant.
    assert held_steps - 10 <= resumed <= held_steps + 1, (held_steps, resumed)
    ee = np.asarray(tp.client.latest_pose().ee_pos)
    assert np.linalg.norm(ee - lift[:3]) < 0.02, "the arm is where it was when its worker died"
    ui.open_tab(page, "Inspect", "Recording the fork")
    ui.shot(page, shots / "fork-resumed.png", scroll_to="Fork from this moment")
    drag(carry[:3], 2.0)
    drag(place[:3], 1.0)
    ui.click(page.get_by_role("button", name="Open", exact=True).last)
    ui.wait(lambda: tp.client.latest_pose().gripper == 0.0, 10, "the gripper to open")
    ui.sim_ticks(tp.client, 50)  # the fingers let the bar go
    drag(place[:3] + np.array([0.0, 0.0, 0.08]))
    ui.wait(
        lambda: tp.success.value, 10, "the task's check to see the bar placed", lambda: ui.teleop_state(tab)
    )
    ui.click_and_wait(
        page.get_by_role("button", name="Stop & save the fork"),
        lambda: ui.wait(
            lambda: tp.status.content.startswith("Saved"),
            120,
            "the fork to be stored",
            lambda: ui.teleop_state(tab),
        ),
    )
    (new,) = [m for m in studio.store.episodes() if m.id not in before]
    assert new.extra["forked_from"] == {"rollout": failed.id, "step": k, "episode": failed.episode_id}
    assert (new.role, new.embodiment, new.task, new.seed, new.success) == (
        "agent",
        "panda",
        failed.task,
        failed.seed,
        True,
    )
    _, _, arrays = studio.store.load_arrays(new.id)
    _, _, rolled = studio.store.load_arrays(failed.episode_id)
    np.testing.assert_array_equal(arrays["qpos"][: k + 1], rolled["qpos"][: k + 1])
    assert np.all(np.diff(arrays["time"]) > 0) and new.num_steps > resumed
    assert studio.drafts.drafts() == [], "the stored episode replaced its draft"
    ui.wait(lambda: f"`{new.id}` (agent, from step {k}, ✔)" in ins.fork_status.content, 20, "the fork listed")
    ui.shot(page, shots / "fork-saved.png")


@pytest.mark.slow
def test_a_rollout_whose_scene_no_longer_loads_says_so(studio, page, shots, monkeypatch):
    import studio.sim.scenes as scenes
    from studio.data.forks import STATES_FILE

    tab = ui.tab(studio)
    ins, tp = tab.inspector, tab.teleop
    failed = studio.store.catalog.rollouts(success=False, checkpoint_id="fixture-run/best")[0]
    ui.open_tab(page, "Inspect", "Every rollout")
    ins.outcome.value = "failures"
    ins.checkpoint.value = "fixture-run/best"
    ui.wait(lambda: ins.rollout.options[0].startswith(failed.id), 10, "the failed rollout listed")

    def gone(*args, **kwargs):
        raise FileNotFoundError("scenes/pick_place.xml was removed")

    with monkeypatch.context() as m:  # the scene file is gone: replaying needs it
        m.setattr(scenes, "build_model", gone)
        ui.click(page.get_by_role("button", name="Open", exact=True).first)
        page.get_by_text("cannot be replayed: its scene does not load here").filter(
            visible=True
        ).first.wait_for(timeout=60_000)
    ui.shot(page, shots / "inspect-scene-gone.png")
    # The scene loads again, but its model changed since the rollout: the fork is refused with the reason.
    ui.click_and_see(page, page.get_by_role("button", name="Open", exact=True).first, "Stages:")
    path = Path(failed.path) / STATES_FILE
    kept = path.read_bytes()
    try:
        with np.load(path) as data:
            np.savez_compressed(path, states=data["states"][:, :-2])
        ui.click(page.get_by_role("button", name="Fork at this step"))
        page.get_by_text("the scene changed since the episode was recorded").filter(
            visible=True
        ).first.wait_for(timeout=60_000)
    finally:
        path.write_bytes(kept)
    assert not tp._recording and studio.drafts.drafts() == [], "a refused fork leaves nothing behind"
    ui.shot(page, shots / "fork-refused.png")
