"""Imitating a held-out Meta-World task in a real browser, as a person does it: choose the task in the Imitate tab,
make a scripted demonstration, plan with the shipped `metaworld-cpu` policy, execute, and read the outcome.

The rollout runs as `studio results` measures the shipped policy (the paper's protocol): choosing a hard task sets
*Re-plans* to 3 and says that each plan executes at most 500 control ticks, and the rollout is bounded so. One
in-process studio on an empty store; every step is a click or a choice in the page.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import browser_support as ui

from studio.sim.env import WORKSPACE

TASK = "metaworld/door-unlock-v3"
EASY = "metaworld/button-press-v3"

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(600)]


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("studio") / "data"


def drawn_plan(studio) -> np.ndarray:
    """Where the scene draws the plan's five waypoint spheres (5, 3)."""
    nodes = {h.name: np.asarray(h.position) for h in ui.tab(studio).view._overlays["plan"]}
    return np.array([nodes[f"/overlay/plan/wp{i}"] for i in range(5)])


def test_a_held_out_meta_world_task_runs_under_the_papers_protocol(studio, page, shots):
    im = ui.tab(studio).imitate
    ui.open_tab(page, "Imitate", "Choose a")
    # An easy task first: one attempt, no re-plans.
    easy = EASY + " (held-out)"
    ui.choose(page, "Task", easy, lambda: im.task.value == easy, "the easy task", lambda: im.task.value)
    page.get_by_text("one attempt, no re-plans").filter(visible=True).first.wait_for(timeout=30_000)
    field = page.get_by_role("textbox", name="Re-plans").filter(visible=True).first
    ui.wait(lambda: field.input_value() == "0", 30, "Re-plans 0 in the page", field.input_value)
    label = TASK + " (held-out)"
    ui.choose(page, "Task", label, lambda: im.task.value == label, "the hard task", lambda: im.task.value)
    note = page.get_by_text("3 re-plans; each plan executes at most 500 control ticks").filter(visible=True)
    note.first.wait_for(timeout=30_000)
    ui.wait(lambda: field.input_value() == "3", 30, "Re-plans 3 in the page", field.input_value)
    page.get_by_text("metaworld-cpu").filter(visible=True).first.wait_for(
        timeout=30_000
    )  # the shipped policy
    ui.click_and_see(
        page, page.get_by_role("button", name="Make a scripted demonstration"), "stored and selected"
    )
    assert "scripted" in im.demo.value
    ui.click(page.get_by_role("button", name="Plan", exact=True))
    page.get_by_text("Planned in").filter(visible=True).first.wait_for(timeout=120_000)
    assert im.plan_wps is not None and im.plan_wps.shape == (5, 4) and np.isfinite(im.plan_wps).all()
    # The spheres stand where the controller sends the arm; what the model put outside the workspace is said.
    with np.load(studio.data_dir / im.plan_job.result["path"]) as data:
        predicted = data["waypoints_world"]
    assert ((im.plan_wps[:, :3] >= WORKSPACE[0]) & (im.plan_wps[:, :3] <= WORKSPACE[1])).all(), im.plan_wps
    spheres = drawn_plan(studio)
    assert np.allclose(spheres, im.plan_wps[:, :3], atol=1e-5), spheres
    # This guided plan extrapolates: its waypoints lie below the table and past the far edge (tens of centimetres).
    out = np.flatnonzero(np.linalg.norm(predicted[:, :3] - im.plan_wps[:, :3], axis=1) > 0.01)
    assert len(out) >= 3, (predicted, im.plan_wps)
    page.get_by_text("outside the workspace").filter(visible=True).first.wait_for(timeout=30_000)
    assert (
        f"waypoints {', '.join(str(i + 1) for i in out[:-1])} and {out[-1] + 1} outside" in im.status.content
    )
    ui.drawn(page)
    ui.shot(page, shots / "metaworld-plan.png", scroll_to="outside the workspace")
    fast = "as fast as possible"
    ui.choose(page, "Speed", fast, lambda: im.speed.value == fast, "the speed", lambda: im.speed.value)
    ui.click(page.get_by_role("button", name="Execute", exact=True))
    ui.wait(lambda: im.rollout is not None, 30, "the rollout", lambda: im.status.content)
    page.get_by_text("✔ Success").or_(page.get_by_text("✘ Failed at")).filter(visible=True).first.wait_for(
        timeout=240_000
    )
    result = ui.wait(lambda: im.rollout.result, 30, "the rollout's result")
    ui.drawn(page)
    ui.shot(
        page, shots / "metaworld-outcome.png", scroll_to="✔ Success" if result["success"] else "✘ Failed at"
    )
    assert im.rollout.spec["replans"] == 3 and result["plan_ticks"] == 500, result
    assert result["replans"] <= 3
    (row,) = [r for r in studio.store.catalog.rollouts(task=TASK) if r.id == result["rollout_id"]]
    assert row.extra["plan_ticks"] == 500
    # Every plan executed at most 500 control ticks (planning takes none).
    with np.load(Path(row.path) / "plans.npz") as plans:
        starts = [int(t) for t in plans["plan_start_ticks"]]
    assert len(starts) == result["replans"] + 1
    ends = [*starts[1:], row.num_steps - 1]
    assert all(0 < e - s <= 500 for s, e in zip(starts, ends)), (starts, row.num_steps)
    # Inspect replays it with the plan where the arm was sent, and says which waypoints the model put outside.
    ins = ui.tab(studio).inspector
    ui.open_tab(page, "Inspect", "Every rollout")
    ui.wait(lambda: any(o.startswith(row.id) for o in ins.rollout.options), 30, "the rollout listed")
    option = next(o for o in ins.rollout.options if o.startswith(row.id))
    if ins.rollout.value != option:
        ui.choose(
            page,
            "Rollout",
            option,
            lambda: ins.rollout.value == option,
            "the rollout",
            lambda: ins.rollout.value,
        )
    ui.click_and_see(page, page.get_by_role("button", name="Open", exact=True).first, "Stages:")
    ins.timeline.slider.value = 1
    ui.wait(lambda: "Plan 1 of" in ins.plan_info.content, 30, "the first plan", lambda: ins.plan_info.content)
    assert "outside the workspace" in ins.plan_info.content, ins.plan_info.content
    drawn = drawn_plan(studio)
    with np.load(Path(row.path) / "plans.npz") as plans:
        assert np.allclose(drawn, plans["plan0_waypoints_commanded"][:, :3], atol=1e-5)
        assert np.allclose(plans["plan0_waypoints_commanded"], im.plan_wps)  # the plan Imitate drew
    ui.shot(page, shots / "metaworld-inspect.png", scroll_to="outside the workspace")
