"""The browser studio: the hub, its workers, the viser server, and one :class:`StudioTab` per browser tab.

:class:`StudioApp` owns what exists once: the :class:`~studio.backend.hub.Hub` (bus router, job queue,
worker directory, episode store), the embedded sim worker and trainer (unless ``workers="none"``), the
:class:`~studio.ui.job_board.JobBoard` every tab reads jobs from and the
:class:`~studio.ui.runs.RunRegistry`. The UI is a client of those services, never a second simulator:
teleop sessions run on a sim worker, plans and rollouts are jobs, training is a job.

Each :class:`StudioTab` has its own scene, its own teleop session and the panels (Teleop & record,
Upload, Datasets, Train, Imitate, Inspect, Compare, Workers). What its scene shows is its *view mode*: the live
teleop session, a running rollout, or a replay. Pose updates reach the scene through one pump thread
per tab (latest wins, at most :data:`MAX_POSE_HZ`), so a slow browser never slows the simulation.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
import traceback
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import viser

from studio.backend import bus
from studio.backend import messages as msg
from studio.backend.hub import Hub
from studio.data.drafts import RecordingDrafts
from studio.ui.job_board import JobBoard
from studio.ui.runs import RunRegistry
from studio.ui.scene_view import SceneView

log = logging.getLogger("studio.ui")

#: Upper bound of scene updates sent to one browser tab per second.
MAX_POSE_HZ = 60.0
#: How often panels refresh what they show from jobs, workers and the store.
REFRESH_HZ = 2.0
#: How long a notification stays open: an error long enough to read its sentence, other news briefly.
ERROR_SECONDS = 15.0
NOTICE_SECONDS = 5.0
#: Error notifications shown at once: a newer one closes the oldest.
MAX_ERRORS_SHOWN = 2


class TeleopStats:
    """Drag-to-motion latency measured on the server, for ``studio bench ui``.

    ``ack_ms``: from the moment the server received a gizmo drag to the first pose frame back from the
    sim worker that applied it; ``push_ms``: to the moment that frame's poses were queued for the browser.
    """

    def __init__(self, keep: int = 20000):
        self.keep = keep
        self.ack_ms: list[float] = []
        self.push_ms: list[float] = []
        self._lock = threading.Lock()

    def add(self, which: str, ms: float) -> None:
        with self._lock:
            series = self.ack_ms if which == "ack" else self.push_ms
            if len(series) < self.keep:
                series.append(ms)

    def reset(self) -> None:
        with self._lock:
            self.ack_ms.clear()
            self.push_ms.clear()


class Panel(Protocol):
    """What a tab's panels provide: a periodic refresh and closing with the tab."""

    def refresh(self) -> None: ...
    def close(self) -> None: ...


