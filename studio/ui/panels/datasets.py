"""Datasets: per task, how many expert and agent episodes there are by source; open one to play its video,
replay it in the scene and see its end-effector path as a 3D spline."""

from __future__ import annotations

from collections import Counter

import numpy as np

from studio.data.episode import SOURCES
from studio.ui.images import thumbnail
from studio.ui.timeline import Timeline

HINT = """Episode counts per task, by role and source. Pick an episode and **Open** it to play its video;
simulated episodes also replay in the scene with their end-effector path (blue: gripper open, orange:
closed)."""


def _by_source(counts: Counter, task: str, role: str) -> str:
    parts = [f"{counts[(task, role, s)]} {s}" for s in SOURCES if counts.get((task, role, s))]
    return ", ".join(parts) or "—"


def counts_table(metas) -> str:
    """Markdown table: one row per task, expert and agent counts by source."""
    counts = Counter((m.task, m.role, m.source) for m in metas)
    tasks = sorted({m.task for m in metas})
    if not tasks:
        return "The dataset is empty: record in *Teleop*, upload a video, or run `studio collect`."
    rows = ["| task | expert | agent |", "|---|---|---|"]
    for t in tasks:
        rows.append(f"| {t} | {_by_source(counts, t, 'expert')} | {_by_source(counts, t, 'agent')} |")
    total = Counter(m.role for m in metas)
    rows.append("")
    rows.append(f"{len(metas)} episodes: {total.get('expert', 0)} expert, {total.get('agent', 0)} agent.")
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
        gui.add_markdown(HINT)
        self.table = gui.add_markdown("…")
        with gui.add_folder("Open an episode"):
            self.task = gui.add_dropdown("Task", ("(all)",), initial_value="(all)")
            self.episode = gui.add_dropdown("Episode", ("(none)",))
            self.open_button = gui.add_button("Open", icon="player-play")
            self.info = gui.add_markdown("")
            self.image = gui.add_image(np.full((120, 160, 3), 255, np.uint8), label="Video", visible=False)
            self.timeline = Timeline(gui, "Frame", self._show_frame)
        self.task.on_update(lambda e: self._fill_episodes())
        self.open_button.on_click(lambda _: tab.run(self.open_selected, "opening the episode"))

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
