"""Imitate: one-shot imitation of a demonstration on a (held-out) task, planned and executed on a sim worker.

*Plan* runs a ``plan`` job: the scene of (task, seed) is shown, then the expert frames the model saw, the
agent's first frame, the predicted latent trajectory decoded to images (when the checkpoint has a
decoder) and the 5 waypoints as spheres joined by a spline (green: gripper open, red: closed), drawn at the
targets the controller will command and with the gripper state it will hold there: a waypoint the model put
outside the workspace (a guided plan may extrapolate) is drawn where the arm is sent and named in the status line.
*Execute* runs a ``rollout`` job paced at real time: its poses stream into the scene, the waypoint being
executed is enlarged, every re-plan's waypoints replace the drawn ones, and the outcome is shown.
Re-planning continues the same episode inside the rollout (``Re-plans`` allowed); *Re-plan* after a
failure runs the same episode again with one more re-plan (seeded, so the first attempts repeat exactly
and the new plan continues from where they failed). Every tab sees a running rollout and can watch it.

What is shown is what runs: choosing a demonstration shows the frames of it the model will see (and clears a plan
made from another one); *Execute* shows the frames of the demonstration it runs. Each plan comes with the
demonstration's score (:mod:`studio.eval.demo_score`), and a one-line warning when the demonstration is far from
the ones the policy learnt from. *Enlarge* shows the expert frames, the agent's frame and the decoded latent images
large, in a modal window.

Each task is planned and executed by the active policy of its scene (:meth:`studio.ui.runs.RunRegistry.active`):
the user's choice for that scene, else the scene's shipped policy, else the oracle planner, labelled as the
execution ceiling. The policy line names the policy of the selected task's scene (its measured summary is in the
*About this policy* fold below it); a checkpoint chosen for a scene it was not trained on is refused with the
reason, never run.

Rollouts run as ``studio results`` measures them: a scene whose split has an evaluation protocol (Meta-World: the
paper's) bounds each plan's execution (500 control ticks), and choosing one of its held-out tasks sets *Re-plans*
to what the protocol allows it (3 on the hard tasks, none on the easy ones), said under the field.
"""

from __future__ import annotations

import re
from typing import Any

import numpy as np

from studio.backend.plan_job import expert_indices
from studio.data.splits import load_split
from studio.model.checkpoint_info import read_checkpoint_info
from studio.sim.tasks import list_tasks
from studio.ui.demo_score_note import demo_score_note
from studio.ui.guidance_note import guidance_note
from studio.ui.images import ENLARGED_HEIGHT, filmstrip, open_enlarged, thumbnail
from studio.ui.runs import SCENES, Checkpoint, SceneMismatch
from studio.ui.workspace_note import workspace_note

HINT = """Choose a **task** (held-out ones were never trained on), a **demonstration** of it and a scene
**seed**. **Plan** shows what the model sees and predicts; **Execute** runs it on the Franka Panda
(the Sawyer in Meta-World) live in the scene. Record demonstrations in *Teleop*, upload them in *Upload*, or make a scripted one here."""

HELD_OUT = " (held-out)"
SPEEDS = {"1× (real time)": 1.0, "0.5×": 0.5, "0.25×": 0.25, "as fast as possible": 0.0}
_WAYPOINT = re.compile(r"waypoint (\d+) of (\d+)")
EXPERT_LABEL = "Expert frames the model sees"
NONE = "(none)"


def frames_seen(checkpoint_path: str) -> int:
    """How many frames of a demonstration ``checkpoint_path``'s model looks at (10 for the oracle or unknown)."""
    if checkpoint_path == "oracle":
        return 10
    try:
        model = (read_checkpoint_info(checkpoint_path).get("config") or {}).get("model") or {}
        return int(model.get("n_expert_frames", 10))
    except (OSError, ValueError, TypeError, AttributeError):
        return 10


