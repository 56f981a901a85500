"""Rollout inspector: stored rollouts filtered by task, checkpoint and outcome (failures first, with the stage
they failed at); one replayed with a timeline — scene poses, the camera frame at that moment, the active
plan's waypoints (with a guided policy, also the plan from the scene alone, in grey), and the predicted latent
image beside the actual frame when the checkpoint has a decoder.

*Fork at this step* restores the simulator exactly as the rollout had it at the timeline's step in this
tab's teleop session (:mod:`studio.backend.forking`), recording: drag the correction, then save it as a
new demonstration (expert) or agent episode of the task, linked to the rollout (``forked_from``). The
episodes forked from a rollout are listed when it is opened."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from studio.backend.messages import Role
from studio.ui.demo_score_note import demo_score_note
from studio.ui.guidance_note import guidance_note
from studio.ui.images import side_by_side, thumbnail
from studio.ui.timeline import Timeline
from studio.ui.workspace_note import workspace_note

HINT = """Every rollout (from *Imitate* or `studio eval`) is stored. Filter them, **Open** one and drag the
timeline: the scene, the camera frame and the plan in force at that moment follow. Failures come first,
with the stage they failed at. **Fork at this step** continues the rollout from that moment in a teleop
session: drag the correction and save it as a new episode of the task."""
FORKING = "**● Recording the fork** — drag the gizmo in the scene, then save it (or discard it)."
ROLES: dict[str, Role] = {"agent episode (the robot's trajectory)": "agent", "expert demonstration": "expert"}

ALL = "(all)"
OUTCOMES = (ALL, "failures", "successes")


def rollout_label(r) -> str:
    mark = "✔ success" if r.success else f"✘ {r.failure_stage or 'failed'}"
    return f"{r.id} · {mark} · {r.task} · seed {r.seed} · {r.checkpoint_id or 'oracle'}"


class InspectorPanel:
    """The *Inspect* tab."""

    def __init__(self, tab):
        self.tab = tab
        self.app = tab.app
        self._version = -1
        self.record = None
        self.replay = None
        self.frames: np.ndarray | None = None
        self.plans: dict[str, np.ndarray] = {}
        self.latents: dict[int, np.ndarray] = {}
        self._token = 0
        gui = tab.client.gui
        gui.add_markdown(HINT)
        self.task = gui.add_dropdown("Task", (ALL,), initial_value=ALL)
        self.checkpoint = gui.add_dropdown("Checkpoint", (ALL,), initial_value=ALL)
        self.outcome = gui.add_dropdown("Outcome", OUTCOMES, initial_value=ALL)
        self.rollout = gui.add_dropdown("Rollout", ("(none)",))
        self.open_button = gui.add_button("Open", icon="timeline")
        self.info = gui.add_markdown("")
        self.image = gui.add_image(np.full((120, 160, 3), 255, np.uint8), label="Camera", visible=False)
        self.timeline = Timeline(gui, "Step", self._show_step, fps=30.0)
        self.plan_info = gui.add_markdown("")
        with gui.add_folder("Fork from this moment", visible=False) as self.fork_folder:
            self.fork_role = gui.add_dropdown("Save as", tuple(ROLES), initial_value=next(iter(ROLES)))
            self.fork_button = gui.add_button(
                "Fork at this step",
                icon="git-fork",
                hint="restore the simulator at the timeline's step and record a correction",
            )
            self.fork_status = gui.add_markdown("")
            self.fork_grip = gui.add_button_group("Fork gripper", ("Open", "Close"), visible=False)
            self.fork_save = gui.add_button("Stop & save the fork", icon="device-floppy", visible=False)
            self.fork_discard = gui.add_button("Discard the fork", icon="x", visible=False)
        self.fork_button.on_click(lambda _: tab.run(self.fork_here, "forking the rollout"))
        self.fork_grip.on_click(lambda e: tab.teleop.set_gripper(1.0 if e.target.value == "Close" else 0.0))
        self.fork_save.on_click(lambda _: tab.run(tab.teleop.stop_and_save, "saving the episode"))
        self.fork_discard.on_click(
            lambda _: tab.run(tab.teleop.discard_recording, "discarding the recording")
        )
        self._forking = False
        self._chosen: str | None = None  # the rollout the user picked (else the first listed is selected)
        self.rollout.on_update(self._on_rollout_chosen)
        for dd in (self.task, self.checkpoint, self.outcome):
            dd.on_update(lambda e: self._fill_rollouts())
        self.open_button.on_click(lambda _: tab.run(self.open_selected, "opening the rollout"))

    # ------------------------------------------------------------------ listing
    def rollouts(self):
        cat = self.app.store.catalog
        task = None if self.task.value == ALL else self.task.value
        success = {ALL: None, "failures": False, "successes": True}[self.outcome.value]
        rows = cat.rollouts(task=task, success=success, limit=500)
        ck = self.checkpoint.value
        if ck != ALL:
            rows = [r for r in rows if (r.checkpoint_id or "oracle") == ck]
        return sorted(rows, key=lambda r: (r.success, -r.created))

    def _on_rollout_chosen(self, event) -> None:
        if event.client is not None:
            self._chosen = self.rollout.value

    def _fill_rollouts(self) -> None:
        options = tuple(rollout_label(r) for r in self.rollouts()) or ("(none)",)
        if self.rollout.options != options:
            self.rollout.options = options
            self.rollout.value = self._chosen if self._chosen in options else options[0]

    def refresh(self) -> None:
        forking = self.tab.teleop.is_recording_fork_of(self.record.id if self.record is not None else None)
        if forking != self._forking:
            self._forking = forking
            for w in (self.fork_grip, self.fork_save, self.fork_discard):
                w.visible = forking
            if forking:
                self.fork_status.content = FORKING
            if not forking and self.record is not None:
                self._show_forks()
        if self.app.dataset_version == self._version:
            return
        self._version = self.app.dataset_version
        rows = self.app.store.catalog.rollouts(limit=2000)
        tasks = (ALL, *sorted({r.task for r in rows}))
        cks = (ALL, *sorted({r.checkpoint_id or "oracle" for r in rows}))
        if self.task.options != tasks:
            self.task.options = tasks
        if self.checkpoint.options != cks:
            self.checkpoint.options = cks
        self._fill_rollouts()

    # ------------------------------------------------------------------ one rollout
    def open_selected(self) -> None:
        rid = self.rollout.value.split(" ")[0]
        if rid == "(none)":
            self.tab.notify("No rollout", "Choose a rollout to open.", error=True)
            return
        self.open(rid)

    def open(self, rollout_id: str) -> None:
        from studio.backend.replay import EpisodeReplay

        store = self.app.store
        found = [r for r in store.catalog.rollouts(limit=100000) if r.id == rollout_id]
        if not found:
            raise KeyError(f"no rollout {rollout_id}")
        r = found[0]
        if r.episode_id is None:
            raise ValueError(f"rollout {rollout_id} was stored without its recording (eval --no-keep)")
        try:
            replay = EpisodeReplay(store, r.episode_id)
        except Exception as e:
            raise ValueError(
                f"rollout {rollout_id} ({r.task}) cannot be replayed: its scene does not load here "
                f"({type(e).__name__}: {e})"
            ) from None
        self.record = r
        self.replay = replay
        self.frames = store.load_frames(r.episode_id)
        self.plans = {}
        self.latents = {}
        if r.path and (Path(r.path) / "plans.npz").is_file():
            with np.load(Path(r.path) / "plans.npz") as data:
                self.plans = {k: data[k] for k in data.files}
        events = []
        if r.path and (Path(r.path) / "events.json").is_file():
            events = json.loads((Path(r.path) / "events.json").read_text())
        for i in range(self.n_plans):
            images = self.plans.get(f"plan{i}_latent_images")
            if images is not None and len(images):
                self.latents[i] = images
        checkpoint = (r.extra or {}).get("checkpoint")
        note = ""
        if not self.latents:
            note = (
                " The oracle has no latent predictions."
                if not checkpoint or checkpoint == "oracle"
                else " No decoded latent images were stored (the checkpoint had no latent decoder)."
            )
        meta = self.replay.meta
        self._token = self.tab.set_mode("replay", f"Replaying rollout `{r.id}` ({r.task}).")
        view = self.tab.view
        view.load(
            self.replay.geometry,
            ("replay", meta.scene, meta.embodiment, meta.task if meta.scene == "metaworld" else ""),
        )
        view.set_camera(store.load_camera(r.episode_id).to_dict())
        view.show_path("path", self.replay.ee_path(), self.replay.arrays.get("gripper_cmd"))
        stages = (r.extra or {}).get("stages", {})
        reached = ", ".join(f"{k} {'✔' if v else '✘'}" for k, v in stages.items())
        waypoints = sum(1 for e in events if e and e[0] == "waypoint")
        self.info.content = (
            f"**{'✔ success' if r.success else '✘ failed at ' + str(r.failure_stage)}** — {r.task}, seed {r.seed}, "
            f"{r.checkpoint_id or 'oracle'}; {self.n_plans} plan(s), {r.replans} re-plan(s), {waypoints} waypoints "
            f"executed, {r.num_steps} steps. Stages: {reached or '—'}.{note}"
        )
        score = demo_score_note((r.extra or {}).get("demo_score"))  # its demonstration against training
        self.info.content += f"\n\n{score}" if score else ""
        self.image.visible = True
        self.fork_folder.visible = True
        self._show_forks()
        self.timeline.reset(self.replay.num_steps, fps=min(30.0, 1.0 / max(meta.control_dt or 0.02, 1e-3)))

    # ------------------------------------------------------------------ forking
    def fork_here(self) -> None:
        """Continue the open rollout from the timeline's step in this tab's teleop session, recording."""
        from studio.backend.forking import fork_rollout

        r = self.record
        if r is None or self.replay is None:
            raise ValueError("open a rollout first, then pick the moment to fork at on its timeline")
        step = int(self.timeline.slider.value)
        role = ROLES[self.fork_role.value]
        go = fork_rollout(self.app.store, self.app.drafts, r.id, step, role)
        self.fork_status.content = f"Restoring rollout `{r.id}` at step {step}…"
        try:
            self.tab.teleop.continue_episode(go, f"rollout `{r.id}` from step {step}")
        except BaseException:
            self.app.drafts.discard(go.fork.draft)
            self.fork_status.content = ""
            raise
        self.fork_status.content = f"Forked `{r.id}` at step {step} of {self.replay.num_steps - 1}. {FORKING}"

    def _show_forks(self) -> None:
        r = self.record
        if r is None:
            return
        forks = [
            m
            for m in self.app.store.episodes(task=r.task, newest_first=True, limit=500)
            if isinstance(m.extra, dict) and (m.extra.get("forked_from") or {}).get("rollout") == r.id
        ]
        listed = "; ".join(
            f"`{m.id}` ({m.role}, from step {m.extra['forked_from'].get('step')}, "
            f"{'✔' if m.success else '✘'})"
            for m in forks[:5]
        )
        text = (
            f"Episodes forked from this rollout: {listed}."
            if forks
            else "No episode was forked from this rollout yet."
        )
        if not self._forking:
            self.fork_status.content = text

    @property
    def n_plans(self) -> int:
        return sum(1 for k in self.plans if re.fullmatch(r"plan\d+_waypoints_world", k))

    def plan_at(self, step: int) -> int | None:
        starts = self.plans.get("plan_start_ticks")
        if starts is None or len(starts) == 0:
            return None
        return int(max(0, np.searchsorted(np.asarray(starts), step, side="right") - 1))

    def _show_step(self, step: int) -> None:
        if self.replay is None or self.frames is None:
            return
        if self.tab.token == self._token:
            self.tab.push_poses(self._token, self.replay.poses_at(step))
        fsteps = self.replay.frame_steps
        fi = int(np.clip(np.searchsorted(fsteps, step, side="right") - 1, 0, len(self.frames) - 1))
        actual = self.frames[fi]
        k = self.plan_at(step)
        image = thumbnail(actual, 150)
        label = "Camera"
        text = f"Step {step} of {self.replay.num_steps - 1}; camera frame {fi + 1} of {len(self.frames)}."
        if k is not None:
            wps = self.plans.get(f"plan{k}_waypoints_world")
            commanded = self.plans.get(
                f"plan{k}_waypoints_commanded"
            )  # absent in rollouts stored before it was
            null = self.plans.get(f"plan{k}_null_waypoints_world")
            if self.tab.token == self._token:
                if wps is not None:
                    self.tab.view.show_waypoints("plan", wps if commanded is None else commanded)
                self.tab.view.show_null_plan(null)
            starts = np.asarray(self.plans["plan_start_ticks"])
            end = int(starts[k + 1]) if k + 1 < len(starts) else self.replay.num_steps - 1
            text += f" Plan {k + 1} of {len(starts)} (from step {int(starts[k])})."
            if wps is not None and commanded is not None:
                text += workspace_note(wps, commanded)
            if null is not None and wps is not None:
                gain = self.plans.get(f"plan{k}_guidance_gain")
                surprise = self.plans.get(f"plan{k}_guidance_surprise")
                scale = self.plans.get(f"plan{k}_guidance_scale")
                moved = float(np.linalg.norm(np.asarray(wps)[:, :3] - np.asarray(null)[:, :3], axis=1).max())
                guidance = {
                    "guided": bool(self.plans.get(f"plan{k}_guided", True)),
                    "gain": None if gain is None else float(gain),
                }
                if surprise is not None:
                    guidance["surprise"] = float(surprise)
                if scale is not None:
                    guidance["scale"] = float(scale)
                text += guidance_note(guidance, moved)
            lat = self.latents.get(k)
            if lat is not None and len(lat):
                frac = (step - int(starts[k])) / max(1, end - int(starts[k]))
                j = int(np.clip(round(frac * (len(lat) - 1)), 0, len(lat) - 1))
                image = side_by_side(actual, lat[j], height=150)
                label = "Camera (left) · predicted latent state (right)"
                text += f" Left: actual frame; right: predicted latent state {j + 1} of {len(lat)}."
        self.image.image = image
        if self.image.label != label:
            self.image.label = label
        self.tab.view.set_camera_image(actual)
        self.plan_info.content = text

    def close(self) -> None:
        self.timeline.close()
