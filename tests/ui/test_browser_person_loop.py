"""A person's whole loop in the browser, from an empty data directory: collect scripted episodes in Data, record a
demonstration by clicking in Teleop, fine-tune the active pick-and-place policy on them in Train, make the result
active, and plan with it in Imitate — every step a click on the page (the canvas or the panel)."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np
import pytest

from studio.bench.click_demo import ClickPerson

sys.path.insert(0, str(Path(__file__).resolve().parent))
import browser_support as ui

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(900)]
TASK = "pick_place/cube->red"


def _collect(page, tab, robot: str, episodes: int) -> None:
    """Data tab: one task, ``episodes`` scripted episodes by ``robot`` (its own role), Start collecting."""
    data = tab.datasets
    if data.c_robot.value != robot:
        ui.choose(page, "Robot", robot, lambda: data.c_robot.value == robot, f"the {robot}")
    box = page.get_by_role("checkbox", name="cube->red", exact=True)
    if not box.is_checked():
        ui.click(box)
    field = page.get_by_role("textbox", name="Episodes per task")
    field.fill(str(episodes))
    field.press("Tab")
    ui.wait(lambda: int(data.c_episodes.value) == episodes, 10, "episodes per task")
    before = len(tab.app.store.episodes(task=TASK, source="scripted"))
    ui.click(page.get_by_role("button", name="Start collecting"))
    ui.wait(
        lambda: len(tab.app.store.episodes(task=TASK, source="scripted")) >= before + episodes,
        180,
        f"{episodes} scripted {robot} episodes",
    )
    page.get_by_text(f"{episodes} of {episodes} episodes stored").filter(visible=True).first.wait_for(
        timeout=60_000
    )


def test_collect_record_fine_tune_activate_and_plan(studio, page, shots):
    tab = ui.tab(studio)
    # 1. Data: scripted demonstrations (Sawyer) and agent episodes (Panda) of one training task.
    ui.open_tab(page, "Data", "Collect scripted episodes")
    _collect(page, tab, "sawyer", 2)
    _collect(page, tab, "panda", 2)
    ui.shot(page, shots / "loop-collected.png")
    # 2. Teleop: a demonstration recorded by clicking.
    ui.open_tab(page, "Teleop", "Move by clicking")
    person = ClickPerson(page, tab)
    before = {m.id for m in studio.store.episodes()}
    person.demonstrate(TASK)
    (mine,) = [m for m in studio.store.episodes() if m.id not in before]
    assert mine.source == "teleop" and mine.success
    # 3. Train: fine-tune the active (shipped) policy on these episodes, then make the result active.
    shipped = studio.runs.active("pick_place")
    assert shipped is not None and shipped.id.startswith("default/"), "the shipped policy is active at first"
    ui.open_tab(page, "Train", "training pair")
    # The active policy reads at a glance; what was measured of it is one fold away.
    assert page.get_by_role("combobox", name="Active policy").input_value() == "shipped policy pick-place-cpu"
    ui.click(page.get_by_text("About the active policy"))
    page.get_by_text(shipped.summary[:60]).filter(visible=True).first.wait_for(timeout=30_000)
    page.get_by_text(re.compile(r"demonstrations? × \d+ agent episodes? of cube->red")).filter(
        visible=True
    ).first.wait_for(timeout=60_000)
    ui.click(page.get_by_role("button", name="Fine-tune the active policy on my episodes"))
    page.get_by_text("ended: finished").filter(visible=True).first.wait_for(timeout=600_000)
    ui.shot(page, shots / "loop-fine-tuned.png")
    ui.click(page.get_by_role("button", name="Make it the active policy"))
    page.get_by_text("is the active policy of pick_place").filter(visible=True).first.wait_for(timeout=60_000)
    active = studio.runs.active("pick_place")
    assert active is not None and active.id != shipped.id and active.run_id is not None
    # 4. Imitate: plan the task with the fine-tuned policy, from the demonstration recorded by clicking.
    ui.open_tab(page, "Imitate", "Plan")
    im = tab.imitate
    ui.choose(page, "Task", TASK, lambda: im.task_name == TASK, "the task")
    ui.wait(lambda: active.id in im.policy.content, 30, "the fine-tuned policy on the policy line")
    option = f"{mine.id} · teleop · sawyer"
    ui.wait(
        lambda: option in im.demo.options, 30, "the clicked demonstration listed", lambda: im.demo.options
    )
    ui.choose(page, "Demonstration", option, lambda: im.demo_id() == mine.id, "the clicked demonstration")
    before_job = im.plan_job
    ui.click(page.get_by_role("button", name="Plan", exact=True))
    job = ui.wait(lambda: im.plan_job is not before_job and im.plan_job, 30, "a new plan job")
    assert job.spec["checkpoint"] == active.path
    page.get_by_text("Planned in").filter(visible=True).first.wait_for(timeout=120_000)
    assert im.plan_wps is not None and im.plan_wps.shape == (5, 4) and np.isfinite(im.plan_wps).all()
    ui.shot(page, shots / "loop-planned.png")
