"""The Train tab on what a user has, in a real browser: the pair count and why episodes are left out (following the
store as it changes), Steps proposed for the pairs with the batch lowered to them, Start queueing one job however
fast it is clicked, Fine-tune refusing a task set without pairs before anything queues, then fine-tuning the active
policy and making the result the active policy.

The store holds tiny synthetic episodes and the first run trains a tiny network (``TINY``) through Start; made
active, it is the policy Fine-tune starts from, so that the fine-tune takes seconds here.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import browser_support as ui
from browser_support import running_studio

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "data"))
from data_fixtures import make_recording
from tiny_network import TINY

RED, GREEN, BLUE, HELD = (
    "pick_place/cube->red",
    "pick_place/cube->green",
    "pick_place/cube->blue",
    "pick_place/bar->blue",
)

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(600)]


@pytest.fixture(scope="module")
def studio(tmp_path_factory):
    from studio.data.store import EpisodeStore

    root = tmp_path_factory.mktemp("studio") / "data"
    with EpisodeStore(root) as store:  # what a person recorded in Teleop: one pair, and three left out
        add = store.add_episode
        add(make_recording(task=RED, robot="sawyer", seed=0), role="expert", source="teleop")
        add(make_recording(task=RED, robot="panda", seed=1), role="agent", source="teleop")
        add(make_recording(task=RED, robot="panda", seed=2, success=False), role="agent", source="teleop")
        add(make_recording(task=GREEN, robot="sawyer", seed=3), role="expert", source="teleop")
        add(make_recording(task=HELD, robot="sawyer", seed=4), role="expert", source="teleop")
    with running_studio(root) as app:
        yield app


def _train_jobs(studio) -> list:
    return [s for s in studio.hub.jobs.jobs() if s.kind == "train"]


def _state(train) -> str:
    return f"pairs {train.pairs.content!r}; plan {train.plan.content!r}; state {train.state.content!r}"


def test_the_pairs_and_why_episodes_are_left_out_follow_the_store(studio, page, shots):
    tab = ui.tab(studio)
    train = tab.train
    ui.open_tab(page, "Train", "Left out:")
    page.get_by_text("1 training pair").filter(visible=True).first.wait_for(timeout=30_000)
    for reason in (
        "1 failed episode (success unticked)",
        "1 demonstration of cube->green: no agent episodes of the task to pair with",
        "1 episode of held-out tasks (bar->blue): never trained on",
    ):
        page.get_by_text(reason).filter(visible=True).first.wait_for(timeout=10_000)
    # the cpu preset's batch of 16 lowered to the one pair; Steps is its 10 epochs, not 0
    page.get_by_text("batch size 16 lowered to 1: there is only 1 training pair").filter(
        visible=True
    ).first.wait_for(timeout=10_000)
    assert int(train.steps.value) == 10
    assert page.get_by_role("textbox", name="Steps").input_value() == "10"
    ui.shot(page, shots / "train-pairs.png")

    # a Panda episode of cube->green recorded meanwhile pairs with its demonstration
    studio.store.add_episode(make_recording(task=GREEN, robot="panda", seed=5), role="agent", source="teleop")
    studio.dataset_changed()
    page.get_by_text("2 training pairs").filter(visible=True).first.wait_for(timeout=30_000)
    assert "cube->green: no agent episodes" not in train.pairs.content
    ui.wait(lambda: int(train.steps.value) == 10, 10, "Steps for 2 pairs at batch 2", lambda: _state(train))


def test_fine_tune_without_pairs_says_what_to_record_before_anything_queues(studio, page):
    train = ui.tab(studio).train
    for task, box in train._task_boxes.items():
        box.value = task == BLUE  # a task nobody recorded
    page.get_by_text("0 training pairs").filter(visible=True).first.wait_for(timeout=30_000)
    before = len(_train_jobs(studio))
    ui.click(page.get_by_role("button", name="Fine-tune the active policy on my episodes"))
    # The note says what to record before any click ("Starts from …. No training pairs yet: …"); only the handled
    # click marks it ✘. Waiting for the sentence alone let a click still on its way to the server through: it then
    # arrived after the tasks below were chosen again and queued a fine-tune that held later tests' Start disabled.
    ui.wait(
        lambda: train.fine_tune_note.content.startswith("✘ No training pairs yet"),
        30,
        "the click to be refused",
        lambda: _state(train),
    )
    page.get_by_text(
        "record a successful demonstration (Sawyer or hand) and a successful agent (Panda)"
    ).filter(visible=True).first.wait_for(timeout=30_000)
    ui.wait(lambda: not ui.tab(studio).actions, 30, "the refused click to be handled")
    assert len(_train_jobs(studio)) == before and train.job_id is None
    for task, box in train._task_boxes.items():
        box.value = task in (RED, GREEN)
    page.get_by_text("2 training pairs").filter(visible=True).first.wait_for(timeout=30_000)


def test_a_double_click_on_start_queues_one_job_whose_result_becomes_active(studio, page, shots):
    tab = ui.tab(studio)
    train = tab.train
    train.overrides.value = "; ".join(TINY)
    page.get_by_text("batch size 16 lowered to 2").filter(visible=True).first.wait_for(timeout=30_000)
    train.steps.value = 4
    page.get_by_text("Start: 4 steps of batch 2").filter(visible=True).first.wait_for(timeout=30_000)
    ui.wait(lambda: not train.start.disabled, 30, "Start to be enabled", lambda: _state(train))
    ui.double_click(page, page.get_by_role("button", name="Start training"))
    page.get_by_text("ended: finished").filter(visible=True).first.wait_for(timeout=300_000)
    ui.wait(lambda: not tab.actions, 30, "both clicks to be handled")
    jobs = _train_jobs(studio)
    assert len(jobs) == 1, [j.job for j in jobs]
    assert not jobs[0].spec.get("fine_tune"), "the presses reached Fine-tune, not Start"
    job = jobs[0].job
    assert train.job_id == job and (studio.data_dir / "runs" / job / "last.pt").is_file()
    ui.wait(lambda: len(train.loss_plot.data[0]) == 4, 30, "the loss curve", lambda: _state(train))
    assert np.isfinite(train.loss_plot.data[1]).all()
    page.get_by_text("step 4/4 · loss").filter(visible=True).first.wait_for(timeout=10_000)
    assert "ETA" not in train.state.content  # an ended run has no time left
    ui.shot(page, shots / "train-tiny-run.png")
    ui.shot(page, shots / "train-tiny-curves.png", scroll_to="Learning rate")

    ui.click(page.get_by_role("button", name="Make it the active policy"))
    ui.wait(
        lambda: studio.runs.active("pick_place").run_id == job,
        30,
        "the run to be active",
        lambda: _state(train),
    )
    page.get_by_text("is the active policy of pick_place").filter(visible=True).first.wait_for(timeout=30_000)
    combo = page.get_by_role("combobox", name="Active policy")
    ui.wait(lambda: combo.input_value().startswith(f"run {job} — last.pt"), 30, "the Active policy choice")


def test_fine_tune_the_active_policy_and_make_the_result_active(studio, page, shots):
    tab = ui.tab(studio)
    train = tab.train
    first = studio.runs.active("pick_place")
    assert first.run_id is not None
    page.get_by_text(f"Starts from run {first.run_id}").filter(visible=True).first.wait_for(timeout=30_000)
    page.get_by_text("and trains on your 2 demonstrations × 2 agent episodes").filter(
        visible=True
    ).first.wait_for(timeout=30_000)
    page.get_by_text("20 steps of batch 2").filter(visible=True).first.wait_for(timeout=10_000)
    ui.click(page.get_by_role("button", name="Fine-tune the active policy on my episodes"))
    ui.wait(lambda: len(_train_jobs(studio)) == 2, 60, "the fine-tuning job", lambda: _state(train))
    page.get_by_text("step 20/20 · loss").filter(visible=True).first.wait_for(timeout=300_000)
    page.get_by_text("ended: finished at step 20").filter(visible=True).first.wait_for(timeout=60_000)
    tuned = train.job_id
    assert tuned != first.run_id
    spec = next(j.spec for j in _train_jobs(studio) if j.job == tuned)
    assert spec["fine_tune"] is True and spec["init"] == first.path
    ui.shot(page, shots / "train-fine-tuned.png")

    ui.click(page.get_by_role("button", name="Make it the active policy"))
    ui.wait(lambda: studio.runs.active("pick_place").run_id == tuned, 30, "the fine-tuned run to be active")
    page.get_by_text("is the active policy of pick_place: plan with it in Imitate").filter(
        visible=True
    ).first.wait_for(timeout=30_000)
    assert f"`{tuned}/last` is the active policy" in train.state.content
    ui.wait(lambda: not train.make_active.visible, 10, "the button to go once done")
    page.get_by_text("fine-tune").filter(visible=True).first.wait_for(
        timeout=30_000
    )  # the runs table names the run's kind
    ui.shot(page, shots / "train-made-active.png", scroll_to="Active policy")


def test_a_cancelled_run_stops_its_clock_and_keeps_its_step(studio, page):
    tab = ui.tab(studio)
    train = tab.train
    train.steps.value = 5000
    page.get_by_text("Start: 5000 steps of batch 2").filter(visible=True).first.wait_for(timeout=30_000)
    ui.click(page.get_by_role("button", name="Start training"))
    ui.wait(lambda: len(_train_jobs(studio)) == 3, 60, "the long run", lambda: _state(train))
    job = train.job_id
    page.get_by_text(" · ETA ").filter(visible=True).first.wait_for(timeout=120_000)
    tracked = studio.jobs.get(job)
    ui.wait(
        lambda: tracked.progress and tracked.progress.step >= 3, 120, "three steps", lambda: _state(train)
    )
    ui.click(page.get_by_role("button", name="Cancel"))
    page.get_by_text("ended: cancelled").filter(visible=True).first.wait_for(timeout=120_000)
    assert "ETA" not in train.state.content and "pairs/s" not in train.state.content
    (run,) = [r for r in studio.runs.runs() if r.id == job]
    assert run.ended == "cancelled" and run.step >= 3
    short = job.removeprefix("train-")
    ui.wait(
        lambda: f"`{short}` | cpu | {run.step}/5000 | cancelled |" in train.runs_table.content,
        30,
        "the runs table row",
        lambda: train.runs_table.content,
    )
    page.get_by_text(f"{run.step}/5000").filter(visible=True).first.wait_for(timeout=30_000)


def test_a_failed_run_says_so_in_the_runs_table(studio, page):
    tab = ui.tab(studio)
    train = tab.train
    train.overrides.value = "; ".join(
        [*TINY, "model.n_expert_frames=1"]
    )  # the trainer refuses: N must be ≥ 2
    train.steps.value = 4
    page.get_by_text("Start: 4 steps of batch 2").filter(visible=True).first.wait_for(timeout=30_000)
    ui.click(page.get_by_role("button", name="Start training"))
    ui.wait(lambda: len(_train_jobs(studio)) == 4, 60, "the run", lambda: _state(train))
    job = train.job_id
    page.get_by_text("must be at least 2").filter(visible=True).first.wait_for(timeout=120_000)
    short = job.removeprefix("train-")
    ui.wait(
        lambda: f"`{short}` | cpu | 0 | failed |" in train.runs_table.content,
        30,
        "the failed run's row",
        lambda: train.runs_table.content,
    )
