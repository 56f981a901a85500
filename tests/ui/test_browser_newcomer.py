"""What a newcomer meets in the browser studio: switching scenes and robots, forking a carry, notifications, uploads.

Each test drives Debian's headless Chromium through Playwright against an in-process :class:`StudioApp` and
asserts on what the page (or the browser's own scene tree) shows. Screenshots go to the test's temporary
directory (printed at the end).
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import browser_support as ui
from browser_support import THROTTLE_RAF

CARRY_TASK = "pick_place/cube->red"
pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(900)]

#: Every scene node the browser holds, read from the viewer's own scene tree (found through React's fibers
#: from the page's DOM): type, colour, vertex count, visibility and the pose it draws the node at.
CLIENT_SCENE = """() => {
  for (const el of [document.querySelector('canvas'), ...document.querySelectorAll('div')]) {
    if (!el) continue;
    const key = Object.keys(el).find((k) => k.startsWith('__reactFiber$'));
    if (!key) continue;
    for (let f = el[key]; f; f = f.return) {
      const v = f.memoizedProps && f.memoizedProps.value;
      if (!(v && v.useSceneTree && v.useSceneTree.getAll && v.mutable)) continue;
      const poses = v.mutable.current.nodePoseData;
      return Object.entries(v.useSceneTree.getAll()).filter(([, n]) => n && n.message).map(([name, n]) => {
        const p = n.message.props || {};
        const pose = poses[name] || {};
        return {name, type: n.message.type, color: p.color ? Array.from(p.color) : null,
                vertices: p.vertices ? p.vertices.length : 0,
                position: Array.from(pose.position || n.position || [0, 0, 0]),
                wxyz: Array.from(pose.wxyz || n.wxyz || [1, 0, 0, 0]),
                visible: n.effectiveVisibility ?? n.visibility ?? true};
      });
    }
  }
  return null;
}"""


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    return _quat_mul(_quat_mul(q, np.r_[0.0, v]), q * np.array([1, -1, -1, -1]))[1:]


def drawn(nodes: list[dict]) -> list[tuple[tuple, np.ndarray, np.ndarray]]:
    """What the browser draws, whatever the nodes are called: (kind, world position, world wxyz) of every
    visible node, its world pose composed along its ancestors' poses (the scene root's own axis change left out,
    as it is the same for every tab)."""
    by_name = {n["name"]: n for n in nodes}
    out = []
    for n in nodes:
        if not n["name"] or not n["visible"]:
            continue
        chain, name = [], n["name"]
        while name:
            chain.append(by_name.get(name))
            name = name.rsplit("/", 1)[0]
        if any(c is None or not c["visible"] for c in chain):
            continue
        pos, quat = np.zeros(3), np.array([1.0, 0, 0, 0])
        for c in reversed(chain):  # the root's child first
            q = np.asarray(c["wxyz"], float)
            pos = pos + _rotate(quat, np.asarray(c["position"], float))
            quat = _quat_mul(quat, q / np.linalg.norm(q))
        kind = (n["type"], tuple(n["color"] or ()), n["vertices"])
        out.append((kind, pos, quat))
    return out


def scene_difference(a: list[dict], b: list[dict], metres: float = 0.01, degrees: float = 3.0) -> list[str]:
    """What one page draws that the other does not (kind and pose matched within ``metres``/``degrees``)."""
    left, right = drawn(a), drawn(b)
    unmatched_b = list(range(len(right)))
    missing = []
    for kind, pos, quat in left:
        hit = None
        for j in unmatched_b:
            k2, p2, q2 = right[j]
            angle = np.degrees(2 * np.arccos(min(1.0, abs(float(np.dot(quat, q2))))))
            if k2 == kind and np.linalg.norm(pos - p2) <= metres and angle <= degrees:
                hit = j
                break
        if hit is None:
            missing.append(f"switched tab only: {kind[0]} {kind[1]} ({kind[2]} floats) at {np.round(pos, 3)}")
        else:
            unmatched_b.remove(hit)
    missing += [
        f"fresh tab only: {right[j][0][0]} {right[j][0][1]} at {np.round(right[j][1], 3)}"
        for j in unmatched_b
    ]
    return missing


def image_difference(a: Path, b: Path, box=(0, 200, 690, 720)) -> float:
    """Fraction of the 3D view's pixels (left of the control panel, below the notifications) that differ."""
    from PIL import Image

    x = np.asarray(Image.open(a).convert("RGB").crop(box), dtype=np.int16)
    y = np.asarray(Image.open(b).convert("RGB").crop(box), dtype=np.int16)
    return float((np.abs(x - y).max(axis=2) > 48).mean())