def task_labels() -> dict[str, str]:
    """Label shown in the dropdown -> task name; held-out (test) tasks first and marked."""
    labels: dict[str, str] = {}
    for scene in SCENES:
        tasks = list_tasks(scene)
        try:
            held = set(load_split(scene).test)
        except ValueError:
            held = set()
        for t in sorted(tasks, key=lambda t: t not in held):
            labels[t + (HELD_OUT if t in held else "")] = t
    return labels


def task_protocol(task: str) -> tuple[int | None, str]:
    """What ``task``'s scene's evaluation protocol (its split's; Meta-World: the paper's) says of it: the re-plans
    it allows (``SplitSpec.protocol_replans``; None where the protocol says nothing: no protocol, a training task,
    and the field keeps what the person chose) and the line under *Re-plans* ('' without a protocol)."""
    try:
        split = load_split(task.split("/", 1)[0])
    except ValueError:
        return None, ""
    replans = split.protocol_replans(task)
    if replans is None:
        bound = f"Each plan executes at most {split.plan_ticks} control ticks" if split.plan_ticks else ""
        return None, f"*{bound}, as `studio results` measures this scene.*" if bound else ""
    attempts = f"{replans} re-plans" if replans else "one attempt, no re-plans"
    bound = f"; each plan executes at most {split.plan_ticks} control ticks" if split.plan_ticks else ""
    return replans, f"*How `studio results` measures this task: {attempts}{bound}.*"


