"""Train: choose a configuration and the training tasks, start a ``train`` job, follow its loss curves,
progress and ETA, cancel it; fine-tune the scene's active policy on the user's episodes in one click; list runs and
checkpoints and choose the active policy of the chosen scene.

A run started here lives in ``<data-dir>/runs/<job-id>/`` (see :mod:`studio.ui.runs`); its task
selection is written there as a split file (the scene's held-out tasks stay held out). Curves come from
the run's ``metrics.jsonl`` (world-model and Soft-DTW losses, learning rate) when this host can read it,
otherwise from the job's progress stream.

Before anything trains the panel says how many training pairs the ticked tasks have and why stored episodes are
left out, counted by :func:`studio.model.train_command.count_training_pairs` — the selection the trainer itself
uses — and shows the run that Start would make of them: the batch (never larger than the pairs), the steps
(the configuration's epochs over the pairs) and, when a run of the same kind has measured its pace here, the
expected wall time. *Fine-tune the active policy on my episodes* queues the same ``train`` job as ``studio train
--init POLICY --fine-tune`` on the ticked tasks' episodes; *Make it the active policy* then hands the result to
Imitate.
"""

from __future__ import annotations

import json
import os
import threading
import time
from typing import Any

import numpy as np
import viser
import viser.uplot as uplot

from studio.backend.job_client import new_job_id
from studio.data.splits import SplitSpec, load_split
from studio.model.config import (
    FINE_TUNE_BATCH,
    PRESETS,
    RunConfig,
    fine_tune_steps,
    fit_batch,
    preset,
    steps_for,
)
from studio.model.train_command import count_training_pairs, init_config
from studio.ui.runs import SCENES, Checkpoint, SceneMismatch, read_metrics

HINT = """Pick a **configuration** (`cpu` trains in minutes on this machine, `paper` is the paper's model) and
the **training tasks**; held-out tasks are never trained on. *Overrides* are `section.field=value`
assignments separated by `;` (e.g. `train.batch_size=8; model.image_size=[96, 128]`). **Start** queues a
job for a trainer; the curves update live, **Cancel** stops after a checkpoint. **Fine-tune the active policy on
my episodes** continues the scene's active policy on the ticked tasks' episodes for a few minutes."""

FINE_TUNE_LABEL = "Fine-tune the active policy on my episodes"
MAKE_ACTIVE_LABEL = "Make it the active policy"


def plural(n: int, word: str) -> str:
    return f"{n} {word if n == 1 else word + 's'}"


def _fmt_duration(seconds: float) -> str:
    s = max(1, round(seconds))
    return (
        f"{s // 3600} h {s % 3600 // 60:02d} min"
        if s >= 3600
        else (f"{s // 60} min {s % 60:02d} s" if s >= 60 else f"{s} s")
    )


def _fmt_eta(seconds: float | None) -> str:
    if seconds is None or not np.isfinite(seconds):
        return "—"
    s = int(seconds)
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


def parse_overrides(text: str) -> list[str]:
    return [part.strip() for part in text.replace("\n", ";").split(";") if part.strip()]