@pytest.fixture(scope="module")
def rollouts(studio):
    """Rollouts stored on demand (once per module): ``carry`` grasps the cube, carries it lifted 18 cm to the
    side of its zone and lets it go there (a failure at the place stage); ``success`` is the oracle's."""
    from studio.eval.oracle import OraclePlanner
    from studio.eval.rollout import run_rollout, store_rollout
    from studio.sim.env import SimEnv

    class Misplaced(OraclePlanner):
        def plan(self, *args):
            plan = super().plan(*args)
            plan.waypoints_world = plan.waypoints_world + np.array([0.0, -0.18, 0.0, 0.0]) * (
                np.arange(5)[:, None] >= 2
            )
            return plan

    made: dict[str, object] = {}

    def get(which: str):
        if which not in made:
            with SimEnv("pick_place", "panda", image_size=(120, 160)) as env:
                planner = Misplaced(env) if which == "carry" else OraclePlanner(env)
                out = run_rollout(
                    env, planner, np.zeros((10, 120, 160, 3), np.uint8), CARRY_TASK, 0, n_frames=20
                )
            assert out.success == (which == "success"), out.stages
            made[which] = store_rollout(studio.store, out, expert_episode_id=None, checkpoint_id=None)
            studio.dataset_changed()
        return made[which]

    return get


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = ui.launch(p)
        yield b
        b.close()


@pytest.fixture
def opened(browser):
    """Closes the pages a test opened, however it ended (a page left open keeps a teleop session on the worker
    and its browser tab in the background)."""
    pages: list = []
    yield pages
    for pg in pages:
        if not pg.is_closed():
            pg.close()


def new_page(browser, studio, viewport=(1100, 720), opened: list | None = None):
    """One more browser tab on the studio, once its teleop session is ready (the tab the app opened for it)."""
    before = set(studio.tabs)
    others = list(opened or [])
    pg = browser.new_page(viewport={"width": viewport[0], "height": viewport[1]})
    ui.watch_page(pg)
    if opened is not None:
        opened.append(pg)
    pg.bring_to_front()  # the tab a person looks at (headless Chromium still draws the others: in_background)
    pg.add_init_script(THROTTLE_RAF)
    with ui.in_background(others):  # the tabs opened before are in the background while this one loads
        pg.goto(studio.url)
        try:
            pg.get_by_text("ready. Drag the gizmo").filter(visible=True).first.wait_for(timeout=120_000)
        except Exception as e:
            shown = {c: ui.teleop_state(t) for c, t in list(studio.tabs.items()) if c not in before}
            raise AssertionError(
                f"the new tab was not ready within 120 s ({shown or 'no tab opened'}): {e}"
            ) from e
    (client_id,) = set(studio.tabs) - before
    return pg, studio.tabs[client_id]


def _ready(tab, scene: str, robot: str) -> bool:
    info = tab.teleop.info
    return (
        info is not None
        and (info.scene, info.robot) == (scene, robot)
        and "ready" in tab.teleop.status.content
        and not tab.actions
    )


