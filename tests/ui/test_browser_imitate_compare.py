"""Imitate and Compare in a real browser: what is shown is what runs, meaningless demonstrations are flagged,
Compare's defaults run, and the images can be enlarged.

One in-process studio (embedded sim worker and trainer) and one headless Chromium page for the module. The store
holds a scripted demonstration of a held-out pick-and-place task and, uploaded as a person's video of the same
task, a three-second video of a coloured blob drifting on a plain background (imported by the code the Upload tab
runs). The shipped pick-and-place policy plans both. Screenshots go to the module's temporary directory (printed at
the end).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import browser_support as ui

HELD_OUT = "pick_place/bar->blue"
OTHER_HELD_OUT = "pick_place/bar->yellow"
#: The blob video's colours: a magenta background, a green disc.
BACKGROUND = (235, 20, 200)
DISC = (30, 200, 60)

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(600)]


def blob_video(path: Path, seconds: float = 3.0, fps: float = 24.0) -> Path:
    """A phone-sized MP4 of a green disc drifting across a magenta background: no task in it."""
    import cv2

    h, w = 360, 480
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    n = int(seconds * fps)
    for t in range(n):
        frame = np.empty((h, w, 3), np.uint8)
        frame[:] = BACKGROUND[::-1]  # OpenCV writes BGR
        cx, cy = int(120 + 240 * t / (n - 1)), int(140 + 80 * t / (n - 1))
        cv2.circle(frame, (cx, cy), 60, DISC[::-1], -1)
        writer.write(frame)
    writer.release()
    return path


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    """A scripted Sawyer demonstration of the held-out task (by the recorder the ``expert`` job runs) and the blob
    video uploaded as a demonstration of the same task."""
    from studio.data.collect import DEFAULT_RECORDER, MIN_FRAMES, load_recorder
    from studio.data.store import EpisodeStore
    from studio.data.video_import import import_video
    from studio.sim.env import default_image_size

    root = tmp_path_factory.mktemp("studio") / "data"
    record = load_recorder(DEFAULT_RECORDER)
    with EpisodeStore(root) as store:
        recording = record(
            "pick_place", "sawyer", HELD_OUT, 1001, default_image_size("pick_place"), MIN_FRAMES
        )
        assert recording.success
        store.add_episode(recording, role="expert", source="scripted")
        video = blob_video(tmp_path_factory.mktemp("videos") / "blob.mp4")
        import_video(store, video, HELD_OUT)
    return root


def demos(studio) -> tuple[str, str]:
    """The option labels of the scripted demonstration and of the uploaded blob."""
    (scripted,) = studio.store.episodes(task=HELD_OUT, source="scripted")
    (blob,) = studio.store.episodes(task=HELD_OUT, source="upload")
    return f"{scripted.id} · scripted · sawyer", f"{blob.id} · upload · human"


def open_imitate(page, studio) -> None:
    im = ui.tab(studio).imitate
    ui.open_tab(page, "Imitate", "Choose a")
    label = HELD_OUT + " (held-out)"
    ui.choose(page, "Task", label, lambda: im.task.value == label, "the held-out task", lambda: im.task.value)


def choose_demo(page, im, option: str) -> None:
    ui.choose(
        page,
        "Demonstration",
        option,
        lambda: im.demo.value == option,
        "the demonstration",
        lambda: im.demo.value,
    )


def visible(page, text: str):
    """The first element showing ``text`` that is visible (other tabs' panels hold the same lines, hidden)."""
    return page.locator(f"text={text} >> visible=true").first


def plan(page, im):
    before = im.plan_job
    ui.click_and_wait(
        page.get_by_role("button", name="Plan", exact=True),
        lambda: ui.wait(lambda: im.plan_job is not before, 30, "a new plan job"),
    )
    job = im.plan_job
    ui.wait(lambda: job.terminal and job.result is not None, 120, "the plan", lambda: im.status.content)
    page.get_by_text("Planned in").filter(visible=True).first.wait_for(timeout=60_000)
    return job


def execute(page, im) -> None:
    """Click Execute (again if the click was lost) until a new rollout is attached."""
    before = im.rollout
    ui.click_and_wait(
        page.get_by_role("button", name="Execute", exact=True),
        lambda: ui.wait(lambda: im.rollout is not before, 30, "a new rollout"),
    )


def share_near(image: np.ndarray, colour, tol: int = 60) -> float:
    """The share of an image's pixels within ``tol`` of ``colour`` on every channel."""
    rgb = np.asarray(image)[..., :3].astype(int)
    return float((np.abs(rgb - np.asarray(colour)).max(-1) <= tol).mean())


def element_pixels(locator) -> np.ndarray:
    """What the page draws for an element: a screenshot of it, as an RGB array."""
    import io

    from PIL import Image

    # Scrolled into view and cut out of a page screenshot: a locator screenshot waits for a page that stands
    # still, which software WebGL on a loaded machine may not give within a minute. The cut is kept only if the
    # element had the same box after the screenshot: a status line added above it meanwhile (a rollout ending)
    # moved it, and the cut showed the button below instead.
    for _ in range(5):
        locator.evaluate("e => e.scrollIntoView({block: 'center'})", timeout=60_000)
        box = locator.bounding_box(timeout=60_000)
        assert box and box["width"] > 0 and box["height"] > 0, f"the element is not drawn: {box}"
        shot = locator.page.screenshot(clip=box, timeout=60_000)
        if locator.bounding_box(timeout=60_000) == box:
            return np.asarray(Image.open(io.BytesIO(shot)).convert("RGB"))
    raise AssertionError(f"{locator} kept moving: no screenshot of it in 5 tries")


def expert_image(page):
    """The panel's expert-frames image as the page draws it (the image under its label)."""
    return page.locator(
        "xpath=//*[starts-with(normalize-space(text()), 'Expert frames the model sees')]/following::img[1]"
    ).first


# ---------------------------------------------------------------------------------------------- item: stale frames
def test_imitate_shows_the_frames_of_the_demonstration_that_runs(studio, page, shots):
    """Plan with the scripted demonstration, choose the uploaded one, Execute: the expert frames on the page are
    the upload's (the blob's magenta, labelled with its id) from the moment it is chosen and while it runs, and
    the scripted plan's latent images are gone."""
    tab = ui.tab(studio)
    im = tab.imitate
    scripted, blob = demos(studio)
    scripted_id, blob_id = scripted.split(" ")[0], blob.split(" ")[0]
    open_imitate(page, studio)
    choose_demo(page, im, scripted)
    job = plan(page, im)
    assert job.spec["expert_episode_id"] == scripted_id and im.latent_strip.visible
    shown = element_pixels(expert_image(page))
    assert share_near(shown, BACKGROUND) < 0.05, "the scripted demonstration has no magenta"
    ui.shot(page, shots / "stale-1-scripted-plan.png", scroll_to="Expert frames the model sees")

    choose_demo(page, im, blob)
    ui.wait(
        lambda: share_near(element_pixels(expert_image(page)), BACKGROUND) > 0.3,
        60,
        "the page to draw the upload's frames",
    )
    page.get_by_text(f"Expert frames the model sees — {blob_id}").filter(visible=True).first.wait_for(
        timeout=60_000
    )
    assert scripted_id not in im.expert_strip.label
    assert not im.latent_strip.visible, "the scripted plan's latent images are not the upload's"
    page.get_by_text("Plan** again").or_(page.get_by_text("Plan again")).filter(visible=True).first.wait_for(
        timeout=30_000
    )
    ui.shot(page, shots / "stale-2-upload-chosen.png", scroll_to="Expert frames the model sees")

    ui.choose(
        page, "Speed", "as fast as possible", lambda: im.speed.value == "as fast as possible", "the speed"
    )
    execute(page, im)
    rollout = im.rollout
    assert rollout.spec["expert_episode_id"] == blob_id, "Execute runs the chosen demonstration"
    assert share_near(element_pixels(expert_image(page)), BACKGROUND) > 0.3, "the frames shown are what runs"
    page.get_by_text(f"Expert frames the model sees — {blob_id}").filter(visible=True).first.wait_for(
        timeout=30_000
    )
    ui.shot(page, shots / "stale-3-executing-upload.png", scroll_to="Expert frames the model sees")
    page.get_by_text("✔ Success").or_(page.get_by_text("✘ Failed at")).filter(visible=True).first.wait_for(
        timeout=180_000
    )
    assert share_near(element_pixels(expert_image(page)), BACKGROUND) > 0.3


# ---------------------------------------------------------------------------------------------- item: score
def test_a_meaningless_demonstration_is_flagged_in_imitate_and_in_inspect(studio, page, shots):
    """The scripted demonstration's plan reads as like the training demonstrations; the blob's plan carries a
    one-line warning with its score above the calibrated threshold, and so does its rollout in Inspect."""
    tab = ui.tab(studio)
    im = tab.imitate
    scripted, blob = demos(studio)
    open_imitate(page, studio)
    choose_demo(page, im, scripted)
    job = plan(page, im)
    score = job.result["demo_score"]
    assert score["familiar"] and score["score"] < score["threshold"], score
    visible(page, "like the demonstrations the policy learnt from").wait_for(timeout=30_000)
    print(
        f"\nscripted: plan {job.result['planning_time_s'] * 1e3:.0f} ms, score {score['score']:.3f} "
        f"(threshold {score['threshold']:.3f}) in {job.result['demo_score_time_s'] * 1e3:.0f} ms"
    )
    ui.shot(page, shots / "score-1-scripted.png", scroll_to="Demonstration score")

    choose_demo(page, im, blob)
    job = plan(page, im)
    score = job.result["demo_score"]
    assert not score["familiar"] and score["score"] > score["threshold"], score
    visible(page, "This demonstration is far from what the policy learnt from").wait_for(timeout=30_000)
    print(
        f"blob: plan {job.result['planning_time_s'] * 1e3:.0f} ms, score {score['score']:.3f} "
        f"in {job.result['demo_score_time_s'] * 1e3:.0f} ms"
    )
    ui.shot(page, shots / "score-2-blob-warning.png", scroll_to="far from what the policy learnt from")

    ui.choose(
        page, "Speed", "as fast as possible", lambda: im.speed.value == "as fast as possible", "the speed"
    )
    execute(page, im)
    rollout = im.rollout
    result = ui.wait(lambda: rollout.result, 180, "the rollout's result", lambda: im.status.content)
    assert result["demo_score"] == score, "the rollout stores the score of its demonstration"

    ins = tab.inspector
    ui.open_tab(page, "Inspect", "Every rollout")
    option = ui.wait(
        lambda: next((o for o in ins.rollout.options if o.startswith(result["rollout_id"])), None),
        30,
        "the rollout among Inspect's",
        lambda: ins.rollout.options,
    )
    ui.choose(
        page, "Rollout", option, lambda: ins.rollout.value == option, "the rollout", lambda: ins.rollout.value
    )
    ui.click_and_wait(
        page.get_by_role("button", name="Open", exact=True).first,
        lambda: visible(page, "far from what the policy learnt").wait_for(timeout=30_000),
    )
    assert f"score {score['score']:.2f}" in ins.info.content
    ui.shot(page, shots / "score-3-inspect.png", scroll_to="waypoints executed")


# ---------------------------------------------------------------------------------------------- item: enlarge
def test_imitate_policy_line_is_short_and_images_enlarge(studio, page, shots):
    """The policy line names the policy without its long summary, which is one click away in a fold; Enlarge
    opens a modal with the expert frames, the agent's frame and the latent images drawn large."""
    tab = ui.tab(studio)
    im = tab.imitate
    policy = studio.runs.active("pick_place")
    scripted, _ = demos(studio)
    open_imitate(page, studio)
    choose_demo(page, im, scripted)
    ui.wait(lambda: policy.id in im.policy.content, 20, "the policy line", lambda: im.policy.content)
    assert policy.summary and policy.summary not in im.policy.content and len(im.policy.content) < 200
    line = page.get_by_text("Policy for pick_place tasks:").first
    line.wait_for(timeout=30_000)
    assert policy.summary[:40] not in line.inner_text()
    assert not page.get_by_text(policy.summary[:40]).first.is_visible()
    ui.click_and_see(page, page.get_by_text("About this policy"), policy.summary[:40])
    ui.drawn(page, 3)
    ui.shot(page, shots / "enlarge-1-policy-fold.png", scroll_to="About this policy")

    plan(page, im)
    modal = page.locator(".mantine-Modal-content")
    ui.click_and_wait(
        page.get_by_role("button", name="Enlarge"),
        lambda: modal.get_by_text("Imitate — enlarged").filter(visible=True).first.wait_for(timeout=30_000),
    )
    images = modal.locator("img")
    ui.wait(lambda: images.count() == 3, 30, "three enlarged images")
    panel = expert_image(page).bounding_box()["width"]

    def widths() -> list[float]:  # an image not yet decoded has no width: wait for it, do not measure it
        return [(images.nth(i).bounding_box() or {}).get("width", 0.0) for i in range(3)]

    ui.wait(
        lambda: min(widths()[0], widths()[2]) > 2 * panel,
        30,
        "the expert frames and the latent images drawn over twice the panel's width",
        lambda: f"widths {widths()}, panel {panel}",
    )
    ui.drawn(page, 3)
    ui.shot(page, shots / "enlarge-2-imitate-modal.png")
    ui.click(modal.get_by_role("button", name="Close"))
    page.locator(".mantine-Modal-content").first.wait_for(state="detached", timeout=30_000)


# ---------------------------------------------------------------------------------------------- item: compare defaults
def test_compare_starts_from_two_policies_of_the_scene_and_makes_missing_demonstrations(studio, page, shots):
    """A fresh Compare tab offers only pick-and-place checkpoints and starts from the active policy against the
    next best; the held-out task without a demonstration gets a scripted one on the sim worker (said in the
    progress line) and the comparison runs to its table. Enlarge shows the two camera views large."""
    tab = ui.tab(studio)
    cmp = tab.compare
    ui.open_tab(page, "Compare", "Run two checkpoints on the")
    ui.wait(lambda: cmp.ck_a.value == "default/pick-place-cpu", 30, "A's default", lambda: cmp.ck_a.value)
    assert cmp.ck_b.value == "default/pick-place-no-world-model", cmp.ck_b.value
    assert page.get_by_role("combobox", name="Checkpoint A").input_value() == "default/pick-place-cpu"
    assert (
        page.get_by_role("combobox", name="Checkpoint B").input_value() == "default/pick-place-no-world-model"
    )
    ui.click(page.get_by_role("combobox", name="Checkpoint B"))
    page.get_by_role("option", name="oracle", exact=True).wait_for(timeout=30_000)
    offered = page.get_by_role("option").all_inner_texts()
    assert not [o for o in offered if "metaworld" in o or "push" in o], offered
    page.keyboard.press("Escape")
    assert not studio.store.episodes(task=OTHER_HELD_OUT, role="expert")
    cmp.episodes.value = 1
    ui.click_and_see(
        page, page.get_by_role("button", name="Start", exact=True), "making a scripted one of each"
    )
    assert OTHER_HELD_OUT in cmp.status.content and HELD_OUT not in cmp.status.content.split("stored:")[0]
    ui.shot(page, shots / "compare-1-making-demonstrations.png")
    ui.wait(
        lambda: "finished:" in cmp.status.content,
        400,
        "the comparison to finish",
        lambda: f"status {cmp.status.content!r}, job {cmp.job and cmp.job.state}",
    )
    assert (
        "with the 1 scripted demonstration(s) just made" not in cmp.status.content
    )  # replaced by the result
    made = studio.store.episodes(task=OTHER_HELD_OUT, role="expert", source="scripted")
    assert len(made) == 1 and len(cmp.rows) == 2
    assert {r.task for r in cmp.rows} == {HELD_OUT, OTHER_HELD_OUT}
    page.get_by_text("episodes in").filter(visible=True).first.wait_for(timeout=60_000)
    ui.shot(page, shots / "compare-2-finished.png", scroll_to="Per-seed table")

    ui.click_and_see(page, page.get_by_role("button", name="Open side by side"), "Paths: A blue")
    modal = page.locator(".mantine-Modal-content")
    ui.click_and_wait(
        page.get_by_role("button", name="Enlarge"),
        lambda: (
            modal.get_by_text("Compare — camera views").filter(visible=True).first.wait_for(timeout=30_000)
        ),
    )
    big = modal.locator("img").first
    ui.wait(lambda: (big.bounding_box() or {}).get("width", 0) > 700, 30, "a large side-by-side view")
    before = np.asarray(cmp._enlarged[0].image).copy()
    cmp.timeline.slider.value = int(cmp.timeline.slider.max)
    ui.wait(
        lambda: not np.array_equal(np.asarray(cmp._enlarged[0].image), before),
        30,
        "the enlarged views to follow the timeline",
    )
    ui.drawn(page, 3)
    ui.shot(page, shots / "compare-3-enlarged.png")
    ui.click(modal.get_by_role("button", name="Close"))
