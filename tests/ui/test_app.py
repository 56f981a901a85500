"""StudioTab.run: one action at a time per tab, queued actions announced, failures notified."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

from studio.ui.app import StudioTab


class _Client:
    client_id = 7

    def __init__(self):
        self.notes: list[tuple[str, str, str | None]] = []

    def add_notification(self, title, body, color=None, auto_close_seconds=None):
        self.notes.append((title, body, color))


def _bare_tab() -> StudioTab:
    """A StudioTab with only what run() uses (no viser server, no panels)."""
    tab = StudioTab.__new__(StudioTab)
    tab.client = _Client()
    tab._closed = threading.Event()
    tab._executor = ThreadPoolExecutor(max_workers=1)
    tab._actions, tab._actions_lock = [], threading.Lock()
    tab._notices, tab._notices_lock = {}, threading.Lock()
    tab.app = SimpleNamespace(note_change=lambda: None)
    return tab


def _finished(tab: StudioTab) -> None:
    """Wait until every action the tab took so far has finished: its executor runs them in order, one at a time."""
    tab._executor.submit(lambda: None).result(timeout=5)


def test_a_queued_action_is_announced_and_runs_after_the_first():
    tab = _bare_tab()
    release, order = threading.Event(), []
    tab.run(lambda: (release.wait(5), order.append("slow")), "opening the session")
    assert tab.actions == ("opening the session",)  # taken at once, before it runs
    assert tab.client.notes == []  # nothing ahead of the first one
    tab.run(lambda: order.append("save"), "saving the episode")
    assert tab.actions == ("opening the session", "saving the episode")
    assert tab.client.notes == [("Waiting", "saving the episode starts after opening the session", None)]
    release.set()
    _finished(tab)
    assert tab.actions == ()
    assert order == ["slow", "save"]
    tab._executor.shutdown()


def test_a_failing_action_is_notified_and_leaves_the_queue():
    tab = _bare_tab()

    def fail():
        raise ValueError("no demonstration of pick_place/bar->blue yet")

    tab.run(fail, "planning")
    _finished(tab)
    assert tab.actions == ()
    (title, body, color), *_ = tab.client.notes
    assert title == "Could not finish planning" and "no demonstration" in body and color == "red"
    tab._closed.set()
    tab.run(lambda: None, "after close")  # a closed tab takes no more actions
    assert tab.actions == ()
    tab._executor.shutdown()