def test_switching_scenes_and_robots_leaves_nothing_of_the_previous_scene(studio, browser, shots, opened):
    """Every robot of every scene, picked by clicks on the Teleop dropdowns, then back to the first scene: the
    browser's scene tree and picture match a tab opened fresh on that scene (no stale pedestal, no second
    tabletop, every cube and zone where it is)."""
    page, tab = new_page(browser, studio, opened=opened)
    state = lambda: ui.teleop_state(tab)  # noqa: E731
    steps = [
        ("Robot", "panda", "pick_place"),
        ("Robot", "hand", "pick_place"),
        ("Robot", "sawyer", "pick_place"),
        ("Scene", "push", None),
        ("Robot", "panda", "push"),
        ("Robot", "hand", "push"),
        ("Scene", "metaworld", None),
        ("Scene", "pick_place", None),
    ]
    robot = "sawyer"
    for box, value, scene in steps:
        if box == "Scene":
            scene = value
            robot = "sawyer" if value == "metaworld" else robot
        else:
            robot = value
        want = (scene, robot)
        ui.choose(page, box, value, lambda w=want: _ready(tab, *w), f"the {want} session", state, timeout=120)
        if scene == "metaworld":
            ui.shot(page, shots / "switch-metaworld.png")
    assert tab.teleop.task.value == "pick_place/cube->red" and int(tab.teleop.seed.value) == 0
    fresh, fresh_tab = new_page(browser, studio, opened=opened)
    assert (fresh_tab.teleop.info.scene, fresh_tab.teleop.info.robot) == ("pick_place", "sawyer")

    def same() -> list[str]:
        return scene_difference(page.evaluate(CLIENT_SCENE), fresh.evaluate(CLIENT_SCENE)) or []

    try:
        ui.wait(
            lambda: not same(),
            60,
            "the switched tab to draw what a fresh tab draws",
            lambda: "\n".join(same()),
        )
    finally:
        ui.shot(page, shots / "switched.png")
        ui.shot(fresh, shots / "fresh.png")

    def pictures_differ() -> float:
        ui.shot(page, shots / "switched.png")
        ui.shot(fresh, shots / "fresh.png")
        return image_difference(shots / "switched.png", shots / "fresh.png")

    # A fresh page fades its lighting in: compare the pictures once it has (a stale scene never matches).
    ui.wait(
        lambda: pictures_differ() < 0.01,
        90,
        "the switched tab's picture to match a fresh tab's (switched.png, fresh.png)",
        lambda: f"{image_difference(shots / 'switched.png', shots / 'fresh.png'):.1%} of the 3D view differs",
    )
    fresh.close()
    page.close()


def test_inspect_selects_the_first_listed_rollout_until_one_is_chosen(
    studio, browser, rollouts, shots, opened
):
    """Failures are listed first, and the list's first entry is the one selected: a failure stored after a
    success takes the selection (nobody chose the success), a rollout the user picked keeps it."""
    page, tab = new_page(browser, studio, opened=opened)
    ins = tab.inspector
    ok = rollouts("success")
    ui.open_tab(page, "Inspect", "Every rollout")
    combo = page.get_by_role("combobox", name="Rollout")
    ui.wait(
        lambda: ok.id in combo.input_value(), 30, "the successful rollout shown", lambda: ins.rollout.options
    )
    failed = rollouts("carry")
    ui.wait(lambda: ins.rollout.options[0].startswith(failed.id), 30, "the failure listed first")
    ui.wait(
        lambda: combo.input_value().startswith(failed.id),
        30,
        "the first listed rollout (the failure) selected",
        lambda: f"page shows {combo.input_value()!r}; options {ins.rollout.options}",
    )
    ui.shot(page, shots / "inspect-first-listed.png", scroll_to="Open")
    # A choice of the user's stays when the list changes.
    label = next(o for o in ins.rollout.options if o.startswith(ok.id))
    ui.choose(page, "Rollout", label, lambda: ins.rollout.value == label, "the success chosen")
    version = studio.dataset_version
    studio.dataset_changed()  # the panels refill their lists, as after a new rollout
    ui.wait(lambda: ins._version == studio.dataset_version > version, 10, "the list refilled")
    assert combo.input_value() == label and ins.rollout.value == label
    page.close()