class TrainPanel:
    """The *Train* tab."""

    def __init__(self, tab):
        self.tab = tab
        self.app = tab.app
        self.job_id: str | None = None
        self._task_boxes: dict[str, viser.GuiCheckboxHandle] = {}
        self._shown: dict[str, Any] = {}  # what is on screen: times, job ids, texts
        self._refusal: tuple[str, str] | None = None  # (scene, why) of the last active-policy choice refused
        self._submit_lock = threading.Lock()
        self._submitting = False  # a Start or Fine-tune click is being turned into a job
        self._count_key: tuple | None = None  # what the pair count shown was computed for
        self._count_at = 0.0
        self._auto_steps: int | None = (
            None  # the Steps value the panel proposed (kept until the user edits it)
        )
        self._pairs: int | None = (
            None  # training pairs of the ticked tasks at the last count (None: not counted)
        )
        self._plan: dict[str, Any] = {}  # the runs Start and Fine-tune would queue, from the last count
        gui = tab.client.gui
        self.gui = gui
        gui.add_markdown(HINT)
        self.config = gui.add_dropdown("Configuration", PRESETS, initial_value="cpu")
        self.scene = gui.add_dropdown("Scene", SCENES, initial_value="pick_place")
        self.tasks_folder = gui.add_folder("Training tasks", expand_by_default=False)
        self.heldout = gui.add_markdown("")
        self.pairs = gui.add_markdown("Counting the training pairs…")
        steps_hint = "optimiser steps (proposed: the configuration's epochs over the training pairs)"
        self.steps = gui.add_number("Steps", initial_value=1, min=1, step=1, hint=steps_hint)
        self.seed = gui.add_number("Seed", initial_value=0, min=0, step=1)
        self.overrides = gui.add_text("Overrides", initial_value="", hint="section.field=value; …")
        self.plan = gui.add_markdown("")
        self.start = gui.add_button("Start training", color="green", icon="player-play")
        with gui.add_folder("Fine-tune"):
            self.fine_tune_note = gui.add_markdown("")
            self.fine_tune = gui.add_button(FINE_TUNE_LABEL, color="blue", icon="adjustments")
        self.cancel = gui.add_button("Cancel", icon="player-stop", disabled=True)
        self.state = gui.add_markdown("No training job yet.")
        self.make_active = gui.add_button(MAKE_ACTIVE_LABEL, color="green", icon="check", visible=False)
        self.progress = gui.add_progress_bar(0.0, visible=False)
        x = np.zeros(1)
        nan = np.full(1, np.nan)
        self.loss_plot = gui.add_uplot(
            (x, nan, nan, nan),
            (
                uplot.Series(label="step"),
                uplot.Series(label="loss", stroke="black", width=1.5),
                uplot.Series(label="soft-DTW", stroke="#1f77b4", width=1.5),
                uplot.Series(label="world model", stroke="#d62728", width=1.5),
            ),
            title="Losses",
            aspect=1.5,
            scales={"x": uplot.Scale(time=False, auto=True)},
        )
        self.lr_plot = gui.add_uplot(
            (x, nan),
            (
                uplot.Series(label="step"),
                uplot.Series(label="learning rate ×1e-4", stroke="#2ca02c", width=1.5),
            ),
            title="Learning rate",
            aspect=2.5,
            scales={"x": uplot.Scale(time=False, auto=True)},
        )
        with gui.add_folder("Runs and checkpoints"):
            self.runs_table = gui.add_markdown("")
            self.active = gui.add_dropdown(
                "Active policy", ("oracle",), hint="plans the Imitate tasks of the scene chosen above"
            )
            self.active_note = gui.add_markdown("")
            with gui.add_folder("About the active policy", expand_by_default=False):
                self.active_about = gui.add_markdown("")
        self._fill_tasks()
        self.scene.on_update(self._on_scene_chosen)
        for widget in (self.config, self.overrides, self.seed):
            widget.on_update(lambda _: self._recount())
        self.start.on_click(lambda _: self._submit(False))
        self.fine_tune.on_click(lambda _: self._submit(True))
        self.cancel.on_click(lambda _: tab.run(self.cancel_training, "cancelling the training job"))
        self.make_active.on_click(
            lambda _: tab.run(self.make_result_active, "making the run the active policy")
        )
        self.active.on_update(self._on_active)
        self._refresh_checkpoints()
        self._show_counts()

    # ------------------------------------------------------------------ configuration
    def _on_scene_chosen(self, event: Any) -> None:
        """A scene chosen by a user (not set by code): its tasks and checkpoints."""
        if event.client:
            self._fill_tasks()
            self._refresh_checkpoints()

    def _fill_tasks(self) -> None:
        for box in self._task_boxes.values():
            box.remove()
        self._task_boxes.clear()
        split = load_split(self.scene.value)
        with self.tasks_folder:
            for task in split.train:
                box = self.gui.add_checkbox(task.split("/", 1)[1], initial_value=True)
                box.on_update(lambda _: self._recount())
                self._task_boxes[task] = box
        held = ", ".join(t.split("/", 1)[1] for t in split.test) or "none"
        self.heldout.content = f"Held out (never trained on): **{held}**"
        self._recount()

    def selected_tasks(self) -> list[str]:
        return [t for t, box in self._task_boxes.items() if box.value]

    def _recount(self) -> None:
        """Count the pairs again at the next refresh (the count reads the catalog: not on viser's threads)."""
        self._count_key = None

    def _chosen_split(self) -> SplitSpec:
        """The split a run started now trains on: the ticked tasks, the scene's held-out tasks held out."""
        tasks = self.selected_tasks()
        if not tasks:
            raise ValueError("choose at least one training task")
        split = load_split(self.scene.value)
        return SplitSpec(
            split.scene, tuple(tasks), tuple(split.test), split.val_fraction, "chosen in the browser studio"
        )

    def _preset_run(self) -> RunConfig:
        """The chosen configuration with the overrides (raises with the reason on a bad override)."""
        return preset(self.config.value, self.scene.value).with_overrides(
            parse_overrides(self.overrides.value)
        )

    def _active_policy(self) -> tuple[Checkpoint | None, str]:
        """The scene's active policy if it can be fine-tuned, else None and the sentence saying why."""
        scene = self.scene.value
        try:
            active = self.app.runs.active(scene)
        except SceneMismatch as e:
            return None, f"The active policy of {scene} cannot be fine-tuned: {e}."
        if active.is_oracle:
            return None, (
                f"No learnt policy is active for {scene} (the oracle plans from the true state and cannot be "
                "fine-tuned): choose one under *Active policy* below."
            )
        return active, ""

    def _busy(self) -> bool:
        """Whether the job this panel follows is still being submitted, queued or running."""
        if self.job_id is None:
            return False
        tracked = self.app.jobs.get(self.job_id)
        return tracked is not None and not tracked.terminal

    def _submit(self, fine_tune: bool) -> None:
        """A click on Start or Fine-tune: one job per click however fast the clicks come (the buttons are
        disabled at once and a click arriving meanwhile is dropped)."""
        with self._submit_lock:
            if self._submitting or self._busy():  # the second click of a double-click, or a stale button
                return
            self._submitting = True
        self.start.disabled = self.fine_tune.disabled = True

        def submit() -> None:
            queued = False
            try:
                self.start_training(fine_tune=fine_tune)
                queued = True
            finally:
                with self._submit_lock:
                    self._submitting = False
                if not queued:
                    self.start.disabled = self.fine_tune.disabled = False

        self.tab.run(submit, "fine-tuning the active policy" if fine_tune else "starting the training job")

    def start_training(self, fine_tune: bool = False) -> str:
        """Queue a ``train`` job (``fine_tune``: from the scene's active policy with the fine-tuning schedule);
        refuses, saying why, before anything queues when the run could not train."""
        if self._busy():
            raise ValueError(f"`{self.job_id}` is still running: cancel it or wait for it to end")
        split = self._chosen_split()
        overrides = parse_overrides(self.overrides.value)
        init: Checkpoint | None = None
        if fine_tune:
            init, why = self._active_policy()
            if init is None:
                self.fine_tune_note.content = f"✘ {why}"
                raise ValueError(why)
            run = RunConfig.from_dict(init_config(init.path)).with_overrides(overrides)
        else:
            run = self._preset_run()  # raises with the reason on a bad override
        count = count_training_pairs(self.app.store, run, split.scene, split_spec=split)
        if count.pairs == 0:
            sentence = count.what_to_record() or "no training pairs"
            (self.fine_tune_note if fine_tune else self.plan).content = f"✘ {sentence}"
            raise ValueError(sentence)
        job = new_job_id("train")
        run_dir = self.app.runs.new_run_dir(job)
        (run_dir / "split.json").write_text(
            json.dumps(
                {
                    "scene": split.scene,
                    "train": list(split.train),
                    "test": list(split.test),
                    "val_fraction": split.val_fraction,
                    "description": split.description,
                }
            )
        )
        spec: dict[str, Any] = {
            "data_dir": str(self.app.data_dir),
            "run_dir": str(run_dir),
            "config": self.config.value,
            "overrides": overrides,
            "steps": None if fine_tune else max(1, int(self.steps.value)),
            "seed": int(self.seed.value),
            "scene": str(run_dir / "split.json"),
        }
        if init is not None:
            spec.update(init=init.path, fine_tune=True)
        (run_dir / "spec.json").write_text(json.dumps(spec, indent=1))
        self.app.runs.register_run(self.app.store.catalog, job, scene=split.scene, config=spec)
        self.job_id = job
        self.app.jobs.submit("train", spec, started_by=self.tab.client.client_id, job=job)
        what = f"Fine-tuning `{init.label.split(' — ')[0]}`" if init is not None else "Training"
        self.state.content = f"Queued `{job}` — waiting for a trainer…"
        self.tab.notify(f"{what} queued", f"{job}: {plural(count.pairs, 'training pair')}")
        return job

    def cancel_training(self) -> None:
        if self.job_id is not None:
            status = self.app.jobs.cancel(self.job_id)
            self.state.content = f"`{self.job_id}`: {status.reason or status.state}"

    # ------------------------------------------------------------------ the result as the active policy
    def _result(self) -> Checkpoint | None:
        """The checkpoint the followed run ended with (its best, else its last), once it finished."""
        tracked = self.app.jobs.get(self.job_id) if self.job_id else None
        if tracked is None or tracked.status is None or tracked.status.state != "succeeded":
            return None
        cks = {c.id: c for c in self.app.runs.checkpoints() if c.run_id == self.job_id}
        return cks.get(f"{self.job_id}/best") or cks.get(f"{self.job_id}/last")

    def make_result_active(self) -> Checkpoint:
        """Make the followed run's checkpoint the active policy of the scene it was trained on."""
        ck = self._result()
        if ck is None:
            raise ValueError("no finished run to make active: its checkpoint is not written yet")
        if ck.scene is None:
            raise SceneMismatch(f"`{ck.id}` does not say which scene it was trained on")
        self.app.runs.set_active(ck.id, ck.scene)
        self.make_active.visible = False
        self._recount()
        if self.scene.value != ck.scene:
            self.scene.value = ck.scene
            self._fill_tasks()
        self._refresh_checkpoints()
        self.tab.notify("Active policy", f"Imitate now plans {ck.scene} tasks with {ck.id}")
        return ck

    def _on_active(self, event) -> None:
        if event.client is None:
            return
        scene = self.scene.value
        choice = {c.label: c for c in self.app.runs.checkpoints()}.get(self.active.value)
        if choice is None:
            return
        try:
            self.app.runs.set_active(choice.id, scene)
        except SceneMismatch as e:  # said plainly, and the scene keeps its policy
            self._refusal = (scene, f"✘ Not chosen for {scene}: {e}.")
            self.tab.notify(f"Not the active policy for {scene}", str(e).replace("`", ""), error=True)
        else:
            self._refusal = None
        self._refresh_checkpoints()
        self._recount()

    def _active_text(self, scene: str) -> tuple[str | None, str]:
        """The label the dropdown shows for ``scene`` (None: leave it) and the note below it."""
        runs = self.app.runs
        try:
            active = runs.active(scene)
        except SceneMismatch as e:
            return None, f"✘ {e}. Imitate refuses to run it."
        chosen = runs.chosen_ids().get(scene) == active.id
        if active.is_oracle:
            why = "chosen" if chosen else f"no policy for {scene} is shipped or chosen"
            return active.label, (
                f"Imitate plans **{scene}** tasks with the **oracle** ({why}): the execution ceiling, "
                "not a learned policy."
            )
        origin = "chosen" if chosen else "shipped"
        return active.label, f"Imitate plans **{scene}** tasks with `{active.path}` ({origin})."

    def _refresh_checkpoints(self) -> None:
        scene = self.scene.value
        labels = tuple(c.label for c in self.app.runs.checkpoints())
        label, note = self._active_text(scene)
        if self.active.options != labels:
            self.active.options = labels
        if label is not None and self.active.value != label:
            self.active.value = label
        if self._refusal is not None and self._refusal[0] == scene:  # until the next choice
            note = f"{self._refusal[1]} {note}"
        if self.active_note.content != note:
            self.active_note.content = note
        about = self._active_summary(scene)
        if self.active_about.content != about:
            self.active_about.content = about

    def _active_summary(self, scene: str) -> str:
        """What was measured of the scene's active policy (its NAME.json summary), for the fold."""
        try:
            active = self.app.runs.active(scene)
        except SceneMismatch:
            return ""
        if active.is_oracle:
            return "The oracle plans from the true state: the execution ceiling, not a learned policy."
        return active.summary or f"No measured summary is recorded for `{active.id}`."

    # ------------------------------------------------------------------ refresh
    def _current_job(self):
        statuses = [s for s in self.app.hub.jobs.jobs() if s.kind == "train"]
        if self.job_id is None and statuses:
            self.job_id = statuses[-1].job
        if self.job_id is None:
            return None
        status = next((s for s in statuses if s.job == self.job_id), None)
        return self.app.jobs.follow(self.job_id, "train", status.spec if status else None)

    def refresh(self) -> None:
        tracked = self._current_job()
        if tracked is not None:
            self._show_job(tracked)
        else:
            self._enable_buttons(running=False)
        now = time.monotonic()
        if now - self._shown.get("runs_at", 0.0) > 3.0:
            self._shown["runs_at"] = now
            self._show_runs()
            self._refresh_checkpoints()
        self._show_counts()

    def _enable_buttons(self, running: bool) -> None:
        idle = not running and not self._submitting
        can_start = idle and self._pairs != 0  # no pairs: the line above Start says what to record
        if self.start.disabled == can_start:
            self.start.disabled = not can_start
        if self.fine_tune.disabled == idle:
            self.fine_tune.disabled = not idle
        if self.cancel.disabled != (not running):
            self.cancel.disabled = not running

    # ------------------------------------------------------------------ the pairs and the runs they make
    def _show_counts(self) -> None:
        """Count the training pairs of the ticked tasks when the data or the choices changed (or every few
        seconds: an episode's outcome or the active policy can change), and show them with the runs Start and
        Fine-tune would make."""
        choices = (self.scene.value, tuple(self.selected_tasks()), self.config.value, self.overrides.value)
        key = (self.app.dataset_version, choices)
        now = time.monotonic()
        if key == self._count_key and now - self._count_at < 5.0:
            return
        self._count_key, self._count_at = key, now
        active = self._active_policy()[0]
        try:
            split = self._chosen_split()
        except ValueError as e:
            self._set(self.pairs, f"✘ {str(e).capitalize()}.")
            self._set(self.plan, "")
            self._set(self.fine_tune_note, "")
            return
        try:
            run = self._preset_run()
            bad_override = ""
        except ValueError as e:
            run, bad_override = preset(self.config.value, self.scene.value), f"✘ Overrides: {e}.  \n"
        count = count_training_pairs(self.app.store, run, split.scene, split_spec=split)
        left = count.left_out()
        text = count.summary() + "." + ("  \nLeft out: " + "; ".join(left) + "." if left else "")
        self._set(self.pairs, text)
        self._pairs = count.pairs
        self._show_plan(run, count.pairs, bad_override)
        self._show_fine_tune(active, split)

    def _set(self, md, text: str) -> None:
        if md.content != text:
            md.content = text

    def _estimate(self, config: str, batch: int, steps: int) -> str:
        pace = self.app.runs.step_seconds(config, batch)
        if pace is None:
            return "wall time: not measured here yet (the ETA shows once it runs)"
        seconds, run = pace
        return (
            f"≈ {_fmt_duration(seconds * steps)} at the {seconds:.1f} s/step of run "
            f"`{run.removeprefix('train-')}` here"
        )

    def _show_plan(self, run: RunConfig, pairs: int, prefix: str) -> None:
        """Steps proposed for Start (the configuration's epochs over the pairs, until the user types another
        number) and the batch, the steps and the expected wall time of the run it would queue."""
        if pairs == 0:
            self._set(
                self.plan,
                prefix
                + "Start needs at least one training pair: record or collect a successful demonstration "
                "and a successful agent episode of the same training task.",
            )
            return
        fitted, note = fit_batch(run, pairs)
        proposed = steps_for(fitted.train, pairs)
        current = int(self.steps.value)
        if self._auto_steps is None or current == self._auto_steps:
            if current != proposed:
                self.steps.value = proposed
            self._auto_steps, current = proposed, proposed
        batch = fitted.train.batch_size
        parts = [f"Start: {plural(current, 'step')} of batch {batch} ({current * batch / pairs:.3g} epochs)"]
        if note:
            parts.append(note)
        parts.append(self._estimate(self.config.value, batch, current))
        self._set(self.plan, prefix + "; ".join(parts) + ".")

    def _show_fine_tune(self, active: Checkpoint | None, split: SplitSpec) -> None:
        """What Fine-tune would do: from which policy, on which episodes, how long."""
        if active is None:
            self._set(self.fine_tune_note, self._active_policy()[1])
            return
        try:
            run = RunConfig.from_dict(init_config(active.path))
        except ValueError as e:
            self._set(self.fine_tune_note, f"✘ {e}.")
            return
        count = count_training_pairs(self.app.store, run, split.scene, split_spec=split)
        name = active.label.split(" — ")[0]
        if count.pairs == 0:
            self._set(self.fine_tune_note, f"Starts from **{name}**. {count.what_to_record()}")
            return
        sources: dict[str, int] = {}
        for t in count.tasks:
            for m in (*t.experts, *t.agents) if t.pairs else ():
                sources[m.source] = sources.get(m.source, 0) + 1
        made = ", ".join(f"{n} {src}" for src, n in sorted(sources.items(), key=lambda kv: -kv[1]))
        steps, batch = fine_tune_steps(count.pairs), min(FINE_TUNE_BATCH, count.pairs)
        episodes = count.summary().split(": ", 1)[-1]
        self._set(
            self.fine_tune_note,
            f"Starts from **{name}** (active for {split.scene}) and trains on your {episodes} ({made}): "
            f"{plural(count.pairs, 'pair')}, {plural(steps, 'step')} of batch {batch}; "
            f"{self._estimate('fine-tune', batch, steps)}.",
        )

    # ------------------------------------------------------------------ the followed job
    def _show_job(self, tracked) -> None:
        st, p = tracked.status, tracked.progress
        running = st is None or st.state in ("queued", "running")
        self._enable_buttons(running)
        parts = [f"`{tracked.job}` — **{st.state if st else 'submitting'}**"]
        if tracked.spec.get("fine_tune"):
            init = os.path.normpath(str(tracked.spec.get("init")))
            parts[0] += (
                f" · fine-tuning `{os.path.join(os.path.basename(os.path.dirname(init)), os.path.basename(init))}`"
            )
        if st is not None and st.state in ("queued", "failed", "cancelled") and st.reason:
            parts.append(st.reason)
        if p is not None and p.total:
            frac = min(1.0, p.step / p.total)
            self.progress.visible = True
            if abs(self.progress.value - 100 * frac) > 0.05:
                self.progress.value = 100.0 * frac
            m = p.metrics
            line = (
                f"step {p.step}/{p.total} · loss {m.get('loss', np.nan):.4f} · lr {m.get('lr', np.nan):.2e}"
            )
            if running:  # a run that ended has no time left, and its last rate is history
                line += f" · {m.get('samples_per_s', np.nan):.1f} pairs/s · ETA {_fmt_eta(p.eta_s)}"
            parts.append(line)
        elif p is not None and p.message:
            parts.append(p.message)
        notes = [m for m in tracked.messages if m and m != "preparing the training data"]
        if notes and p is not None and p.total:
            parts.append(notes[-1])
        if st is not None and st.terminal and self._shown.get("catalog_done") != tracked.job:
            self._shown["catalog_done"] = tracked.job
            self._record_end(tracked)
        if tracked.result is not None:
            r = tracked.result
            best = r.get("best_val_loss")
            best_text = f"; best validation loss {best:.4f}" if isinstance(best, float) else ""
            parts.append(f"ended: {r.get('status')} at step {r.get('step')}{best_text}")
        result = self._result()
        offer = result is not None and self.app.runs.chosen_ids().get(str(result.scene)) != result.id
        if result is not None and offer:
            parts.append(
                f"**{MAKE_ACTIVE_LABEL}** makes `{result.id}` the policy Imitate plans {result.scene} tasks with."
            )
        elif result is not None:
            parts.append(f"`{result.id}` is the active policy of {result.scene}: plan with it in Imitate.")
        if self.make_active.visible != offer:
            self.make_active.visible = offer
        text = "  \n".join(parts)
        if self._shown.get("state") != text:
            self._shown["state"] = text
            self.state.content = text
        self._show_curves(tracked)

    def _record_end(self, tracked) -> None:
        """The catalog's run row follows the job's end (rows of runs started elsewhere are left alone)."""
        catalog = self.app.store.catalog
        if not any(r.id == tracked.job for r in catalog.runs()):
            return
        status = {"succeeded": "done", "failed": "failed", "cancelled": "cancelled"}[tracked.status.state]
        catalog.update_run(
            tracked.job,
            status=status,
            finished=tracked.status.updated_at,
            error=tracked.status.reason if status == "failed" else None,
        )

    def _show_curves(self, tracked) -> None:
        run_dir = tracked.spec.get("run_dir")
        if run_dir:
            try:
                st = os.stat(os.path.join(run_dir, "metrics.jsonl"))
                stamp = (st.st_size, st.st_mtime_ns, len(tracked.history))
            except OSError:
                stamp = (0, 0, len(tracked.history))
            if self._shown.get("metrics_stamp") == stamp:
                return
            self._shown["metrics_stamp"] = stamp
        curves = read_metrics(run_dir) if run_dir else None
        if curves is None or len(curves["step"]) == 0:
            hist = [h for h in tracked.history if "loss" in h.metrics]
            if not hist:
                return
            step = np.array([h.step for h in hist], dtype=np.float64)
            loss = np.array([h.metrics["loss"] for h in hist])
            lr = np.array([h.metrics.get("lr", np.nan) for h in hist])
            sdtw = wm = np.full(len(step), np.nan)
            source = "history"
        else:
            step, loss, sdtw, wm, lr = (curves[k] for k in ("step", "loss", "loss_sdtw", "loss_wm", "lr"))
            source = "file"
        # The source is part of what is shown: curves drawn from the job's progress messages (no metrics file
        # yet) have no separate losses, and must be replaced once the file holds the same steps.
        key = (source, len(step), float(step[-1]) if len(step) else 0.0)
        if self._shown.get("curves") == key:
            return
        self._shown["curves"] = key
        # uPlot starts a series' range at its first value: a series beginning with NaN (no world-model loss
        # before α warms up, none at all without a world model) left the whole chart blank. The losses' range
        # is therefore set here from their finite values, and uPlot skips the missing points.
        finite = np.concatenate([a[np.isfinite(a)] for a in (loss, sdtw, wm)])
        if finite.size:
            lo, hi = float(finite.min()), float(finite.max())
            pad = 0.05 * (hi - lo) or 0.05 * abs(hi) or 1e-3
            y = (round(lo - pad, 6), round(hi + pad, 6))
            if self._shown.get("loss_range") != y:
                self._shown["loss_range"] = y
                self.loss_plot.scales = {
                    "x": uplot.Scale(time=False, auto=True),
                    "y": uplot.Scale(auto=False, range=y),
                }
        self.loss_plot.data = (step, loss, sdtw, wm)
        self.lr_plot.data = (step, lr * 1e4)

    def _show_runs(self) -> None:
        runs = self.app.runs.runs()
        if not runs:
            text = "No runs yet." + (
                " A shipped policy is available." if self.app.runs.default_policies() else ""
            )
        else:
            rows = ["| run | config | step | ended | best val | checkpoints |", "|---|---|---|---|---|---|"]
            # a run whose job failed or was cancelled before its loop wrote an end: the catalog's row says so
            ended_in_catalog = {
                row.id: row.status
                for row in self.app.store.catalog.runs()
                if row.status in ("failed", "cancelled")
            }
            for r in reversed(runs[-10:]):
                total = f"/{r.total}" if r.total else ""
                best = f"{r.best_val:.4f}" if r.best_val is not None else "—"
                cks = ", ".join(c.id.split("/")[-1] for c in r.checkpoints) or "—"
                rows.append(
                    f"| `{r.id.removeprefix('train-')}` | {r.config} | {r.step}{total} | {r.ended or ended_in_catalog.get(r.id, '…')} | {best} | {cks} |"
                )
            text = "\n".join(rows)
        if self._shown.get("runs") != text:
            self._shown["runs"] = text
            self.runs_table.content = text

    def close(self) -> None:
        pass
