"""A newcomer's walkthrough: one browser tab on a fresh studio, Teleop → Data → Train → Imitate → Inspect → Compare
with the default choices only (the buttons each tab offers, never a changed dropdown or number).

Nothing may show a red notification, and no ``studio.*`` logger may write an ERROR line on the server. Each
step's problems are collected and the test fails at the end with all of them, so that one broken tab does not
hide what the next ones do.
"""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import browser_support as ui

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(3600)]


class _Errors(logging.Handler):
    """ERROR (and worse) records of the ``studio`` loggers."""

    def __init__(self):
        super().__init__(level=logging.ERROR)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(f"{record.levelname} {record.name}: {record.getMessage().splitlines()[0]}")


def _job_done(
    studio, kind: str, after: tuple[float, int], timeout: float, what: str, notes: list, state=None
):
    """The first ``kind`` job submitted ``after`` a click, once it is finished. Fails at once if a red notification
    comes first (the panel refused), and within two minutes if no such job is queued. ``after``: the time and the
    number of notifications before the click."""
    since, seen = after

    def jobs():
        return [j for j in studio.hub.jobs.jobs() if j.kind == kind and j.submitted_at >= since]

    def refused() -> str | None:
        return next((f"{t}: {b}" for t, b, e in notes[seen:] if e), None)

    def describe() -> str:
        return f"jobs {[(j.kind, j.state, j.reason) for j in studio.hub.jobs.jobs()]}" + (
            f"; the panel shows {state()!r}" if state else ""
        )

    ui.wait(lambda: jobs() or refused(), 120, f"a {kind} job to be queued", describe)
    if not jobs():
        raise AssertionError(f"no {kind} job: {refused()}")
    return ui.wait(lambda: jobs()[0] if jobs()[0].terminal else None, timeout, what, describe)


def test_a_newcomer_goes_through_every_tab_with_the_defaults(tmp_path, monkeypatch):
    from studio.ui.app import StudioTab

    notes: list[tuple[str, str, bool]] = []
    notify = StudioTab.notify

    def recorded(self, title, body, error=False, seconds=None):
        notes.append((title, body, error))
        notify(self, title, body, error, seconds)

    monkeypatch.setattr(StudioTab, "notify", recorded)
    errors = _Errors()
    logging.getLogger("studio").addHandler(errors)
    problems: list[str] = []
    shots = tmp_path / "screenshots"
    shots.mkdir()
    try:
        with ui.running_studio(tmp_path / "data") as studio, ui.open_page(studio) as page:
            tab = ui.tab(studio)

            def step(name: str, action) -> None:
                """Run one step; what went wrong (a failed wait, a red notification, an ERROR line) is kept."""
                seen_notes, seen_errors = len(notes), len(errors.lines)
                try:
                    action()
                except (
                    AssertionError,
                    TimeoutError,
                    Exception,
                ) as e:  # the walkthrough goes on to the next tab
                    problems.append(f"{name}: {type(e).__name__}: {str(e).splitlines()[0][:400]}")
                finally:
                    ui.shot(page, shots / f"{name.lower()}.png")
                problems.extend(f"{name}: red notification {t!r}: {b}" for t, b, e in notes[seen_notes:] if e)
                problems.extend(f"{name}: server log {line}" for line in errors.lines[seen_errors:])

            def teleop() -> None:
                tp = tab.teleop
                ui.click_and_wait(
                    page.get_by_role("button", name="Record"),
                    lambda: ui.wait(lambda: tp._recording, 60, "the recording", lambda: ui.teleop_state(tab)),
                )
                start = tp.client.latest_pose()
                ee = np.asarray(start.ee_pos, dtype=float)
                x, y = ui.screen_point(page, tab.client, ee + np.array([0.0, 0.0, 0.05]))
                page.mouse.move(x, y)
                page.mouse.down()
                for i in range(1, 16):
                    page.mouse.move(x, y - 3 * i)
                    page.wait_for_timeout(50)
                page.mouse.up()
                ui.wait(
                    lambda: tp.drags > 0, 20, "the drag to reach the studio", lambda: ui.teleop_state(tab)
                )
                ui.stop_and_save(page, tab)

            def data() -> None:
                ui.open_tab(page, "Data", "1 episode")
                ui.click_and_wait(
                    page.get_by_role("button", name="Open", exact=True),
                    lambda: ui.wait(lambda: tab.mode == "replay", 60, "the episode replayed"),
                )

            def train() -> None:
                # With the defaults there is one unsuccessful demonstration and no agent episode: nothing to
                # train on. Train says what to record, and Start waits for it instead of failing.
                ui.open_tab(page, "Train", "is the paper's model")
                page.get_by_text("Start needs at least one training pair: record").filter(
                    visible=True
                ).first.wait_for(timeout=60_000)
                start = page.get_by_role("button", name="Start training")
                ui.wait(start.is_disabled, 30, "Start to wait for training pairs")

            def imitate() -> None:
                im = tab.imitate
                ui.open_tab(page, "Imitate", "held-out ones were never trained on")
                if im.demo.value == "(none)" or im.demo.value.startswith("("):
                    since = time.time(), len(notes)
                    ui.click(page.get_by_role("button", name="Make a scripted demonstration"))
                    job = _job_done(studio, "expert", since, 300, "the scripted demonstration", notes)
                    assert job.state == "succeeded", f"scripted demonstration {job.state}: {job.reason}"
                    ui.wait(
                        lambda: not im.demo.value.startswith("("),
                        30,
                        "the scripted demonstration to be chosen",
                        lambda: im.demo.options,
                    )
                since = time.time(), len(notes)
                ui.click(page.get_by_role("button", name="Plan", exact=True))
                job = _job_done(studio, "plan", since, 300, "the plan", notes, lambda: im.status.content)
                assert job.state == "succeeded", f"plan {job.state}: {job.reason}"
                since = time.time(), len(notes)
                ui.click(page.get_by_role("button", name="Execute", exact=True))
                job = _job_done(
                    studio, "rollout", since, 600, "the rollout", notes, lambda: im.status.content
                )
                assert job.state == "succeeded", f"rollout {job.state}: {job.reason}"

            def inspect() -> None:
                ins = tab.inspector
                ui.open_tab(page, "Inspect", "Every rollout")
                ui.wait(lambda: not ins.rollout.value.startswith("("), 30, "a rollout listed")
                ui.click_and_wait(
                    page.get_by_role("button", name="Open", exact=True),
                    lambda: ui.wait(lambda: ins.record is not None, 90, "the rollout replayed"),
                )

            def compare() -> None:
                ui.open_tab(page, "Compare", "Run two checkpoints on the")
                since = time.time(), len(notes)
                ui.click(page.get_by_role("button", name="Start", exact=True))
                job = _job_done(
                    studio,
                    "compare",
                    since,
                    1500,
                    "the comparison",
                    notes,
                    lambda: tab.compare.status.content,
                )
                assert job.state == "succeeded", f"comparison {job.state}: {job.reason}"

            for name, action in (
                ("Teleop", teleop),
                ("Data", data),
                ("Train", train),
                ("Imitate", imitate),
                ("Inspect", inspect),
                ("Compare", compare),
            ):
                step(name, action)
    finally:
        logging.getLogger("studio").removeHandler(errors)
        print(f"\nscreenshots: {shots}")
    assert not problems, "the walkthrough met problems:\n" + "\n".join(problems)
