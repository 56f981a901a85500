"""The Teleop and Upload tabs in a real browser (Debian's headless Chromium driven by Playwright): record and save
an episode by dragging the gizmo, upload a video (and refuse a corrupt one), teleoperate the Meta-World scene.

The tests share one in-process :class:`StudioApp` (with its embedded sim worker and trainer) and one page, so
that they can drive the gizmo through the same server-side callback a browser drag reaches and look at what the
app holds. Chromium renders WebGL in software here; the page's animation frames are throttled to ~5 fps so that
the browser does not starve the simulation on a shared 2-core machine.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

from studio.model.checkpoint_info import read_checkpoint_info

sys.path.insert(0, str(Path(__file__).resolve().parent))
import browser_support as ui
from browser_stores import HELD_OUT

# Tests that share the app are slow one by one (marked); the fast ones stay in `-m "not slow"` runs.
pytestmark = [pytest.mark.browser, pytest.mark.timeout(420)]


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
    ui.open_tab(page, "Upload", "Upload a video of")
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

    ui.open_tab(page, "Data", "1 upload")
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
