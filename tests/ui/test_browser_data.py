"""The Data tab in a real browser: collect scripted episodes from the page into an empty dataset.

Real clicks tick a task, set *Episodes per task*, press **Start collecting** (twice at once: one job), follow the
progress line and bar while the counts table grows, and **Cancel collecting** a longer run mid-way (the episodes
stored stay). Screenshots go to the test's temporary directory (printed at the end).
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import browser_support as ui

TASK = "pick_place/cube->red"
pytestmark = [pytest.mark.browser, pytest.mark.timeout(420)]


def _collect_jobs(studio) -> list:
    return [s for s in studio.hub.jobs.jobs() if s.kind == "collect"]


def _set_episodes(page, data, n: int) -> None:
    field = page.get_by_role("textbox", name="Episodes per task")
    for _ in range(3):
        field.fill(str(n))
        field.press("Tab")
        try:
            ui.wait(lambda: int(data.c_episodes.value) == n, 10, f"episodes per task = {n}")
            return
        except AssertionError:
            continue
    raise AssertionError(f"the page did not take {n} episodes per task (value {data.c_episodes.value})")


def _counted(data) -> int:
    """The scripted expert episodes of TASK the counts table shows."""
    m = re.search(rf"\| {re.escape(TASK)} \| (\d+) scripted", data.table.content)
    return int(m.group(1)) if m else 0


def _state(data) -> str:
    return f"status {data.c_status.content!r}, table {data.table.content!r}, tab actions {data.tab.actions}"


@pytest.mark.slow
def test_collect_scripted_episodes_from_the_data_tab(studio, page, shots):
    tab = ui.tab(studio)
    data = tab.datasets
    ui.open_tab(page, "Data", "The dataset is empty")
    assert "Start collecting" in data.table.content  # the empty dataset points at the button
    assert (data.c_scene.value, data.c_robot.value, data.c_role.value) == ("pick_place", "sawyer", "expert")
    assert page.get_by_role("checkbox", name="bar->blue (held-out)").is_visible()
    start = page.get_by_role("button", name="Start collecting")
    # Nothing ticked: refused with the field named, nothing queued.
    ui.click_and_see(page, start, "tasks: tick at least one task")
    assert not _collect_jobs(studio)

    box = page.get_by_role("checkbox", name="cube->red", exact=True)
    for _ in range(3):  # a click lost on a loaded machine is clicked again; one that landed is not undone
        if data.selected_tasks() != [TASK]:
            ui.click(box)
        try:
            ui.wait(lambda: data.selected_tasks() == [TASK], 10, "the task to be ticked")
            break
        except AssertionError:
            continue
    assert data.selected_tasks() == [TASK]
    _set_episodes(page, data, 2)

    # A double-click on Start collecting queues one job.
    clicks = []
    on_start = data._on_start
    data._on_start = lambda: (clicks.append(1), on_start())
    ui.double_click(page, start)
    ui.wait(lambda: _collect_jobs(studio), 30, "the collect job to be queued", lambda: _state(data))
    page.get_by_text("2 of 2 episodes stored (2 new)").filter(visible=True).first.wait_for(timeout=120_000)
    assert len(_collect_jobs(studio)) == 1, (
        f"a double-click ({len(clicks)} clicks heard) queued two collections"
    )
    data._on_start = on_start
    (job,) = _collect_jobs(studio)
    assert job.state == "succeeded" and job.spec["tasks"] == [TASK] and job.spec["episodes"] == 2
    page.get_by_text("2 scripted").filter(visible=True).first.wait_for(timeout=30_000)  # the counts table
    assert "| pick_place/cube->red | 2 scripted | — |" in data.table.content
    assert data.c_progress.value == 100.0 and data.c_progress.visible
    metas = studio.store.episodes()
    assert len(metas) == 2 and {(m.task, m.role, m.source, m.embodiment) for m in metas} == {
        (TASK, "expert", "scripted", "sawyer")
    }
    ui.shot(page, shots / "data-collected.png", scroll_to="Start collecting")

    # A longer run of the same seed resumes after the two, shows its progress while the table grows, and is
    # cancelled mid-way from the page.
    _set_episodes(page, data, 120)
    ui.click_and_wait(start, lambda: ui.wait(lambda: len(_collect_jobs(studio)) == 2, 20, "a second job"))
    running = re.compile(r"running\W+episode (\d+) of 120")
    ui.wait(
        lambda: (m := running.search(data.c_status.content)) and int(m.group(1)) >= 5,
        120,
        "episode 5 of 120",
        lambda: _state(data),
    )
    page.get_by_text(re.compile(r"episode \d+ of 120")).filter(visible=True).first.wait_for(timeout=30_000)
    assert page.get_by_role("button", name="Start collecting").is_disabled(), "no second run while one runs"
    ui.wait(lambda: _counted(data) > 2, 30, "the counts table to grow", lambda: _state(data))
    assert 0 < data.c_progress.value < 100
    ui.shot(page, shots / "data-collecting.png", scroll_to="Cancel collecting")
    ui.click_and_see(page, page.get_by_role("button", name="Cancel collecting"), "cancelled")
    second = _collect_jobs(studio)[-1]
    ui.wait(lambda: "kept" in data.c_status.content, 30, "the cancelled run's counts", lambda: _state(data))
    stored = studio.store.episodes()
    assert second.state == "cancelled" and 5 <= len(stored) < 120
    made = len(stored) - 2
    assert f"{made} new episodes kept ({len(stored)} of 120 stored); {120 - len(stored)} not made" in (
        data.c_status.content
    )
    assert {m.collect_index for m in stored} == set(range(len(stored)))  # the slots in order, none half-made
    page.get_by_text(f"{len(stored)} scripted").filter(visible=True).first.wait_for(timeout=30_000)
    assert not page.get_by_role("button", name="Start collecting").is_disabled()
    ui.shot(page, shots / "data-cancelled.png", scroll_to="Cancel collecting")
    ui.shot(page, shots / "data-counts.png", scroll_to=f"{len(stored)} episodes: ")
    print(f"\nthe double-click reached the server as {len(clicks)} clicks")
