"""Recording a demonstration by clicking, as a person does: real mouse clicks on the 3D canvas and the panel.

Every action is a browser event (a mouse click on the canvas where the object appears, a click on a panel
button), made by :class:`studio.bench.click_demo.ClickPerson`, which reads the app only to know where things are
on the screen and to wait for the arm to arrive before its next click, as a person watches it. The actions and
the simulated time are counted, and the stored episode passes the task's own check, computed here from its
arrays: the success box is never touched.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import numpy as np
import pytest

from studio.bench.click_demo import ClickPerson
from studio.sim.tasks import get_task

sys.path.insert(0, str(Path(__file__).resolve().parent))
import browser_support as ui

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(600)]

#: A person met no grasp in ten minutes of dragging; clicking must do it in this many actions ...
MAX_ACTIONS = 12
#: ... and this much simulated time.
MAX_SIM_SECONDS = 60.0


class _Errors(logging.Handler):
    """ERROR lines the studio logs while the tests run (the server log a person would read)."""

    def __init__(self):
        super().__init__(logging.ERROR)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(f"{record.name}: {record.getMessage()}")


@pytest.fixture(scope="module")
def errors():
    handler = _Errors()
    logging.getLogger("studio").addHandler(handler)
    yield handler
    logging.getLogger("studio").removeHandler(handler)


@pytest.fixture(scope="module")
def studio(tmp_path_factory, errors):
    with ui.running_studio(tmp_path_factory.mktemp("studio") / "data") as app:
        yield app


def _new_episode(studio, before: set[str]):
    (new,) = [m for m in studio.store.episodes() if m.id not in before]
    return new


def _task_check(studio, meta) -> bool:
    """The task's own success check on the stored episode's last tick (not the verdict the panel stored)."""
    _, _, arrays = studio.store.load_arrays(meta.id)
    poses = arrays["object_poses"]
    objects = {n: poses[-1, k, :3] for k, n in enumerate(meta.object_names)}
    initial = {n: poses[0, k, :3] for k, n in enumerate(meta.object_names)}
    task = get_task(meta.task)
    held = task.obj if arrays["gripper_cmd"][-1] >= 0.5 and task.scene == "pick_place" else None
    layout = task.sample_layout(meta.seed)
    return bool(task.success(objects, initial, layout, arrays["ee_pos_world"][-1], held))


class ShootingPerson(ClickPerson):
    """The same person, with screenshots at the moments worth looking at."""

    def __init__(self, page, tab, shots: Path, prefix: str):
        super().__init__(page, tab)
        self.shots, self.prefix = shots, prefix
        self.seen: list[tuple[str, str]] = []

    def button(self, name: str) -> None:
        self.seen.append((name, self.tp.status.content))  # what the status line said when the person pressed
        if name in ("Close", "Stop & save"):
            ui.shot(self.page, self.shots / f"{self.prefix}-before-{name.split()[0].lower()}.png")
        super().button(name)


def _check_saved(studio, tp, person, before, task: str) -> None:
    new = _new_episode(studio, before)
    seconds = new.num_steps * tp.info.control_dt
    assert _task_check(studio, new), f"{task}: the stored episode fails the task's own check"
    assert new.success is True and new.task == task and new.source == "teleop" and new.role == "expert"
    assert not tp._success_touched, "the verdict is the task's check, not the test's"
    assert len(person.actions) <= MAX_ACTIONS, person.actions
    assert seconds < MAX_SIM_SECONDS, f"{seconds:.1f} s of simulated time"
    print(f"\n{task} by clicking: {len(person.actions)} actions, {seconds:.1f} s simulated")


def test_a_pick_and_place_demonstration_by_clicking(studio, page, shots, errors):
    """Record, click the cube, Down, Close, Up, click the red zone, Down, Open, Stop & save: nine actions."""
    tab = ui.tab(studio)
    tp = tab.teleop
    assert (tp.info.scene, tp.info.robot, tp.info.task) == ("pick_place", "sawyer", "pick_place/cube->red")
    person = ShootingPerson(page, tab, shots, "pick")
    before = {m.id for m in studio.store.episodes()}
    person.demonstrate("pick_place/cube->red")
    _check_saved(studio, tp, person, before, "pick_place/cube->red")
    assert person.actions[:3] == ["Record", "click the cube", "Down"], person.actions
    downs = [status for name, status in person.seen if name == "Down"]
    assert "**cube**" in downs[0] and "**Close** to grasp" in downs[0], downs
    # carrying the cube over the zone, the line says what comes next: lower it and open
    assert "red zone" in downs[1] and "**Down** to lower the cube, **Open** to release it" in downs[1], downs
    assert not errors.lines, f"the server logged errors while recording and saving: {errors.lines}"


def test_the_depth_cues_name_the_object_under_the_gripper(studio, page, shots):
    """Just after placing the cube (the gripper open over it): the status line says how high above the cube's
    top the grasp point is, and the drop line, shadow and yellow outline are drawn."""
    tab = ui.tab(studio)
    tp = tab.teleop
    person = ClickPerson(page, tab)
    cube = person.objects()["obj_cube"]
    ui.wait(lambda: "above the cube" in tp.cue_line.content, 10, "the cue line", lambda: tp.cue_line.content)
    ui.wait(lambda: tp.cues.visible, 5, "the depth cues")
    ui.shot(page, shots / "cues-over-cube.png")
    height = float(tp.cue_line.content.split("**")[1].split()[0]) / 100
    assert abs(height - (person.ee()[2] - (cube[2] + 0.022))) < 0.01, tp.cue_line.content  # the cube's top
    assert "from the cube" in tp.cue_line.content, tp.cue_line.content


def test_a_push_demonstration_by_clicking(studio, page, shots):
    """Push scene: click behind the box, Close, Down, click beyond it, Stop & save."""
    tab = ui.tab(studio)
    tp = tab.teleop
    ui.choose(
        page,
        "Scene",
        "push",
        lambda: tp.info and tp.info.scene == "push" and not tab.actions,
        "the push scene",
        lambda: ui.teleop_state(tab),
    )
    assert tp.info.task == "push/red-forward", tp.info.task
    person = ShootingPerson(page, tab, shots, "push")
    before = {m.id for m in studio.store.episodes()}
    person.demonstrate("push/red-forward")
    _check_saved(studio, tp, person, before, "push/red-forward")


def test_teleop_marks_a_held_out_task(studio, page, shots):
    """Choosing a held-out task in Teleop says it is held out (a demonstration of it is for Imitate)."""
    tab = ui.tab(studio)
    tp = tab.teleop
    ui.choose(
        page,
        "Scene",
        "pick_place",
        lambda: tp.info and tp.info.scene == "pick_place" and not tab.actions,
        "the pick-and-place scene",
        lambda: ui.teleop_state(tab),
    )
    assert not page.get_by_text("is held out").first.is_visible(), "cube->red is a training task"
    ui.choose(
        page,
        "Task",
        "pick_place/bar->blue",
        lambda: tp.info and tp.info.task == "pick_place/bar->blue" and not tab.actions,
        "the held-out task",
        lambda: ui.teleop_state(tab),
    )
    page.get_by_text("is held out").filter(visible=True).first.wait_for(timeout=20_000)
    ui.shot(page, shots / "teleop-held-out.png", scroll_to="is held out")


def test_an_interrupted_recording_is_offered_open(studio, page, shots):
    """A draft a stopped studio left behind: its Resume button shows without opening a fold."""
    states = np.zeros((30, 8))
    studio.drafts.create(
        "d-left-behind",
        {
            "scene": "pick_place",
            "robot": "sawyer",
            "task": "pick_place/cube->red",
            "seed": 0,
            "control_dt": 0.01,
            "role": "expert",
        },
    )
    studio.drafts.append(
        "d-left-behind", 0, states, {"time": np.arange(30) * 0.01, "gripper_cmd": np.zeros(30)}
    )
    resume = page.get_by_role("button", name="Resume", exact=True)
    resume.wait_for(state="visible", timeout=30_000)
    ui.shot(page, shots / "teleop-interrupted.png", scroll_to="Interrupted recordings")
    studio.drafts.discard("d-left-behind")


def test_keys_nudge_the_gripper(studio, page, shots):
    """The arrow keys and PageUp nudge the target by the chosen step (viser command hotkeys), as the buttons do."""
    tab = ui.tab(studio)
    tp = tab.teleop
    page.mouse.click(30, 700)  # focus the page (the canvas), not a text field of the panel
    goals = []
    for key in ("ArrowRight", "ArrowRight", "PageUp"):
        before, _ = tp.motion
        page.keyboard.press(key)
        ui.wait(
            lambda before=before: tp.motion[0] > before, 20, f"{key}'s nudge", lambda: ui.teleop_state(tab)
        )
        goals.append(tp.motion[1])
    assert np.allclose(goals[1] - goals[0], [0.01, 0.0, 0.0], atol=1e-6), goals
    assert np.allclose(goals[2] - goals[1], [0.0, 0.0, 0.01], atol=1e-6), goals
