"""Datasets: per task, how many expert and agent episodes there are by source; collect scripted episodes in bulk;
open one to play its video, replay it in the scene and see its end-effector path as a 3D spline.

*Collect scripted episodes* runs ``studio collect`` as a ``collect`` job on a sim worker
(:mod:`studio.backend.collect_job`): scene, robot and role, the tasks (held-out ones marked), episodes per task and
seed. **Start collecting** is disabled while a collection is queued or running (from any tab), so a double-click
never queues two; the progress line and bar follow the job, **Cancel collecting** stops it between episodes (those
stored stay), and the counts table grows as the episodes arrive.
"""

from __future__ import annotations

import threading
from collections import Counter
from typing import Any

import numpy as np

from studio.backend.collect_job import MAX_EPISODES, MAX_SEED, SpecError, check_spec
from studio.backend.job_client import new_job_id
from studio.data.collect import ROLE_OF_ROBOT
from studio.data.episode import SOURCES
from studio.data.splits import load_split
from studio.sim.tasks import list_tasks
from studio.ui.images import thumbnail
from studio.ui.timeline import Timeline

HINT = """Episode counts per task, by role and source. **Collect scripted episodes** fills the dataset with the
scripted experts (as `studio collect`). Pick an episode and **Open** it to play its video; simulated episodes also
replay in the scene with their end-effector path (blue: gripper open, orange: closed)."""

COLLECT_HINT = """The scripted experts on a sim worker: the **Sawyer** and the simulated **hand** demonstrate
(expert), the **Panda** imitates (agent) or, with role *expert*, demonstrates for a Panda agent. Episodes are
stored as they are made; the same seed again makes only the missing ones. While a collection runs, the sim worker
takes no other job (*Imitate*'s Plan and Execute wait for it)."""

COLLECT_FOLDER = "Collect scripted episodes"
START = "Start collecting"
CANCEL = "Cancel collecting"
EPISODES = "Episodes per task"
HELD_OUT = " (held-out)"
SCENES = ("pick_place", "push", "metaworld")
SELECT = ("All", "Training", "Held-out", "None")
#: Server-wide: one tab at a time checks for a running collection and submits one.
_START_LOCK = threading.Lock()


def robots_of(scene: str) -> tuple[str, ...]:
    """The robots that collect in ``scene``: Meta-World has only the Sawyer."""
    return ("sawyer",) if scene == "metaworld" else ("sawyer", "panda", "hand")


def roles_of(robot: str, scene: str = "pick_place") -> tuple[str, ...]:
    """The robot's own role first; the human hand only demonstrates, and Meta-World's one pool of Sawyer episodes
    is stored as ``expert`` (the training view pairs it with itself)."""
    own = ROLE_OF_ROBOT[robot]
    return (
        (own,) if robot == "hand" or scene == "metaworld" else (own, "agent" if own == "expert" else "expert")
    )


def task_box_labels(scene: str) -> dict[str, str]:
    """Checkbox label -> task name, in the scene's order; held-out tasks marked."""
    held = set(load_split(scene).test)
    return {t.split("/", 1)[1] + (HELD_OUT if t in held else ""): t for t in list_tasks(scene)}


def collect_status(tracked) -> tuple[str, float | None]:
    """The progress line of a collect job and its fraction done (None: nothing to show on the bar)."""
    st, p, r = tracked.status, tracked.progress, tracked.result
    state = st.state if st is not None else "submitting"
    spec = tracked.spec
    what = f"{spec.get('robot', '?')} {spec.get('role') or ''}".strip()
    head = f"Collection `{tracked.job}` ({what})"
    frac = min(1.0, p.step / p.total) if p is not None and p.total else None
    if state in ("submitting", "queued"):
        return f"{head} **queued**: {st.reason if st is not None else 'submitting…'}", frac
    if state == "running":
        if p is None:
            return f"{head} **running**: starting…", frac
        eta = f" · about {p.eta_s:.0f} s left" if p.eta_s else ""
        return f"{head} **running**: {p.message}{eta}", frac
    if r is not None:
        made, total = int(r.get("made", 0)), int(r.get("requested", 0))
        stored = int(r.get("already_present", 0)) + made
        tail = ""
        if r.get("missing"):
            shown = ", ".join(r["missing"][:3]) + ("…" if len(r["missing"]) > 3 else "")
            tail = f"; {len(r['missing'])} failed every scripted attempt ({shown})"
        if state == "cancelled":
            return (
                f"{head} **cancelled**: {made} new episodes kept ({stored} of {total} stored); "
                f"{r.get('left', 0)} not made — **{START}** with the same seed makes them{tail}."
            ), frac
        return (
            f"{head} **{state}**: {stored} of {total} episodes stored ({made} new) in "
            f"{float(r.get('seconds', 0)):.0f} s{tail}.",
            1.0,
        )
    if state == "succeeded":
        return f"{head} **succeeded**", 1.0
    reason = st.reason if st is not None else ""
    return f"{head} **{state}**" + (f": {reason}" if reason else ""), frac