class StudioTab:
    """One browser tab: its scene view, its panels, and the threads that keep them current."""

    def __init__(self, app: StudioApp, client: viser.ClientHandle):
        from studio.ui.panels.compare import ComparePanel
        from studio.ui.panels.datasets import DatasetsPanel
        from studio.ui.panels.imitate import ImitatePanel
        from studio.ui.panels.inspector import InspectorPanel
        from studio.ui.panels.teleop import SHOW_LIVE, TeleopPanel
        from studio.ui.panels.train import TrainPanel
        from studio.ui.panels.upload import UploadPanel
        from studio.ui.panels.workers import WorkersPanel

        self.app, self.client = app, client
        self.view = SceneView(client)
        self.feed = bus.Latest()
        self.mode = "teleop"
        self._token = 0
        self._closed = threading.Event()
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"tab{client.client_id}")
        self._actions: list[str] = []  # what run() holds, oldest (the running one) first
        self._actions_lock = threading.Lock()
        self._notices: dict[str, tuple[Any, float, bool]] = {}  # title -> (handle, shown at, is an error)
        self._notices_lock = threading.Lock()
        self.pose_pushes = 0
        gui = client.gui
        gui.configure_theme(control_width="large", show_logo=False)
        self.view_note = gui.add_markdown("")
        self.back_to_teleop = gui.add_button("Back to the live teleop scene", visible=False)
        tabs = gui.add_tab_group()
        with tabs.add_tab("Teleop", icon=viser.Icon.HAND_GRAB):
            self.teleop = TeleopPanel(self)
        with tabs.add_tab("Upload", icon=viser.Icon.UPLOAD):
            self.upload = UploadPanel(self)
        with tabs.add_tab("Data", icon=viser.Icon.DATABASE):
            self.datasets = DatasetsPanel(self)
        with tabs.add_tab("Train", icon=viser.Icon.CHART_LINE):
            self.train = TrainPanel(self)
        with tabs.add_tab("Imitate", icon=viser.Icon.ROBOT):
            self.imitate = ImitatePanel(self)
        with tabs.add_tab("Inspect", icon=viser.Icon.TIMELINE):
            self.inspector = InspectorPanel(self)
        with tabs.add_tab("Compare", icon=viser.Icon.ARROWS_DIFF):
            self.compare = ComparePanel(self)
        with tabs.add_tab("Workers", icon=viser.Icon.SERVER):
            self.workers = WorkersPanel(self)
        self.back_to_teleop.on_click(lambda _: self.run(self.teleop.show_live, SHOW_LIVE))
        self.panels: list[Panel] = [
            self.teleop,
            self.upload,
            self.datasets,
            self.train,
            self.imitate,
            self.inspector,
            self.compare,
            self.workers,
        ]
        self._pump = threading.Thread(target=self._pump_loop, name=f"pump{client.client_id}", daemon=True)
        self._pump.start()
        self.teleop.start()

    # ------------------------------------------------------------------ helpers for panels
    def run(self, fn: Callable[[], Any], what: str) -> None:
        """Run a slow action off viser's callback threads (one at a time per tab); errors become notifications.

        An action that has to wait for an earlier one says so, so that a click never seems lost."""

        def guarded() -> None:
            started = time.monotonic()
            try:
                fn()
            except Exception as e:
                if isinstance(e, (ValueError, bus.RemoteError)):  # the person's to act on: said, not a fault
                    log.info("tab %s: %s refused: %s", self.client.client_id, what, _describe(e))
                else:
                    log.warning("tab %s: %s failed:\n%s", self.client.client_id, what, traceback.format_exc())
                self.notify(f"Could not finish {what}", _describe(e), error=True)
            finally:
                with self._actions_lock:
                    self._actions.remove(what)
                self.app.note_change()
                log.debug("tab %s: %s took %.2f s", self.client.client_id, what, time.monotonic() - started)

        if self._closed.is_set():
            return
        with self._actions_lock:
            ahead = list(self._actions)
            self._actions.append(what)
        if ahead:
            self.notify(
                "Waiting",
                f"{what} starts after {ahead[0]}" + (f" and {len(ahead) - 1} more" if len(ahead) > 1 else ""),
                seconds=3.0,
            )
        self._executor.submit(guarded)

    @property
    def actions(self) -> tuple[str, ...]:
        """The actions :meth:`run` holds: the running one first, then those waiting for it."""
        with self._actions_lock:
            return tuple(self._actions)

    def notify(self, title: str, body: str, error: bool = False, seconds: float | None = None) -> None:
        """Show a notification that closes by itself (errors after :data:`ERROR_SECONDS`).

        One of the same title replaces the previous one, and at most :data:`MAX_ERRORS_SHOWN` errors are open
        at once (a newer one closes the oldest), so that repeated failures never pile up."""
        seconds = seconds if seconds is not None else (ERROR_SECONDS if error else NOTICE_SECONDS)
        with self._notices_lock:
            now = time.monotonic()
            # Replace the same title's notification, and close the oldest errors beyond the limit. One that
            # closed by itself already is harmless to close again: the browser's timer is the one that counts.
            closing = [self._notices.pop(title)] if title in self._notices else []
            if error:
                errors = sorted((n for n in self._notices.items() if n[1][2]), key=lambda n: n[1][1])
                for t, _ in errors[: max(0, len(errors) - MAX_ERRORS_SHOWN + 1)]:
                    closing.append(self._notices.pop(t))
            for t in [t for t, n in self._notices.items() if not n[2] and n[1] < now - 60.0]:
                del self._notices[t]  # long closed news: nothing to replace any more
            for handle, _, _ in closing:
                with contextlib.suppress(Exception):
                    handle.remove()
            with contextlib.suppress(Exception):
                handle = self.client.add_notification(
                    title, body, color="red" if error else None, auto_close_seconds=seconds
                )
                self._notices[title] = (handle, now, error)

    # ------------------------------------------------------------------ the scene's view mode
    def set_mode(self, mode: str, note: str = "") -> int:
        """Switch what the scene shows; returns the token pose sources must present (stale ones are dropped)."""
        self._token += 1
        self.mode = mode
        self.view_note.content = note
        self.back_to_teleop.visible = mode != "teleop"
        teleop = getattr(self, "teleop", None)
        if teleop is not None:
            teleop.on_mode(mode)
        self.view.clear_overlays()  # a new view starts clean; panels draw what belongs to it
        return self._token

    @property
    def token(self) -> int:
        return self._token

    def push_poses(self, token: int, poses: np.ndarray, ack: tuple[int, float] | None = None) -> None:
        """Hand the latest poses of the current source to the pump (ignored if the mode has changed)."""
        if token == self._token:
            self.feed.put((token, poses, ack))

    def _pump_loop(self) -> None:
        version = 0
        next_push = 0.0
        while not self._closed.is_set():
            value, version = self.feed.wait_newer(version, 0.5)
            if value is None or self._closed.is_set():
                continue
            token, poses, ack = value
            if token != self._token:
                continue
            now = time.perf_counter()
            if now < next_push:
                time.sleep(next_push - now)
                value, version = self.feed.get()  # newer poses may have arrived meanwhile: latest wins
                token, poses, ack = value
                if token != self._token:
                    continue
            next_push = time.perf_counter() + 1.0 / MAX_POSE_HZ
            try:
                self.view.apply(poses)
                self.pose_pushes += 1
            except Exception:
                log.exception("tab %s: pose update failed", self.client.client_id)
                continue
            if ack is not None:
                self.app.stats.add("push", 1e3 * (time.perf_counter() - ack[1]))

    def refresh(self) -> None:
        for panel in self.panels:
            try:
                panel.refresh()
            except Exception:
                log.exception("tab %s: refreshing %s failed", self.client.client_id, type(panel).__name__)

    def close(self) -> None:
        self._closed.set()
        if self._pump is not threading.current_thread():
            self._pump.join(timeout=1.0)
        for panel in self.panels:
            with contextlib.suppress(Exception):
                panel.close()
        self._executor.shutdown(wait=False, cancel_futures=True)


