"""What the panels say to a person: counts in the right number, one age per worker, notifications that close,
an upload's frame rate and its rejection in plain sentences."""

import threading
import time
from types import SimpleNamespace

from studio.backend import messages as msg
from studio.backend.presence import WorkerEntry
from studio.ui.panels.datasets import counts_table
from studio.ui.panels.upload import UPLOAD_FPS_CAP, describe_import
from studio.ui.panels.workers import WorkersPanel


def test_one_episode_is_one_episode():
    meta = SimpleNamespace(task="pick_place/cube->red", role="expert", source="teleop")
    assert "1 episode: 1 expert, 0 agent." in counts_table([meta])
    assert "2 episodes: 2 expert, 0 agent." in counts_table([meta, meta])


def _status(worker: str, kind: str, started_at: float) -> msg.WorkerStatus:
    return msg.WorkerStatus(
        worker=worker,
        kind=kind,
        host="box",
        pid=7,
        state="idle",
        activity="idle",
        job_kinds=("plan",),
        unavailable={},
        job=None,
        sessions=0,
        started_at=started_at,
        updated_at=started_at,
    )


def test_each_worker_row_says_how_long_that_worker_has_been_up():
    now = time.time()
    entries = [
        WorkerEntry("sim", "sim-a", _status("sim-a", "sim", now - 40 * 60), now),
        WorkerEntry("train", "train-a", _status("train-a", "train", now - 30), now),
    ]
    panel = WorkersPanel.__new__(WorkersPanel)
    panel.tab = SimpleNamespace(
        app=SimpleNamespace(hub=SimpleNamespace(directory=SimpleNamespace(workers=lambda: entries)))
    )
    text = panel.describe()
    rows = {line.split("|")[2].strip(" `"): line for line in text.splitlines() if "`" in line}
    assert rows["sim-a"].rstrip(" |").endswith("40\u00a0min") and rows["train-a"].rstrip(" |").endswith(
        "30\u00a0s"
    )
    assert "2 workers on the bus." in text and "min, " not in text
    entries.pop()
    assert "1 worker on the bus." in panel.describe()


def test_an_upload_says_when_its_frame_rate_was_lowered():
    meta = SimpleNamespace(
        num_frames=31, fps=10.0, width=320, height=240, extra={"source_fps": 20.0, "fit": "letterbox"}
    )
    text = describe_import("hand.mp4", meta)
    assert "31 frames at 10 fps (resampled from the video's 20 fps" in text
    assert f"at most {UPLOAD_FPS_CAP:.0f} a second" in text
    meta.extra["source_fps"], meta.fps = 10.0, 10.0
    assert "resampled" not in describe_import("hand.mp4", meta)


class _Notice:
    def __init__(self, shown: list, title: str):
        self.shown, self.title = shown, title
        shown.append(self)

    def remove(self) -> None:
        self.shown.remove(self)


class _Client:
    client_id = 1

    def __init__(self):
        self.shown: list[_Notice] = []
        self.closing: dict[str, float | None] = {}

    def add_notification(self, title, body, color=None, auto_close_seconds=None):
        self.closing[title] = auto_close_seconds
        return _Notice(self.shown, title)


def test_error_notifications_close_by_themselves_and_never_pile_up():
    from studio.ui import app as app_module
    from studio.ui.app import StudioTab

    tab = StudioTab.__new__(StudioTab)
    tab.client = _Client()
    tab._notices, tab._notices_lock = {}, threading.Lock()
    for title in ("Planning failed", "Planning failed", "Video rejected", "No rollout", "Not saved yet"):
        tab.notify(title, "why", error=True)
    titles = [n.title for n in tab.client.shown]
    assert titles == ["No rollout", "Not saved yet"], titles
    assert all(s == app_module.ERROR_SECONDS for s in tab.client.closing.values())
    tab.notify("Episode saved", "fine")  # news beside the errors, closing sooner
    assert [n.title for n in tab.client.shown][-1] == "Episode saved"
    assert tab.client.closing["Episode saved"] == app_module.NOTICE_SECONDS < app_module.ERROR_SECONDS
    assert len(tab.client.shown) == 3
    # However long ago an error was shown (its browser timer may be paused, e.g. while the pointer is on it),
    # the next one of its title replaces it.
    tab._notices = {t: (h, at - 3600.0, e) for t, (h, at, e) in tab._notices.items()}
    tab.notify("No rollout", "still none", error=True)
    assert [n.title for n in tab.client.shown].count("No rollout") == 1