def _by_source(counts: Counter, task: str, role: str) -> str:
    parts = [f"{counts[(task, role, s)]} {s}" for s in SOURCES if counts.get((task, role, s))]
    return ", ".join(parts) or "—"


def counts_table(metas) -> str:
    """Markdown table: one row per task, expert and agent counts by source."""
    counts = Counter((m.task, m.role, m.source) for m in metas)
    tasks = sorted({m.task for m in metas})
    if not tasks:
        return (
            f"The dataset is empty: make scripted episodes with **{START}** in *{COLLECT_FOLDER}* below, "
            "record in *Teleop*, or upload a video."
        )
    rows = ["| task | expert | agent |", "|---|---|---|"]
    for t in tasks:
        rows.append(f"| {t} | {_by_source(counts, t, 'expert')} | {_by_source(counts, t, 'agent')} |")
    total = Counter(m.role for m in metas)
    rows.append("")
    n = len(metas)
    rows.append(f"{n} episode{'' if n == 1 else 's'}: {total['expert']} expert, {total['agent']} agent.")
    return "\n".join(rows)


def forked_note(extra: dict | None) -> str:
    """Where a forked episode came from, in one sentence (empty for other episodes)."""
    origin = (extra or {}).get("forked_from") if isinstance(extra, dict) else None
    if not isinstance(origin, dict) or "rollout" not in origin:
        return ""
    return (
        f" Forked from rollout `{origin['rollout']}` at step {origin.get('step')}: its first "
        f"{int(origin.get('step', 0)) + 1} steps are the rollout's."
    )