class ImitatePanel:
    """The *Imitate* tab."""

    def __init__(self, tab):
        self.tab = tab
        self.app = tab.app
        self.labels = task_labels()
        self.plan_job = None
        self.expert_job = None
        self.rollout = None
        self.plan_wps: np.ndarray | None = None
        self._listener = None
        self._rollout_token = 0
        self._demo_version = -1
        self._shown: dict[str, object] = {}
        self._frames_of: str | None = None  # the demonstration whose frames the panel shows
        self._expert_frames: np.ndarray | None = None  # those frames, full size (for Enlarge)
        self._agent_frame: np.ndarray | None = None
        self._latents: np.ndarray | None = None
        gui = tab.client.gui
        gui.add_markdown(HINT)
        first = next(iter(self.labels))
        self.task = gui.add_dropdown("Task", tuple(self.labels), initial_value=first)
        self.demo = gui.add_dropdown("Demonstration", ("(none)",))
        self.scripted = gui.add_button(
            "Make a scripted demonstration",
            icon="robot",
            hint="records the scene's scripted Sawyer expert (seed = Seed + 1000)",
        )
        self.seed = gui.add_number(
            "Seed", initial_value=0, min=0, step=1, hint="the scene the robot starts in"
        )
        self.replans = gui.add_number(
            "Re-plans",
            initial_value=1,
            min=0,
            max=5,
            step=1,
            hint="re-plans allowed within the episode after a failed attempt",
        )
        self.protocol_note = gui.add_markdown("")
        self.speed = gui.add_dropdown(
            "Speed",
            tuple(SPEEDS),
            initial_value="1× (real time)",
            hint="how fast the rollout runs while you watch it",
        )
        self.policy = gui.add_markdown("")
        with gui.add_folder("About this policy", expand_by_default=False):
            self.policy_details = gui.add_markdown("")
        buttons = gui.add_button_group("Run", ("Plan", "Execute", "Re-plan", "Cancel"))
        self.buttons = buttons
        self.watch = gui.add_button("Watch the running rollout", visible=False)
        self.status = gui.add_markdown("")
        self.score_note = gui.add_markdown("")
        self.outcome = gui.add_markdown("")
        self.enlarge = gui.add_button(
            "Enlarge",
            icon="arrows-maximize",
            visible=False,
            hint="the expert frames, the agent's frame and the latent images, large",
        )
        self.expert_strip = gui.add_image(
            np.full((20, 100, 3), 255, np.uint8), label=EXPERT_LABEL, visible=False
        )
        self.agent_image = gui.add_image(
            np.full((20, 100, 3), 255, np.uint8), label="Agent's first frame", visible=False
        )
        self.latent_strip = gui.add_image(
            np.full((20, 100, 3), 255, np.uint8), label="Predicted latent trajectory (decoded)", visible=False
        )
        self.latent_note = gui.add_markdown("")
        self._apply_protocol()
        self.task.on_update(self._on_task_chosen)
        self.demo.on_update(lambda e: self._show_policy())  # a human video may have its own policy
        self.enlarge.on_click(lambda _: tab.run(self.open_enlarged, "enlarging the images"))
        self.scripted.on_click(lambda _: tab.run(self.make_scripted, "making a scripted demonstration"))
        buttons.on_click(self._on_button)
        self.watch.on_click(lambda _: tab.run(self._watch_other, "watching the rollout"))

    # ------------------------------------------------------------------ choices
    @property
    def task_name(self) -> str:
        return self.labels[self.task.value]

    def demonstrator(self) -> str | None:
        """The embodiment of the chosen demonstration (``human``, ``sawyer``, ``panda``); None without one."""
        parts = self.demo.value.split(" · ")
        return parts[-1] if len(parts) >= 3 else None

    def policy_for(self, task: str, demonstrator: str | None = None) -> Checkpoint:
        """The active policy of ``task``'s scene for a demonstration by ``demonstrator`` (see
        :meth:`studio.ui.runs.RunRegistry.active`); raises ``SceneMismatch`` (a ``ValueError``, shown as a
        notification) when the choice for that scene was trained on another one."""
        return self.app.runs.active(task.split("/", 1)[0], demonstrator)

    def policy_text(self, task: str, demonstrator: str | None = None) -> str:
        """The policy line: which policy plans ``task`` (its scene's) from a ``demonstrator``'s demonstration,
        and why that one, in a few words (what was measured is :meth:`policy_about`)."""
        scene = task.split("/", 1)[0]
        head = f"Policy for **{scene}** tasks:"
        try:
            ck = self.policy_for(task, demonstrator)
        except SceneMismatch as e:
            return f"{head} ✘ {e}. Plan and Execute refuse to run it."
        chosen = self.app.runs.chosen_ids().get(scene) == ck.id
        if ck.is_oracle:
            why = "chosen in Train" if chosen else f"no policy for {scene} is shipped or chosen in Train"
            return f"{head} **oracle — execution ceiling** (plans from the simulator's true state, not a model; {why})"
        if chosen:
            origin = " (chosen in Train)"
        elif demonstrator is not None and demonstrator in ck.demonstrators:
            origin = f" (learnt from {demonstrator} demonstrations, like this one)"
        else:
            origin = ""
        return f"{head} `{ck.id}`{origin}"

    def policy_about(self, task: str, demonstrator: str | None = None) -> str:
        """The fold under the policy line: the policy's measured results (its ``NAME.json`` summary) and file."""
        try:
            ck = self.policy_for(task, demonstrator)
        except SceneMismatch as e:
            return f"Refused: {e}."
        if ck.is_oracle:
            return (
                "The oracle plans the scripted expert's waypoints from the simulator's true state: what execution "
                "reaches with a perfect plan, not a model."
            )
        summary = ck.summary or "No measured results are recorded with this checkpoint."
        return f"{summary}\n\nFile: `{ck.path}`"

    def _on_task_chosen(self, event: Any) -> None:
        """Another task: its demonstrations, the policy that plans it and its scene's protocol."""
        self._fill_demos()
        self._show_policy()
        self._apply_protocol()

    def _apply_protocol(self) -> None:
        """A held-out task of a scene whose split has an evaluation protocol (Meta-World: the paper's) gets that
        protocol's re-plans, said under the field; execution bounds each plan as the protocol does."""
        replans, text = task_protocol(self.task_name)
        if replans is not None:
            self.replans.value = replans
        if self._shown.get("protocol") != text:
            self._shown["protocol"] = text
            self.protocol_note.content = text

    def _show_policy(self) -> None:
        task, who = self.task_name, self.demonstrator()
        text, about = self.policy_text(task, who), self.policy_about(task, who)
        if self._shown.get("policy") != text:
            self._shown["policy"] = text
            self.policy.content = text
        if self._shown.get("policy_about") != about:
            self._shown["policy_about"] = about
            self.policy_details.content = about

    def _fill_demos(self) -> None:
        metas = self.app.store.episodes(task=self.task_name, role="expert", newest_first=True, limit=100)
        options = tuple(f"{m.id} · {m.source} · {m.embodiment}" for m in metas) or (NONE,)
        if self.demo.options != options:
            keep = self.demo.value
            self.demo.options = options
            if keep in options:
                self.demo.value = keep

    def selected_demo(self) -> str | None:
        """The id of the chosen demonstration; None when there is none."""
        eid = self.demo.value.split(" ")[0]
        return None if eid == NONE else eid

    def demo_id(self) -> str:
        eid = self.demo.value.split(" ")[0]
        if eid == NONE:
            raise ValueError(
                f"no demonstration of {self.task_name} yet: record, upload or make a scripted one"
            )
        return eid

    def _on_button(self, event) -> None:
        action = event.target.value
        if action == "Plan":
            self.tab.run(self.plan, "planning")
        elif action == "Execute":
            self.tab.run(self.execute, "starting the rollout")
        elif action == "Re-plan":
            self.tab.run(self.replan, "re-planning")
        elif action == "Cancel":
            self.tab.run(self.cancel, "cancelling")

    # ------------------------------------------------------------------ what is shown
    def shown_demo(self) -> str | None:
        """The demonstration whose frames the panel must show: the running rollout's while one is attached and
        running, else the one chosen."""
        if self.rollout is not None and not self.rollout.terminal:
            return str(self.rollout.spec["expert_episode_id"])
        return self.selected_demo()

    def show_expert_frames(self, episode_id: str | None, n: int | None = None) -> None:
        """Show the frames of ``episode_id`` the model sees (``n`` of them; by default as many as the policy of the
        task looks at), labelled with the demonstration's id; None hides them. A plan made from another
        demonstration is cleared: its waypoints, latent images and score no longer belong to what is shown."""
        if episode_id == self._frames_of and n is None:
            return
        planned = self.plan_job.spec.get("expert_episode_id") if self.plan_job is not None else None
        if episode_id != planned and self._frames_of is not None and self.rollout_idle():
            self._clear_plan(
                f"Demonstration changed to `{episode_id}`: **Plan** again to see its plan."
                if episode_id
                else ""
            )
        self._frames_of = episode_id
        if episode_id is None:
            self.expert_strip.visible = False
            self._expert_frames = None
            return
        if n is None:
            try:
                n = frames_seen(self.policy_for(self.task_name, self.demonstrator()).path)
            except ValueError:
                n = 10
        try:
            frames = self.app.store.load_frames(episode_id)
        except (KeyError, OSError, ValueError) as e:  # deleted meanwhile, or unreadable: say so, show nothing
            self.expert_strip.visible = False
            self._expert_frames = None
            self.status.content = f"Demonstration `{episode_id}` cannot be shown: {e}"
            return
        idx = expert_indices(len(frames), n)
        self._expert_frames = frames[idx]
        self.expert_strip.image = filmstrip(
            frames[idx], cols=5, height=60, labels=[str(i + 1) for i in range(len(idx))]
        )
        self.expert_strip.label = f"{EXPERT_LABEL} — {episode_id}"
        self.expert_strip.visible = True
        self.enlarge.visible = True

    def rollout_idle(self) -> bool:
        return self.rollout is None or self.rollout.terminal

    def _clear_plan(self, status: str) -> None:
        """Forget the shown plan (its waypoints, agent frame, latent images and score)."""
        self.plan_wps = None
        self._agent_frame, self._latents = None, None
        self.agent_image.visible = False
        self.latent_strip.visible = False
        self.latent_note.content = ""
        self.score_note.content = ""
        if self.tab.mode == "imitate" and self.tab.token != self._rollout_token:
            self.tab.view.clear_overlay("plan")
            self.tab.view.show_null_plan(None)
        if status:
            self.status.content = status

    def enlarged_images(self) -> list[tuple[str, np.ndarray]]:
        """What *Enlarge* shows: the expert frames, the agent's first frame and the decoded latent images."""
        images = []
        if self._expert_frames is not None:
            frames = self._expert_frames
            images.append(
                (
                    f"{EXPERT_LABEL} — {self._frames_of}",
                    filmstrip(
                        frames,
                        cols=5,
                        height=ENLARGED_HEIGHT,
                        labels=[str(i + 1) for i in range(len(frames))],
                    ),
                )
            )
        if self._agent_frame is not None:
            images.append(("Agent's first frame", thumbnail(self._agent_frame, 2 * ENLARGED_HEIGHT)))
        if self._latents is not None:
            lat = self._latents
            images.append(
                (
                    "Predicted latent trajectory (decoded)",
                    filmstrip(
                        lat,
                        cols=min(5, len(lat)),
                        height=ENLARGED_HEIGHT,
                        labels=[f"t{i + 2}" for i in range(len(lat))],
                    ),
                )
            )
        return images

    def open_enlarged(self) -> None:
        images = self.enlarged_images()
        if not images:
            raise ValueError("nothing to enlarge yet: choose a demonstration or Plan")
        open_enlarged(self.tab.client.gui, "Imitate — enlarged", images)

    # ------------------------------------------------------------------ actions
    def make_scripted(self):
        task = self.task_name
        self.expert_job = self.app.jobs.submit(
            "expert",
            {"task": task, "seed": int(self.seed.value) + 1000},
            started_by=self.tab.client.client_id,
        )
        self.status.content = f"Recording a scripted demonstration of **{task}**…"
        return self.expert_job

    def _show_scene(self, task: str, seed: int, note: str) -> int:
        scene = task.split("/", 1)[0]
        geometry, poses = self.app.geometry(scene, "panda" if scene != "metaworld" else "sawyer", task, seed)
        token = self.tab.set_mode("imitate", note)
        self.tab.view.load(geometry, ("local", scene, task if scene == "metaworld" else ""))
        self.tab.push_poses(token, poses)
        return token

    def _robot(self, task: str) -> str:
        return "sawyer" if task.startswith("metaworld/") else "panda"

    def plan(self):
        task, seed, demo = self.task_name, int(self.seed.value), self.demo_id()
        ck = self.policy_for(task, self.demonstrator())
        self._show_scene(task, seed, f"Plan for **{task}**, seed {seed}.")
        self.tab.view.clear_overlay("plan")
        self.tab.view.show_null_plan(None)
        self.plan_job = self.app.jobs.submit(
            "plan",
            {
                "checkpoint": ck.path,
                "expert_episode_id": demo,
                "task": task,
                "seed": seed,
                "robot": self._robot(task),
            },
            started_by=self.tab.client.client_id,
        )
        self._clear_plan("")  # the previous plan's images must not pass for this one's
        self.show_expert_frames(demo, frames_seen(ck.path))
        self.status.content = f"Planning with {'the **oracle**' if ck.is_oracle else f'`{ck.id}`'}…"
        self.outcome.content = ""
        return self.plan_job

    def _show_plan(self, tracked) -> None:
        result = tracked.result or {}
        data = np.load(self.app.data_dir / result["path"])
        predicted = np.asarray(data["waypoints_world"])
        self.plan_wps = (
            np.asarray(data["waypoints_commanded"]) if "waypoints_commanded" in data else predicted
        )
        if tracked.spec["expert_episode_id"] != self.shown_demo():
            self.plan_wps = None  # planned from a demonstration no longer chosen: not shown
            self.status.content = (
                f"The plan of `{tracked.spec['expert_episode_id']}` is not shown: another demonstration is chosen "
                "now. **Plan** again."
            )
            return
        self.tab.view.show_waypoints("plan", self.plan_wps)
        self.tab.view.show_null_plan(data["null_waypoints_world"] if "null_waypoints_world" in data else None)
        self.show_expert_frames(tracked.spec["expert_episode_id"], len(data["expert_indices"]))
        self._agent_frame = np.asarray(data["agent_frame"])
        self.agent_image.image = thumbnail(data["agent_frame"], 150)
        self.agent_image.visible = True
        self.tab.view.set_camera_image(data["agent_frame"])
        if "latent_images" in data:
            lat = data["latent_images"]
            self._latents = np.asarray(lat)
            self.latent_strip.image = filmstrip(
                lat, cols=min(5, len(lat)), height=60, labels=[f"t{i + 2}" for i in range(len(lat))]
            )
            self.latent_strip.visible = True
            self.latent_note.content = ""
        else:
            self.latent_strip.visible = False
            why = (
                "the oracle has no latent states"
                if tracked.spec["checkpoint"] == "oracle"
                else "this checkpoint has no latent decoder (`studio train-decoder`)"
            )
            self.latent_note.content = f"No decoded latent images: {why}."
        grip = " ".join("●" if g > 0.5 else "○" for g in self.plan_wps[:, 3])
        self.status.content = (
            (
                f"Planned in {result.get('planning_time_s', 0.0) * 1e3:.0f} ms. Waypoints 1–5, gripper {grip} "
                "(● closed). **Execute** to run it."
            )
            + workspace_note(predicted, self.plan_wps)
            + guidance_note(result.get("guidance"))
        )
        self.score_note.content = demo_score_note(result.get("demo_score"))

    def execute(self):
        task, seed, demo = self.task_name, int(self.seed.value), self.demo_id()
        ck = self.policy_for(task, self.demonstrator())
        replans = int(self.replans.value)
        spec = {
            "checkpoint": ck.path,
            "checkpoint_id": ck.id,
            "expert_episode_id": demo,
            "task": task,
            "seed": seed,
            "replans": replans,
            "robot": self._robot(task),
            "speed": SPEEDS[self.speed.value],
        }
        self.app.runs.register_checkpoint(self.app.store.catalog, ck)  # the stored rollout refers to it
        tracked = self.app.jobs.submit("rollout", spec, started_by=self.tab.client.client_id)
        self.outcome.content = ""
        self.attach(tracked)
        return tracked

    def replan(self):
        if self.rollout is None or not self.rollout.terminal:
            raise ValueError("re-planning continues a finished, failed rollout: Execute first")
        if (self.rollout.result or {}).get("success"):
            raise ValueError("the rollout succeeded: there is nothing to re-plan")
        self.replans.value = int(self.rollout.spec.get("replans", 0)) + 1
        return self.execute()

    def cancel(self) -> None:
        for tracked in (self.rollout, self.plan_job, self.expert_job):
            if tracked is not None and not tracked.terminal:
                self.app.jobs.cancel(tracked.job)

    def attach(self, tracked) -> None:
        """Show a rollout job live in this tab's scene."""
        self.detach()
        spec = tracked.spec
        self.rollout = tracked
        token = self._show_scene(
            spec["task"],
            int(spec["seed"]),
            f"Rollout `{tracked.job}` — **{spec['task']}**, seed {spec['seed']} (live).",
        )
        self._rollout_token = token

        def on_frame(frame) -> None:
            self.tab.push_poses(token, frame.poses_array())

        self._listener = on_frame
        tracked.add_pose_listener(on_frame)
        planned = self.plan_job.spec if self.plan_job is not None else {}
        same = all(planned.get(k) == spec.get(k) for k in ("task", "seed", "expert_episode_id", "checkpoint"))
        if self.plan_wps is not None and same:
            self.tab.view.show_waypoints("plan", self.plan_wps)
        self.show_expert_frames(str(spec["expert_episode_id"]), frames_seen(str(spec["checkpoint"])))
        self.status.content = "Starting the rollout…"

    def detach(self) -> None:
        if self.rollout is not None and self._listener is not None:
            self.rollout.remove_pose_listener(self._listener)
        self._listener = None

    def _watch_other(self) -> None:
        for s in reversed(self.app.hub.jobs.jobs()):
            if s.kind == "rollout" and not s.terminal and (self.rollout is None or s.job != self.rollout.job):
                self.attach(self.app.jobs.follow(s.job, "rollout", s.spec))
                return

    # ------------------------------------------------------------------ refresh
    def refresh(self) -> None:
        if self.app.dataset_version != self._demo_version:
            self._demo_version = self.app.dataset_version
            self._fill_demos()
        self._show_policy()
        if self.shown_demo() != self._frames_of:
            self.show_expert_frames(self.shown_demo())
        self._refresh_expert_job()
        self._refresh_plan_job()
        self._refresh_rollout()
        others = any(
            s.kind == "rollout" and not s.terminal and (self.rollout is None or s.job != self.rollout.job)
            for s in self.app.hub.jobs.jobs()
        )
        if self.watch.visible != others:
            self.watch.visible = others

    def _refresh_expert_job(self) -> None:
        job = self.expert_job
        if job is None or not job.terminal or job is self._shown.get("expert_done"):
            return
        if job.state == "succeeded" and job.result is None:
            return
        self._shown["expert_done"] = job
        if job.state == "succeeded":
            eid = job.result["episode_id"]
            self._fill_demos()
            match = [o for o in self.demo.options if o.startswith(eid)]
            if match:
                self.demo.value = match[0]
            # Its frames now, not at the next refresh: that one would clear a plan of the previous demonstration
            # with "Demonstration changed", over this message, before the page had shown it.
            self.show_expert_frames(self.shown_demo())
            self.status.content = f"Scripted demonstration `{eid}` stored and selected."
            self.app.dataset_changed()
        else:
            self.status.content = f"Scripted demonstration failed: {job.status.reason}"
            self.tab.notify("No scripted demonstration", job.status.reason, error=True)

    def _refresh_plan_job(self) -> None:
        job = self.plan_job
        if job is None or job is self._shown.get("plan_done"):
            return
        if not job.terminal:
            if job.progress is not None and job.progress.message:
                self.status.content = f"Plan: {job.progress.message}…"
            elif job.status is not None and job.status.state == "queued":
                self.status.content = f"Plan queued: {job.status.reason}"
            return
        if job.state == "succeeded" and job.result is None:
            return
        self._shown["plan_done"] = job
        if job.state == "succeeded":
            self.tab.run(lambda: self._show_plan(job), "showing the plan")
        else:
            self.status.content = f"Planning {job.state}: {job.status.reason}"
            self.tab.notify("Planning failed", job.status.reason, error=True)

    def _refresh_rollout(self) -> None:
        job = self.rollout
        if job is None:
            return
        p = job.progress
        msg_text = p.message if p is not None else ""
        n_plans = len(job.plans)
        key = (job.state, msg_text, n_plans, job.result is not None)
        if self._shown.get("rollout") == key:
            return
        self._shown["rollout"] = key
        if n_plans:
            current = None
            m = _WAYPOINT.match(msg_text)
            if m:
                current = int(m.group(1)) - 1
            if self.tab.token == self._rollout_token:
                self.tab.view.show_waypoints("plan", job.plans[-1], current=current)
        if not job.terminal:
            where = f"plan {n_plans}" if n_plans else "planning"
            self.status.content = f"Rollout `{job.job}` ({where}): **{msg_text or job.state}**"
            return
        if job.state == "succeeded" and job.result is None:
            return
        self.detach()
        if job.state != "succeeded":
            self.outcome.content = f"### ✘ Rollout {job.state}\n{job.status.reason}"
            return
        r = job.result
        self.score_note.content = demo_score_note(r.get("demo_score"))
        if r["success"]:
            self.outcome.content = f"### ✔ Success\n{r['replans']} re-plan(s); rollout `{r['rollout_id']}`."
        else:
            self.outcome.content = (
                f"### ✘ Failed at {r['failure_stage']}\nafter {r['replans']} re-plan(s); rollout "
                f"`{r['rollout_id']}` (open it in *Inspect*). **Re-plan** tries once more in the same episode."
            )
        self.status.content = f"Rollout `{job.job}` finished: {'success' if r['success'] else 'failure'}."
        self.app.dataset_changed()

    def close(self) -> None:
        self.detach()