def _describe(e: BaseException) -> str:
    if isinstance(e, bus.RemoteError):
        return e.message
    return str(e) or type(e).__name__


class StudioApp:
    """The studio server.

    Args:
        host, port: where the browser connects (loopback unless told otherwise; the next free port is used
            if ``port`` is taken).
        data_dir: dataset root (None: ``STUDIO_DATA_DIR`` or the user data directory).
        bus_config: the hub's Zenoh configuration (default: a router on ``tcp/127.0.0.1:7447``).
        workers: ``"embedded"`` starts one sim worker and one trainer as child processes; ``"none"`` waits
            for external workers (``studio worker sim|train --connect …``).
        policy_dir: where shipped policies are looked for (default ``studio/policies``).
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 8080,
        data_dir: str | Path | None = None,
        bus_config: bus.BusConfig | None = None,
        workers: str = "embedded",
        policy_dir: str | Path | None = None,
    ):
        from studio.backend.embedded import start_embedded_workers

        if workers not in ("embedded", "none"):
            raise ValueError(f"workers must be 'embedded' or 'none', got {workers!r}")
        self.hub = Hub(bus_config, data_dir=data_dir)
        self.store = self.hub.store
        self.data_dir = self.hub.data_dir
        self.embedded = None
        self.server: viser.ViserServer | None = None
        try:
            if workers == "embedded":
                self.embedded = start_embedded_workers(self.hub)
            self.jobs = JobBoard(self.hub.job_client)
            self.runs = RunRegistry(self.data_dir, policy_dir)
            self.drafts = RecordingDrafts(self.data_dir)
            self.stats = TeleopStats()
            self.dataset_version = 0
            self._dataset_mark: tuple | None = None
            self.tabs: dict[int, StudioTab] = {}
            self._lock = threading.Lock()
            self._changes = threading.Condition()
            self._change_count = 0
            self._geometry: dict[tuple, msg.SceneGeometry] = {}
            self._stop = threading.Event()
            self.server = viser.ViserServer(host=host, port=port, label="OSVI Studio", verbose=False)
            self.server.scene.set_up_direction("+z")
            self.server.scene.world_axes.visible = False
            # Shadows cost every frame and add little to a tabletop scene; without them laptops without a
            # good GPU (and software WebGL) keep up with 60 Hz updates.
            self.server.scene.configure_default_lights(enabled=True, cast_shadow=False)
            self.server.on_client_connect(self._connect)
            self.server.on_client_disconnect(self._disconnect)
            self._ticker = threading.Thread(target=self._tick_loop, name="studio-refresh", daemon=True)
            self._ticker.start()
        except BaseException:
            self.stop()
            raise

    @property
    def url(self) -> str:
        if self.server is None:
            raise RuntimeError("the studio's web server is not running")
        host = self.server.get_host()
        return f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{self.server.get_port()}"

    # ------------------------------------------------------------------ tabs
    def _connect(self, client: viser.ClientHandle) -> None:
        client.camera.position = (0.8, 1.15, 0.7)
        client.camera.look_at = (-0.08, 0.36, 0.12)
        client.camera.up_direction = (0.0, 0.0, 1.0)
        tab = StudioTab(self, client)
        with self._lock:
            self.tabs[client.client_id] = tab

    def _disconnect(self, client: viser.ClientHandle) -> None:
        with self._lock:
            tab = self.tabs.pop(client.client_id, None)
        if tab is not None:
            tab.close()

    def _tick_loop(self) -> None:
        while not self._stop.wait(1.0 / REFRESH_HZ):
            try:
                self.jobs.poll()
                self._check_dataset()
            except Exception:
                log.exception("refresh failed")
            with self._lock:
                tabs = list(self.tabs.values())
            for tab in tabs:
                tab.refresh()
            self.note_change()

    def _check_dataset(self) -> None:
        ids = self.store.catalog.episode_ids()
        rollouts = self.store.catalog.rollouts(limit=1)
        mark = (len(ids), max(ids) if ids else "", rollouts[0].id if rollouts else "")
        if mark != self._dataset_mark:
            self._dataset_mark = mark
            self.dataset_version += 1

    def dataset_changed(self) -> None:
        """Called after this process changed the store (tabs refresh their lists)."""
        self._dataset_mark = None

    # ------------------------------------------------------------------ scenes without a live session
    def geometry(self, scene: str, robot: str, task: str, seed: int) -> tuple[msg.SceneGeometry, np.ndarray]:
        """Geometry of (scene, robot) and the bodies' poses at the start of (task, seed), from the scene files."""
        from studio.backend.replay import scene_snapshot

        geometry, poses = scene_snapshot(scene, robot, task, seed)
        key = (scene, robot, task if scene == "metaworld" else "")
        with self._lock:
            geometry = self._geometry.setdefault(key, geometry)
        return geometry, poses

    # ------------------------------------------------------------------ changes
    def note_change(self) -> None:
        """Wake :meth:`wait_until`'s waiters: a refresh of every tab, or a tab's action, has just finished."""
        with self._changes:
            self._change_count += 1
            self._changes.notify_all()

    def wait_until(self, predicate: Callable[[], Any], timeout: float) -> Any:
        """Block until ``predicate()`` is truthy and return its value (None after ``timeout`` seconds).

        It is checked now and again each time the app has changed what it shows: after each refresh of the
        tabs (``REFRESH_HZ``) and each finished tab action. For scripts and tests that drive the app and wait
        on what it shows, without guessing a delay."""
        deadline = time.monotonic() + timeout
        while True:
            with self._changes:
                seen = self._change_count
            value = predicate()
            if value:
                return value
            with self._changes:
                while self._change_count == seen:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        return None
                    self._changes.wait(left)

    # ------------------------------------------------------------------ lifecycle
    def wait_for_workers(self, timeout: float = 60.0) -> bool:
        """Wait until the embedded workers (if any) have joined the bus."""
        return True if self.embedded is None else self.embedded.wait_ready(self.hub.directory, timeout)

    def stop(self) -> None:
        if hasattr(self, "_stop"):
            self._stop.set()
        for tab in list(getattr(self, "tabs", {}).values()):
            tab.close()
        if self.server is not None:
            self.server.stop()
        if getattr(self, "jobs", None) is not None:
            self.jobs.close()
        if self.embedded is not None:
            self.embedded.stop()
        self.hub.close()