class DatasetsPanel:
    """The *Data* tab."""

    def __init__(self, tab):
        self.tab = tab
        self.app = tab.app
        self._version = -1
        self.frames: np.ndarray | None = None
        self.replay = None
        self.meta = None
        self._token = 0
        gui = tab.client.gui
        self.gui = gui
        gui.add_markdown(HINT)
        self.table = gui.add_markdown("…")
        self._build_collect(gui)
        with gui.add_folder("Open an episode"):
            self.task = gui.add_dropdown("Task", ("(all)",), initial_value="(all)")
            self.episode = gui.add_dropdown("Episode", ("(none)",))
            self.open_button = gui.add_button("Open", icon="player-play")
            self.info = gui.add_markdown("")
            self.image = gui.add_image(np.full((120, 160, 3), 255, np.uint8), label="Video", visible=False)
            self.timeline = Timeline(gui, "Frame", self._show_frame)
        self.task.on_update(lambda e: self._fill_episodes())
        self.open_button.on_click(lambda _: tab.run(self.open_selected, "opening the episode"))

    # ------------------------------------------------------------------ collect scripted episodes
    def _build_collect(self, gui) -> None:
        self.collect_job: str | None = None  # the collect job shown (the newest, whoever started it)
        self._collect_lock = threading.Lock()
        self._starting = False
        self._task_boxes: dict[str, Any] = {}  # task name -> checkbox
        self._collect_shown: dict[str, object] = {}
        with gui.add_folder(COLLECT_FOLDER):
            gui.add_markdown(COLLECT_HINT)
            self.c_scene = gui.add_dropdown("Scene", SCENES, initial_value="pick_place")
            self.c_robot = gui.add_dropdown("Robot", robots_of("pick_place"), initial_value="sawyer")
            self.c_role = gui.add_dropdown("Role", roles_of("sawyer"), initial_value="expert")
            self.c_tasks = gui.add_folder("Tasks")
            with self.c_tasks:
                self.c_select = gui.add_button_group("Select tasks", SELECT)
                self.c_heldout = gui.add_markdown("")
            self.c_episodes = gui.add_number(EPISODES, initial_value=10, min=1, max=MAX_EPISODES, step=1)
            self.c_seed = gui.add_number(
                "Seed",
                initial_value=0,
                min=0,
                max=MAX_SEED,
                step=1,
                hint="base seed of the run: the same seed again makes only the missing episodes",
            )
            self.c_start = gui.add_button(START, color="green", icon="player-play")
            self.c_cancel = gui.add_button(CANCEL, icon="player-stop", disabled=True)
            self.c_status = gui.add_markdown("No collection yet.")
            self.c_progress = gui.add_progress_bar(0.0, visible=False)
        self._fill_collect_tasks()
        self.c_scene.on_update(lambda _: self._on_collect_scene())
        self.c_robot.on_update(lambda _: self._fill_roles())
        self.c_select.on_click(lambda e: self._select_tasks(e.target.value))
        self.c_start.on_click(lambda _: self._on_start())
        self.c_cancel.on_click(lambda _: self.tab.run(self.cancel_collecting, "cancelling the collection"))

    def _on_collect_scene(self) -> None:
        robots = robots_of(self.c_scene.value)
        if self.c_robot.options != robots:
            self.c_robot.options = robots
        if self.c_robot.value not in robots:
            self.c_robot.value = robots[0]
        self._fill_roles()
        self._fill_collect_tasks()

    def _fill_roles(self) -> None:
        roles = roles_of(self.c_robot.value, self.c_scene.value)
        if self.c_role.options != roles:
            self.c_role.options = roles
            self.c_role.value = roles[0]

    def _fill_collect_tasks(self) -> None:
        scene = self.c_scene.value
        if self._collect_shown.get("tasks_scene") == scene:
            return
        self._collect_shown["tasks_scene"] = scene
        for box in self._task_boxes.values():
            box.remove()
        self._task_boxes.clear()
        with self.c_tasks:
            for label, task in task_box_labels(scene).items():
                self._task_boxes[task] = self.gui.add_checkbox(label, initial_value=False)
        held = ", ".join(t.split("/", 1)[1] for t in load_split(scene).test) or "none"
        self.c_heldout.content = (
            f"Held out (never trained on; their demonstrations serve evaluation): **{held}**"
        )

    def _select_tasks(self, which: str) -> None:
        split = load_split(self.c_scene.value)
        chosen = {"All": set(self._task_boxes), "Training": set(split.train), "Held-out": set(split.test)}
        for task, box in self._task_boxes.items():
            box.value = task in chosen.get(which, set())

    def selected_tasks(self) -> list[str]:
        return [t for t, box in self._task_boxes.items() if box.value]

    def collect_spec(self) -> dict:
        """The job spec the folder's widgets say (not checked yet)."""
        return {
            "scene": self.c_scene.value,
            "robot": self.c_robot.value,
            "role": self.c_role.value,
            "tasks": self.selected_tasks(),
            "episodes": int(self.c_episodes.value),
            "seed": int(self.c_seed.value),
        }

    def _on_start(self) -> None:
        """The click, on viser's thread: taken once until the job it starts is queued (a double-click is one)."""
        with self._collect_lock:
            if self._starting:
                return
            self._starting = True
        self.c_start.disabled = True
        self.tab.run(self.start_collecting, "starting the collection")

    def start_collecting(self) -> str | None:
        """Check the spec (a bad field: a notification naming it), then queue one collect job."""
        try:
            spec = self.collect_spec()
            if not spec["tasks"]:
                raise SpecError("tasks", "tick at least one task")
            checked = check_spec(spec)
            with _START_LOCK:
                active = self._active_collect()
                if active is not None:
                    self.collect_job = active.job
                    self.tab.notify(
                        "Already collecting", f"{active.job} is {active.state}; wait for it or cancel it"
                    )
                    return None
                job = new_job_id("collect")
                self.collect_job = job
                self.app.jobs.submit("collect", spec, started_by=self.tab.client.client_id, job=job)
            self._collect_shown.pop("status", None)
            self.c_status.content = f"Collection `{job}` queued…"
            self.tab.notify("Collection queued", f"{checked.total} episodes: {job}")
            return job
        finally:
            with self._collect_lock:
                self._starting = False
            self._show_collect()

    def cancel_collecting(self) -> None:
        if self.collect_job is not None:
            status = self.app.jobs.cancel(self.collect_job)
            if not status.terminal:
                self.c_status.content = (
                    f"Collection `{self.collect_job}`: cancelling after the current episode…"
                )

    def _active_collect(self):
        """The collect job queued or running on the hub (whichever tab started it), if any."""
        for s in reversed(self.app.hub.jobs.jobs()):
            if s.kind == "collect" and s.state in ("queued", "running"):
                return s
        return None

    def _tracked_collect(self):
        statuses = [s for s in self.app.hub.jobs.jobs() if s.kind == "collect"]
        if statuses and (self.collect_job is None or statuses[-1].job != self.collect_job):
            newest = statuses[-1]
            if self.collect_job is None or newest.state in ("queued", "running"):
                self.collect_job = newest.job  # one started in another tab (or before this tab opened)
        if self.collect_job is None:
            return None
        status = next((s for s in statuses if s.job == self.collect_job), None)
        return self.app.jobs.follow(self.collect_job, "collect", status.spec if status else None)

    def _show_collect(self) -> None:
        tracked = self._tracked_collect()
        running = tracked is not None and not tracked.terminal
        busy = running or self._starting
        if self.c_start.disabled != busy:
            self.c_start.disabled = busy
        if self.c_cancel.disabled != (not running):
            self.c_cancel.disabled = not running
        if tracked is None:
            return
        text, frac = collect_status(tracked)
        if self._collect_shown.get("status") != text:
            self._collect_shown["status"] = text
            self.c_status.content = text
        value = 100.0 * (frac or 0.0)
        if not self.c_progress.visible:
            self.c_progress.visible = True
        if abs(self.c_progress.value - value) > 0.05:
            self.c_progress.value = value
        if tracked.terminal and self._collect_shown.get("ended") != tracked.job:
            self._collect_shown["ended"] = tracked.job
            self.app.dataset_changed()

    # ------------------------------------------------------------------ episodes
    def _fill_episodes(self) -> None:
        task = None if self.task.value == "(all)" else self.task.value
        metas = self.app.store.episodes(task=task, newest_first=True, limit=200)
        options = tuple(f"{m.id} · {m.task} · {m.role}/{m.embodiment} · {m.source}" for m in metas) or (
            "(none)",
        )
        if self.episode.options != options:
            self.episode.options = options

    def open_selected(self) -> None:
        eid = self.episode.value.split(" ")[0]
        if eid == "(none)":
            self.tab.notify("No episode", "Choose an episode to open.", error=True)
            return
        self.open(eid)

    def open(self, episode_id: str) -> None:
        from studio.backend.replay import EpisodeReplay

        store = self.app.store
        meta = store.get(episode_id)
        self.meta = meta
        self.frames = store.load_frames(episode_id)
        self.replay = None
        self.info.content = (
            f"`{meta.id}` — **{meta.task}**, {meta.role} by {meta.embodiment} ({meta.source}), seed {meta.seed}, "
            f"{meta.num_frames} frames at {meta.fps:.0f} fps, {meta.num_steps} steps, "
            f"success: {'yes' if meta.success else 'no' if meta.success is False else 'unknown'}."
            + forked_note(meta.extra)
        )
        self.image.visible = True
        if meta.has_arrays and meta.seed is not None:
            self.replay = EpisodeReplay(store, episode_id)
            view = self.tab.view
            self._token = self.tab.set_mode("replay", f"Replaying episode `{meta.id}` ({meta.task}).")
            view.load(
                self.replay.geometry,
                ("replay", meta.scene, meta.embodiment, meta.task if meta.scene == "metaworld" else ""),
            )
            view.set_camera(store.load_camera(episode_id).to_dict())
            gripper = self.replay.arrays.get("gripper_cmd")
            view.show_path("path", self.replay.ee_path(), gripper)
        self.timeline.reset(len(self.frames), fps=min(max(meta.fps, 1.0), 30.0))

    def _show_frame(self, i: int) -> None:
        if self.frames is None:
            return
        i = int(np.clip(i, 0, len(self.frames) - 1))
        self.image.image = thumbnail(self.frames[i], 180)
        if self.replay is not None and self.tab.token == self._token:
            step = int(self.replay.frame_steps[min(i, len(self.replay.frame_steps) - 1)])
            self.tab.push_poses(self._token, self.replay.poses_at(step))
            self.tab.view.set_camera_image(self.frames[i])

    def refresh(self) -> None:
        self._show_collect()
        if self.app.dataset_version == self._version:
            return
        self._version = self.app.dataset_version
        metas = self.app.store.episodes()
        self.table.content = counts_table(metas)
        tasks = ("(all)", *sorted({m.task for m in metas}))
        if self.task.options != tasks:
            self.task.options = tasks
        self._fill_episodes()

    def close(self) -> None:
        self.timeline.close()