def test_a_fork_mid_carry_keeps_the_object_in_the_gripper(studio, browser, rollouts, shots, opened):
    """Inspect → a failed rollout at a step where the cube is held and lifted → Fork at this step → lift with the
    keyboard: the cube rises with the gripper, and the saved fork's gripper command stays closed from the fork on."""
    failed = rollouts("carry")
    _, _, rolled = studio.store.load_arrays(failed.episode_id)
    z = rolled["object_poses"][:, :, 2]
    obj = int(np.argmax(z.max(axis=0) - z[0]))  # the object the rollout carried
    held = np.flatnonzero((rolled["gripper_cmd"] > 0.5) & (z[:, obj] > z[0, obj] + 0.08))
    k = int(held[len(held) // 2])  # mid-carry
    page, tab = new_page(browser, studio, opened=opened)
    ins, tp = tab.inspector, tab.teleop
    ui.open_tab(page, "Inspect", "Every rollout")
    label = next(o for o in ins.rollout.options if o.startswith(failed.id))
    ui.choose(page, "Rollout", label, lambda: ins.rollout.value == label, "the carrying rollout chosen")
    ui.click_and_wait(
        page.get_by_role("button", name="Open", exact=True).first,
        lambda: ui.wait(lambda: ins.record is not None and ins.record.id == failed.id, 90, "the replay"),
    )
    ui.wait(lambda: "opening the rollout" not in tab.actions, 120, "every queued Open", lambda: tab.actions)
    ins.timeline.slider.value = k
    ui.wait(lambda: f"Step {k} of" in ins.plan_info.content, 30, "the timeline to move")
    before = {m.id for m in studio.store.episodes()}
    ui.click_and_see(page, page.get_by_role("button", name="Fork at this step"), "Recording the fork")
    ui.wait(
        lambda: tp._recording and tab.mode == "teleop" and not tab.actions,
        60,
        "the fork session",
        lambda: ui.teleop_state(tab),
    )
    names = tp.info.body_names
    body = next(i for i, n in enumerate(names) if n.startswith("obj_") and "cube" in n)
    start = tp.client.poses.wait_until(lambda f: f.step >= k and f.body_count == len(names), 10)
    assert start is not None and start.gripper > 0.5, "the fork starts with the gripper closed"
    cube0 = start.poses_array()[body, :3].astype(float)
    assert np.linalg.norm(cube0 - np.asarray(start.ee_pos)) < 0.05, "the cube is in the gripper at the fork"
    ui.shot(page, shots / "fork-carry-restored.png")

    # Lifted with the keyboard, as a person steering the fork does: PageUp raises the target by the nudge step
    # (1 cm) from where the last press left it; five presses, each taken by the panel. (The gizmo's mouse drag is
    # tested in test_browser.py; a drag of its arrow here, over the Panda's hand, missed in two of three whole
    # runs, cause not found.)
    ee = np.asarray(start.ee_pos, dtype=float)
    page.evaluate("() => document.activeElement && document.activeElement.blur()")
    for _ in range(5):
        motions, _ = tp.motion
        page.keyboard.press("PageUp")
        ui.wait(
            lambda motions=motions: tp.motion[0] > motions, 20, "PageUp's nudge", lambda: ui.teleop_state(tab)
        )
    ui.wait(
        lambda: tp.client.latest_pose().ee_pos[2] > ee[2] + 0.03,
        30,
        "the gripper to rise",
        lambda: f"ee {np.round(tp.client.latest_pose().ee_pos, 3)}; {ui.teleop_state(tab)}",
    )
    settled = tp.client.latest_pose().step
    now = tp.client.poses.wait_until(lambda f: f.step >= settled + 25, 10)  # half a second later
    cube = now.poses_array()[body, :3].astype(float)
    ui.shot(page, shots / "fork-carry-lifted.png")
    assert now.gripper > 0.5, "the lift left the gripper closed"
    assert cube[2] > cube0[2] + 0.02 and np.linalg.norm(cube - np.asarray(now.ee_pos)) < 0.05, (
        f"the cube fell: at {np.round(cube, 3)}, gripper at {np.round(now.ee_pos, 3)} (fork at {np.round(cube0, 3)})"
    )
    ui.click_and_wait(
        page.get_by_role("button", name="Stop & save the fork"),
        lambda: ui.wait(
            lambda: tp.status.content.startswith("Saved"),
            120,
            "the fork stored",
            lambda: ui.teleop_state(tab),
        ),
    )
    (new,) = [m for m in studio.store.episodes() if m.id not in before]
    _, _, arrays = studio.store.load_arrays(new.id)
    assert new.extra["forked_from"]["step"] == k
    assert np.all(arrays["gripper_cmd"][k:] > 0.5), (
        f"the stored gripper command opens at step {k + int(np.argmax(arrays['gripper_cmd'][k:] <= 0.5))}"
    )
    page.close()


def _visible(page, text: str) -> int:
    return page.get_by_text(text, exact=True).locator("visible=true").count()


def test_upload_errors_are_one_sentence_and_error_notifications_close_without_piling_up(
    studio, browser, shots, tmp_path, opened
):
    """Three rejected uploads and two other errors in a row: the rejection reads as a sentence (no decoder
    exception), one notification per title and at most two errors open at once, and they close by themselves."""
    from studio.ui import app as app_module

    page, tab = new_page(browser, studio, opened=opened)
    ui.open_tab(page, "Upload", "Upload a video of")
    for i in range(3):
        notes = tmp_path / f"notes{i}.mp4"
        notes.write_text("meeting notes, definitely not a video\n" * 50)
        page.locator("input[type=file]").first.set_input_files(str(notes))
        page.get_by_text(f"notes{i}.mp4 is not a video file the studio can read").filter(
            visible=True
        ).first.wait_for(timeout=60_000)
    page.get_by_text("Video rejected", exact=True).filter(visible=True).first.wait_for(timeout=30_000)
    body = page.locator("body").inner_text()
    assert "Errno" not in body and "InvalidDataError" not in body, "the decoder's exception reached the page"
    # A replaced notification leaves with a short animation (slow here: animation frames are throttled).
    ui.wait(
        lambda: _visible(page, "Video rejected") == 1, 10, "one notification for three rejections of a kind"
    )
    tab.notify("Planning failed", "the plan job failed on the sim worker.", error=True)
    tab.notify("No rollout", "Choose a rollout to open.", error=True)
    page.get_by_text("No rollout", exact=True).filter(visible=True).first.wait_for(timeout=30_000)
    titles = ("Video rejected", "Planning failed", "No rollout")
    shown = lambda: {t: _visible(page, t) for t in titles}  # noqa: E731
    ui.wait(lambda: sum(shown().values()) <= 2, 10, "at most two error notifications", shown)
    assert shown()["No rollout"] == 1 and shown()["Video rejected"] == 0, shown()
    ui.shot(page, shots / "notifications.png")
    ui.wait(
        lambda: not any(_visible(page, t) for t in titles),
        app_module.ERROR_SECONDS + 20,
        "the error notifications to close by themselves",
        shown,
    )
    page.close()


def test_an_upload_says_its_frame_rate_was_lowered(studio, browser, shots, opened, tmp_path):
    """A 20 fps video becomes 10 fps (whole frames, at most 15 a second), and the page says so."""
    from studio.data.video import write_video

    frames = np.full((62, 120, 160, 3), 235, np.uint8)
    for i in range(62):
        frames[i, 40:80, 2 * i : 2 * i + 30] = (200, 60, 50)  # a "hand" crossing the view
    video = tmp_path / "hand20.mp4"
    write_video(video, frames, fps=20)
    page, tab = new_page(browser, studio, opened=opened)
    ui.open_tab(page, "Upload", "Upload a video of")
    page.locator("input[type=file]").first.set_input_files(str(video))
    page.get_by_text("The 10 frames the model will see").filter(visible=True).first.wait_for(timeout=60_000)
    page.get_by_text("resampled from the video's 20 fps").filter(visible=True).first.wait_for(timeout=30_000)
    assert re.search(r"\d+ frames at 10 fps \(resampled from the video's 20 fps", tab.upload.status.content)
    ui.shot(page, shots / "upload-resampled.png", scroll_to="resampled from")
    ui.click(page.get_by_role("button", name="Discard upload"))
    page.close()


def test_workers_and_data_say_counts_and_ages_as_a_person_would(studio, browser, rollouts, shots, opened):
    """The Workers tab gives each worker its own age ("2 workers on the bus.", no "up for 40 min, 40 min"), and
    the Data tab counts episodes in the right number."""
    page, tab = new_page(browser, studio, opened=opened)
    ui.open_tab(page, "Workers", "workers on the bus")
    table = tab.workers.table.content
    rows = [line for line in table.splitlines() if line.startswith("| sim") or line.startswith("| train")]
    assert len(rows) == 2 and all(re.search(r"\| \d+\u00a0(s|min|h) \|$", r) for r in rows), table
    assert "2 workers on the bus." in table and "worker(s)" not in table
    ui.shot(page, shots / "workers.png")
    rollouts("success")  # at least one episode
    n = len(studio.store.episodes())
    counted = f"{n} episode{'' if n == 1 else 's'}: "
    ui.open_tab(page, "Data", counted)
    assert counted in tab.datasets.table.content and "1 episodes" not in tab.datasets.table.content
    page.close()
