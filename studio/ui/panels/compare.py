"""Compare: two checkpoints on the same seeded scenes and demonstrations, then any seed played side by side.

*Start* runs a ``compare`` job on a sim worker (:mod:`studio.eval.compare`, as ``studio compare``): every episode
— (task, scene seed, demonstration) drawn once — is rolled out by A and by B and stored. The panel shows the job's
progress, then the totals, a dropdown of the compared seeds (differing first) and the per-seed table. Two
evaluations already in the catalog that share episodes (``studio eval`` runs, earlier comparisons) can be compared
without running anything.

*Open* plays the two rollouts of one seed on ONE timeline: the camera frames of A and B at the same control step
side by side, the scene with the poses of A (or B: *Scene shows*), both end-effector paths in their colours with a
sphere where each gripper is at that step, and what each rollout was doing then. The timeline spans the longer
rollout; the shorter holds its last frame. *Enlarge* shows the two camera views large, in a modal window that
follows the timeline.

Checkpoints A and B offer only what may plan the chosen scene (checkpoints trained on it, read from their files
without torch, and the oracle); a fresh tab, or a change of scene, starts from the scene's active policy (A) and the
best other one (B, :func:`studio.eval.compare.default_pair`). Tasks that have no demonstration in the store get one
first: *Start* makes a scripted demonstration of each on a sim worker (the ``expert`` job Imitate's *Make a
scripted demonstration* runs), says so in the progress line, and starts the comparison once they are stored.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from studio.backend.replay import EpisodeReplay
from studio.data.catalog import RolloutRecord
from studio.eval.compare import (
    Candidate,
    CompareRow,
    compare_stored,
    default_pair,
    rank_candidates,
    recorded_held_out,
    render_markdown,
    stage_at,
    stored_evaluations,
    task_list,
    totals,
    totals_line,
)
from studio.eval.evaluation import default_expert_embodiments
from studio.sim.tasks import list_tasks
from studio.ui.images import ENLARGED_HEIGHT, filmstrip, open_enlarged
from studio.ui.job_board import TrackedJob
from studio.ui.runs import Checkpoint, RunRegistry, SceneMismatch
from studio.ui.timeline import Timeline

HINT = """Run two checkpoints on the **same** seeded scenes and demonstrations and see where they differ.
**Start** rolls out every episode with A and with B on a sim worker (all stored). Then choose a seed and
**Open** it: one timeline plays both rollouts side by side."""

SCENES = ("pick_place", "push", "metaworld")
SPLIT_CHOICES = ("held-out", "train", "all")
NONE = "(none)"
#: The two rollouts' colours: paths and end-effector spheres in the scene.
A_RGB = (40, 110, 235)
B_RGB = (225, 50, 170)
#: Seconds between re-reads of the checkpoint list (run directories on disk).
CHOICES_EVERY_S = 5.0
#: Seeds a missing scripted demonstration is tried with before the comparison gives up on it.
SCRIPTED_SEEDS = (2000, 2001, 2002)


def candidate(ck: Checkpoint) -> Candidate:
    """How :func:`~studio.eval.compare.default_pair` sees a checkpoint: the held-out success its ``NAME.json``
    records (a shipped policy's), and when its file was written."""
    if ck.is_oracle:
        return Candidate(ck.id, oracle=True)
    try:
        about = json.loads(Path(ck.path).with_suffix(".json").read_text())
    except (OSError, ValueError):
        about = {}
    try:
        created = os.stat(ck.path).st_mtime
    except OSError:
        created = 0.0
    return Candidate(ck.id, recorded_held_out(about) if isinstance(about, dict) else None, created)


def scene_checkpoints(runs: RunRegistry, scene: str) -> list[Checkpoint]:
    """The checkpoints that may plan ``scene``'s tasks (trained on it, and the oracle), best first."""
    cks = {c.id: c for c in runs.checkpoints() if c.plans(scene)}
    return [cks[c.id] for c in rank_candidates(candidate(ck) for ck in cks.values())]


def default_checkpoints(runs: RunRegistry, scene: str) -> tuple[str, str]:
    """The ids of A and B a comparison on ``scene`` starts with: the scene's active policy and the best other
    checkpoint of the scene (:func:`studio.eval.compare.default_pair`)."""
    try:
        active: str | None = runs.active(scene).id
    except SceneMismatch:
        active = None  # the choice for this scene is refused: it is not offered either
    return default_pair([candidate(c) for c in scene_checkpoints(runs, scene)], active)


@dataclass
class ScriptedDemos:
    """Scripted demonstrations being made for tasks that have none, before the comparison ``spec`` starts."""

    spec: dict
    labels: tuple[str, str]
    tasks: list[str]
    jobs: dict[str, TrackedJob] = field(default_factory=dict)  # task -> its expert job
    tries: dict[str, int] = field(default_factory=dict)  # task -> seeds tried
    done: set[str] = field(default_factory=set)


def task_choices(scene: str) -> tuple[str, ...]:
    """The split words, then every task of ``scene``."""
    return (*SPLIT_CHOICES, *list_tasks(scene))


def seed_label(k: int, row: CompareRow) -> str:
    return (
        f"{k + 1}. {row.task.split('/', 1)[-1]} #{row.index} · seed {row.seed} · {row.difference} "
        f"(A {row.a.mark}, B {row.b.mark})"
    )


@dataclass
class OpenedRollout:
    """One opened rollout: its catalog row, its replay and frames, what to call it."""

    name: str
    label: str
    record: RolloutRecord
    replay: EpisodeReplay
    frames: np.ndarray
    plan_starts: np.ndarray

    @property
    def steps(self) -> int:
        return int(self.replay.num_steps)

    def frame_at(self, step: int) -> np.ndarray:
        fsteps = self.replay.frame_steps
        i = int(np.clip(np.searchsorted(fsteps, step, side="right") - 1, 0, len(self.frames) - 1))
        return self.frames[i]

    def short(self, step: int) -> str:
        """A few ASCII words for the label drawn on its camera frame."""
        r = self.record
        if step >= self.steps - 1:
            return "ended: success" if r.success else f"ended: failed at {r.failure_stage}"
        return stage_at((r.extra or {}).get("stage_ticks"), step) or f"step {step}"

    def describe(self, step: int) -> str:
        """What this rollout was doing at ``step`` (held at its end once it is over)."""
        r = self.record
        last = self.steps - 1
        outcome = "✔ success" if r.success else f"✘ failed at {r.failure_stage}"
        if step >= last:
            return f"ended at step {last}: {outcome}" + (" (holding its last frame)" if step > last else "")
        doing = stage_at((r.extra or {}).get("stage_ticks"), step)
        text = doing or "stage timing not recorded"
        if len(self.plan_starts) > 1:
            k = int(max(0, np.searchsorted(self.plan_starts, step, side="right") - 1))
            text += f", plan {k + 1} of {len(self.plan_starts)}"
        return text


class ComparePanel:
    """The *Compare* tab."""

    def __init__(self, tab):
        self.tab = tab
        self.app = tab.app
        self.job = None
        self.rows: list[CompareRow] = []
        self.labels = ("A", "B")
        self.sides: tuple[OpenedRollout, OpenedRollout] | None = None
        self._token = 0
        self._version = -1
        self._choices_at = -CHOICES_EVERY_S
        self._shown: dict[str, object] = {}
        self._stored: dict[str, str] = {}  # description shown -> evaluation id
        self._prefer: list[str] | None = None  # evaluation ids to select when the list is next filled
        self._filled = False
        gui = tab.client.gui
        gui.add_markdown(HINT)
        self.making: ScriptedDemos | None = None
        self._pair_scene: str | None = None  # the scene A and B were last chosen for
        self.scene = gui.add_dropdown("Scene", SCENES, initial_value="pick_place")
        self.ck_a = gui.add_dropdown(
            "Checkpoint A", ("oracle",), hint="checkpoints of the chosen scene, best first"
        )
        self.ck_b = gui.add_dropdown(
            "Checkpoint B", ("oracle",), hint="checkpoints of the chosen scene, best first"
        )
        self.tasks = gui.add_dropdown("Tasks", task_choices("pick_place"), initial_value="held-out")
        self.episodes = gui.add_number("Episodes per task", initial_value=5, min=1, max=500, step=1)
        self.seed = gui.add_number(
            "Seed", initial_value=0, min=0, step=1, hint="the evaluation seed, as in studio eval"
        )
        self.replans = gui.add_number("Re-plans", initial_value=0, min=0, max=5, step=1)
        self.buttons = gui.add_button_group("Compare", ("Start", "Cancel"))
        self.status = gui.add_markdown("")
        with gui.add_folder("Stored evaluations", expand_by_default=False):
            self.eval_a = gui.add_dropdown("Evaluation A", (NONE,))
            self.eval_b = gui.add_dropdown("Evaluation B", (NONE,))
            self.stored_button = gui.add_button(
                "Compare stored rollouts",
                icon="table",
                hint="their shared (task, seed, demonstration) episodes; nothing runs",
            )
        self.totals = gui.add_markdown("")
        self.pick = gui.add_dropdown("Compared seed", (NONE,))
        self.open_button = gui.add_button("Open side by side", icon="timeline")
        self.shows = gui.add_dropdown(
            "Scene shows",
            ("A", "B"),
            initial_value="A",
            hint="whose poses the 3D scene shows; both paths are drawn",
        )
        self.info = gui.add_markdown("")
        self.image = gui.add_image(
            np.full((120, 320, 3), 255, np.uint8), label="Camera: A (left) · B (right)", visible=False
        )
        self.enlarge = gui.add_button(
            "Enlarge",
            icon="arrows-maximize",
            visible=False,
            hint="A's and B's camera views large; they follow the timeline",
        )
        self._enlarged: list = []  # the open Enlarge modal's image, updated as the timeline moves
        self.timeline = Timeline(gui, "Step", self._show_step, fps=30.0)
        self.step_info = gui.add_markdown("")
        with gui.add_folder("Per-seed table"):
            self.table = gui.add_markdown("")
        self.scene.on_update(self._on_scene_chosen)
        self.enlarge.on_click(lambda _: tab.run(self.open_enlarged, "enlarging the camera views"))
        self.buttons.on_click(self._on_button)
        self.stored_button.on_click(lambda _: tab.run(self.compare_stored, "comparing stored rollouts"))
        self.open_button.on_click(lambda _: tab.run(self.open_selected, "opening the compared rollouts"))
        self.shows.on_update(lambda _: self._show_step(int(self.timeline.slider.value)))

    # ------------------------------------------------------------------ choices
    def _on_scene_chosen(self, event: Any) -> None:
        """Another scene: its tasks and checkpoints."""
        self._fill_tasks()
        self._fill_checkpoints()

    def _fill_tasks(self) -> None:
        options = task_choices(self.scene.value)
        if self.tasks.options != options:
            self.tasks.options = options
            self.tasks.value = "held-out"

    def _fill_checkpoints(self) -> None:
        scene = self.scene.value
        ids = tuple(c.id for c in scene_checkpoints(self.app.runs, scene))
        fresh = self._pair_scene != scene  # a new tab, or another scene: start from the scene's defaults
        self._pair_scene = scene
        defaults = default_checkpoints(self.app.runs, scene)
        for k, dd in enumerate((self.ck_a, self.ck_b)):
            if dd.options != ids:
                dd.options = ids
            value = defaults[k] if fresh or dd.value not in ids else dd.value
            if dd.value != value:
                dd.value = value

    def _fill_stored(self) -> None:
        before = [self._stored.get(dd.value) for dd in (self.eval_a, self.eval_b)]
        evals = stored_evaluations(self.app.store.catalog)
        self._stored = {e.describe(): e.eval_id for e in evals}
        label_of = {eval_id: label for label, eval_id in self._stored.items()}
        options = tuple(self._stored) or (NONE,)
        # The comparison that just finished, else what was chosen, else the newest comparison's two sides (listed
        # newest first: B's side, then A's).
        wanted = self._prefer if self._prefer is not None else before
        self._prefer = None
        for k, dd in enumerate((self.eval_a, self.eval_b)):
            if dd.options != options:
                dd.options = options
            value = label_of.get(wanted[k] or "", options[min(1 - k, len(options) - 1)])
            if dd.value != value:
                dd.value = value

    def _on_button(self, event) -> None:
        if event.target.value == "Start" and self.making is not None:
            self.tab.notify(
                "Comparison", "scripted demonstrations are being made for it; it starts after them"
            )
        elif event.target.value == "Start":
            self.tab.run(self.start, "starting the comparison")
        else:
            self.tab.run(self.cancel, "cancelling the comparison")

    # ------------------------------------------------------------------ actions
    def start(self):
        scene = self.scene.value
        choices = {c.id: c for c in self.app.runs.checkpoints()}
        a, b = choices.get(self.ck_a.value), choices.get(self.ck_b.value)
        if a is None or b is None:
            raise ValueError("choose checkpoints A and B")
        for ck in (a, b):
            if not ck.plans(scene):
                raise ValueError(
                    f"`{ck.id}` was trained on {ck.scene or 'no one scene'}'s tasks, not on {scene}'s"
                )
        for ck in (a, b):
            self.app.runs.register_checkpoint(self.app.store.catalog, ck)  # the stored rollouts refer to it
        spec = {
            "a": a.path,
            "b": b.path,
            "label_a": a.id,
            "label_b": b.id,
            "checkpoint_id_a": None if a.is_oracle else a.id,
            "checkpoint_id_b": None if b.is_oracle else b.id,
            "scene": scene,
            "tasks": self.tasks.value,
            "episodes": int(self.episodes.value),
            "seed": int(self.seed.value),
            "replan": int(self.replans.value),
        }
        missing = self.tasks_without_demonstrations(scene, task_list(scene, self.tasks.value))
        if missing:
            self.making = ScriptedDemos(spec, (a.id, b.id), missing)
            for task in missing:
                self._make_scripted(task)
            self._show_making()
            return None
        return self._submit(spec, (a.id, b.id))

    def tasks_without_demonstrations(self, scene: str, tasks: list[str]) -> list[str]:
        """Those of ``tasks`` the store has no demonstration of by the embodiments the comparison imitates."""
        who = list(default_expert_embodiments(scene))
        return [
            t for t in tasks if not self.app.store.episodes(task=t, role="expert", embodiment=who, limit=1)
        ]

    def _make_scripted(self, task: str) -> None:
        making = self.making
        assert making is not None
        tried = making.tries.get(task, 0)
        making.tries[task] = tried + 1
        making.jobs[task] = self.app.jobs.submit(
            "expert", {"task": task, "seed": SCRIPTED_SEEDS[tried]}, started_by=self.tab.client.client_id
        )

    def _show_making(self) -> None:
        making = self.making
        if making is None:
            return
        names = ", ".join(f"`{t}`" for t in making.tasks)
        text = (
            f"No demonstration of {names} is stored: making a scripted one of each on a sim worker (the `expert` "
            f"job of Imitate's *Make a scripted demonstration*), {len(making.done)} of {len(making.tasks)} "
            "stored; the comparison starts after them…"
        )
        if self._shown.get("status") != text:
            self._shown["status"] = text
            self.status.content = text

    def _refresh_making(self) -> None:
        making = self.making
        if making is None:
            return
        for task, job in list(making.jobs.items()):
            if task in making.done or not job.terminal or (job.state == "succeeded" and job.result is None):
                continue
            if job.state == "succeeded":
                making.done.add(task)
                self.app.dataset_changed()
            elif job.state == "failed" and making.tries[task] < len(SCRIPTED_SEEDS):
                self._make_scripted(task)  # the scripted expert failed on that seed: another one
            else:
                self.making = None
                reason = job.status.reason if job.status is not None else job.state
                self.status.content = (
                    f"No comparison: the scripted demonstration of `{task}` {job.state}: {reason}"
                )
                if job.state == "failed":
                    self.tab.notify(
                        "Comparison not started", f"no demonstration of {task}: {reason}", error=True
                    )
                return
        self._show_making()
        if len(making.done) == len(making.tasks):
            self.making = None
            self._submit(making.spec, making.labels, made=len(making.tasks))

    def _submit(self, spec: dict, labels: tuple[str, str], made: int = 0):
        self.job = self.app.jobs.submit("compare", spec, started_by=self.tab.client.client_id)
        note = f" with the {made} scripted demonstration(s) just made" if made else ""
        self.status.content = (
            f"Comparison `{self.job.job}` submitted{note}: **{labels[0]}** (A) against **{labels[1]}** (B)…"
        )
        self._shown["status"] = self.status.content
        return self.job

    def cancel(self) -> None:
        making, self.making = self.making, None
        if making is not None:
            for job in making.jobs.values():
                if not job.terminal:
                    self.app.jobs.cancel(job.job)
            self.status.content = (
                "Cancelled before the comparison started (scripted demonstrations stored stay)."
            )
        if self.job is not None and not self.job.terminal:
            self.app.jobs.cancel(self.job.job)

    def compare_stored(self) -> None:
        a, b = self._stored.get(self.eval_a.value), self._stored.get(self.eval_b.value)
        if a is None or b is None or a == b:
            raise ValueError("choose two different stored evaluations")
        rows = compare_stored(self.app.store.catalog, a, b)
        if not rows:
            raise ValueError(f"{a} and {b} share no (task, seed, demonstration) episode")
        by_id = {e.eval_id: e for e in stored_evaluations(self.app.store.catalog)}
        self.show_rows(rows, (by_id[a].label or by_id[a].checkpoint, by_id[b].label or by_id[b].checkpoint))
        self.status.content = f"Stored evaluations `{a}` (A) and `{b}` (B): {len(rows)} shared episodes."

    def show_rows(self, rows: list[CompareRow], labels: tuple[str, str]) -> None:
        """Show a comparison's rows (in table order): totals, the seed dropdown, the table."""
        self.rows, self.labels = list(rows), labels
        self.totals.content = totals_line(totals(rows), *labels)
        self.table.content = render_markdown(rows, *labels, compact=True)
        options = tuple(seed_label(k, r) for k, r in enumerate(rows)) or (NONE,)
        self.pick.options = options
        self.pick.value = options[0]

    def open_selected(self) -> None:
        options = list(self.pick.options)
        if not self.rows or self.pick.value not in options:
            raise ValueError("no compared seed to open: run or load a comparison first")
        self.open(self.rows[options.index(self.pick.value)])

    def open(self, row: CompareRow) -> None:
        store = self.app.store
        sides = []
        for name, outcome, label in (("A", row.a, self.labels[0]), ("B", row.b, self.labels[1])):
            record = store.catalog.get_rollout(outcome.rollout_id)
            if record is None:
                raise KeyError(f"no rollout {outcome.rollout_id} in the catalog")
            if record.episode_id is None:
                raise ValueError(f"rollout {record.id} was stored without its recording: nothing to play")
            starts = np.zeros(1, np.int64)
            if record.path and (Path(record.path) / "plans.npz").is_file():
                with np.load(Path(record.path) / "plans.npz") as plans:
                    starts = np.asarray(plans["plan_start_ticks"])
            sides.append(
                OpenedRollout(
                    name,
                    label,
                    record,
                    EpisodeReplay(store, record.episode_id),
                    store.load_frames(record.episode_id),
                    starts,
                )
            )
        a, b = sides
        self.sides = (a, b)
        meta = a.replay.meta
        self._token = self.tab.set_mode(
            "compare", f"Comparing `{row.task}` seed {row.seed}: A and B side by side."
        )
        view = self.tab.view
        view.load(
            a.replay.geometry,
            ("replay", meta.scene, meta.embodiment, meta.task if meta.scene == "metaworld" else ""),
        )
        view.set_camera(store.load_camera(a.record.episode_id).to_dict())
        view.show_path("path", a.replay.ee_path(), color=A_RGB)
        view.show_path("path_b", b.replay.ee_path(), color=B_RGB)
        self.info.content = (
            f"**{row.task}** #{row.index}, seed {row.seed}, demonstration `{row.expert_episode_id}` — "
            f"**A** {a.label}: {row.a.mark} ({a.steps} steps); **B** {b.label}: {row.b.mark} ({b.steps} steps). "
            f"Paths: A blue, B magenta; spheres: each gripper at this step."
        )
        self.image.visible = True
        self.enlarge.visible = True
        dt = meta.control_dt or 0.02
        self.timeline.reset(max(a.steps, b.steps), fps=min(30.0, 1.0 / max(dt, 1e-3)))

    # ------------------------------------------------------------------ playback
    def _show_step(self, step: int) -> None:
        if self.sides is None:
            return
        a, b = self.sides
        sa, sb = min(step, a.steps - 1), min(step, b.steps - 1)
        da, db = a.describe(step), b.describe(step)
        self.image.image = filmstrip(
            np.stack([a.frame_at(sa), b.frame_at(sb)]),
            cols=2,
            height=150,
            labels=[f"A: {a.short(step)}", f"B: {b.short(step)}"],
        )
        if self._enlarged:
            self._enlarged[0].image = self.enlarged_views(step)
        if self.tab.token == self._token:
            shown = a if self.shows.value == "A" else b
            self.tab.push_poses(self._token, shown.replay.poses_at(step))
            view = self.tab.view
            view.show_marker("ee_a", a.replay.ee_path()[sa], A_RGB)
            view.show_marker("ee_b", b.replay.ee_path()[sb], B_RGB)
            view.set_camera_image(shown.frame_at(min(step, shown.steps - 1)))
        self.step_info.content = (
            f"Step {step} of {max(a.steps, b.steps) - 1}. **A** ({a.label}): {da}. **B** ({b.label}): {db}. "
            f"The scene shows {self.shows.value}."
        )

    def enlarged_views(self, step: int) -> np.ndarray:
        """A's and B's camera frames at ``step``, side by side and large (what *Enlarge* shows)."""
        assert self.sides is not None
        a, b = self.sides
        frames = np.stack([a.frame_at(min(step, a.steps - 1)), b.frame_at(min(step, b.steps - 1))])
        return filmstrip(
            frames,
            cols=2,
            height=2 * ENLARGED_HEIGHT,
            gap=8,
            labels=[f"A {a.label}: {a.short(step)}", f"B {b.label}: {b.short(step)}"],
        )

    def open_enlarged(self) -> None:
        if self.sides is None:
            raise ValueError("open a compared seed first")
        step = int(self.timeline.slider.value)
        self._enlarged = open_enlarged(
            self.tab.client.gui,
            "Compare — camera views, A (left) and B (right)",
            [("Step follows the timeline", self.enlarged_views(step))],
            on_close=self._enlarged.clear,
        )

    # ------------------------------------------------------------------ refresh
    def refresh(self) -> None:
        now = time.monotonic()
        if now - self._choices_at >= CHOICES_EVERY_S:
            self._choices_at = now
            self._fill_checkpoints()
        if self.app.dataset_version != self._version:
            self._version = self.app.dataset_version
            self._fill_stored()
        self._refresh_making()
        self._refresh_job()

    def _refresh_job(self) -> None:
        job = self.job
        if job is None or job is self._shown.get("job_done"):
            return
        if not job.terminal:
            p = job.progress
            if p is not None and p.message:
                eta = f" — about {p.eta_s:.0f} s left" if p.eta_s else ""
                text = f"Comparison `{job.job}`: **{p.message}**{eta}"
            elif job.status is not None and job.status.state == "queued":
                text = f"Comparison `{job.job}` queued: {job.status.reason}"
            else:
                text = f"Comparison `{job.job}`: {job.state}…"
            if self._shown.get("status") != text:
                self._shown["status"] = text
                self.status.content = text
            return
        if job.state == "succeeded" and job.result is None:
            return  # the result is on its way
        self._shown["job_done"] = job
        if job.state != "succeeded":
            self.status.content = f"Comparison `{job.job}` {job.state}: {job.status.reason}"
            if job.state == "failed":
                self.tab.notify("Comparison failed", job.status.reason, error=True)
            return
        r = job.result
        rows = [CompareRow.from_dict(d) for d in r["rows"]]
        self.show_rows(rows, (r["label_a"], r["label_b"]))
        self._prefer = list(r["eval_ids"])
        self.status.content = (
            f"Comparison `{r['compare_id']}` finished: {len(rows)} episodes in {r['wall_s'] / 60:.1f} min; "
            f"stored as evaluations `{r['eval_ids'][0]}` (A) and `{r['eval_ids'][1]}` (B)."
        )
        self.app.dataset_changed()

    def close(self) -> None:
        self.timeline.close()
