"""Train: choose a configuration and the training tasks, start a ``train`` job, follow its loss curves,
progress and ETA, cancel it; list runs and checkpoints and choose the active policy of the chosen scene.

A run started here lives in ``<data-dir>/runs/<job-id>/`` (see :mod:`studio.ui.runs`); its task
selection is written there as a split file (the scene's held-out tasks stay held out). Curves come from
the run's ``metrics.jsonl`` (world-model and Soft-DTW losses, learning rate) when this host can read it,
otherwise from the job's progress stream.
"""

from __future__ import annotations

import json
import os
import time
from typing import Any

import numpy as np
import viser
import viser.uplot as uplot

from studio.backend.jobs import new_job_id
from studio.data.splits import load_split
from studio.model.config import PRESETS, preset
from studio.ui.runs import SCENES, SceneMismatch, read_metrics

HINT = """Pick a **configuration** (`cpu` trains in minutes on this machine, `paper` is the paper's model) and
the **training tasks**; held-out tasks are never trained on. *Overrides* are `section.field=value`
assignments separated by `;` (e.g. `train.batch_size=8; model.image_size=[96, 128]`). **Start** queues a
job for a trainer; the curves update live, **Cancel** stops after a checkpoint."""


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
        gui = tab.client.gui
        self.gui = gui
        gui.add_markdown(HINT)
        self.config = gui.add_dropdown("Configuration", PRESETS, initial_value="cpu")
        self.scene = gui.add_dropdown("Scene", SCENES, initial_value="pick_place")
        self.tasks_folder = gui.add_folder("Training tasks", expand_by_default=False)
        self.heldout = gui.add_markdown("")
        self.steps = gui.add_number(
            "Steps", initial_value=0, min=0, step=1, hint="0: the configuration's epochs"
        )
        self.seed = gui.add_number("Seed", initial_value=0, min=0, step=1)
        self.overrides = gui.add_text("Overrides", initial_value="", hint="section.field=value; …")
        self.start = gui.add_button("Start training", color="green", icon="player-play")
        self.cancel = gui.add_button("Cancel", icon="player-stop", disabled=True)
        self.state = gui.add_markdown("No training job yet.")
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
            title="Losses", aspect=1.5, scales={"x": uplot.Scale(time=False, auto=True)},
        )  # fmt: skip
        self.lr_plot = gui.add_uplot(
            (x, nan), (uplot.Series(label="step"), uplot.Series(label="learning rate ×1e-4", stroke="#2ca02c", width=1.5)),
            title="Learning rate", aspect=2.5, scales={"x": uplot.Scale(time=False, auto=True)},
        )  # fmt: skip
        with gui.add_folder("Runs and checkpoints"):
            self.runs_table = gui.add_markdown("")
            self.active = gui.add_dropdown(
                "Active policy", ("oracle",), hint="plans the Imitate tasks of the scene chosen above"
            )
            self.active_note = gui.add_markdown("")
        self._fill_tasks()
        self.scene.on_update(lambda e: e.client and (self._fill_tasks(), self._refresh_checkpoints()))
        self.start.on_click(lambda _: tab.run(self.start_training, "starting the training job"))
        self.cancel.on_click(lambda _: tab.run(self.cancel_training, "cancelling the training job"))
        self.active.on_update(self._on_active)
        self._refresh_checkpoints()

    # ------------------------------------------------------------------ configuration
    def _fill_tasks(self) -> None:
        for box in self._task_boxes.values():
            box.remove()
        self._task_boxes.clear()
        split = load_split(self.scene.value)
        with self.tasks_folder:
            for task in split.train:
                self._task_boxes[task] = self.gui.add_checkbox(task.split("/", 1)[1], initial_value=True)
        held = ", ".join(t.split("/", 1)[1] for t in split.test) or "none"
        self.heldout.content = f"Held out (never trained on): **{held}**"

    def selected_tasks(self) -> list[str]:
        return [t for t, box in self._task_boxes.items() if box.value]

    def start_training(self) -> str:
        tasks = self.selected_tasks()
        if not tasks:
            raise ValueError("choose at least one training task")
        overrides = parse_overrides(self.overrides.value)
        preset(self.config.value).with_overrides(overrides)  # raises with the reason on a bad override
        split = load_split(self.scene.value)
        job = new_job_id("train")
        run_dir = self.app.runs.new_run_dir(job)
        (run_dir / "split.json").write_text(
            json.dumps({"scene": split.scene, "train": tasks, "test": list(split.test),
                        "val_fraction": split.val_fraction, "description": "chosen in the browser studio"})
        )  # fmt: skip
        spec = {
            "data_dir": str(self.app.data_dir),
            "run_dir": str(run_dir),
            "config": self.config.value,
            "overrides": overrides,
            "steps": int(self.steps.value) or None,
            "seed": int(self.seed.value),
            "scene": str(run_dir / "split.json"),
        }
        (run_dir / "spec.json").write_text(json.dumps(spec, indent=1))
        self.app.runs.register_run(self.app.store.catalog, job, scene=split.scene, config=spec)
        self.app.jobs.submit("train", spec, started_by=self.tab.client.client_id, job=job)
        self.job_id = job
        self.state.content = f"Queued `{job}` — waiting for a trainer…"
        self.tab.notify("Training queued", job)
        return job

    def cancel_training(self) -> None:
        if self.job_id is not None:
            status = self.app.jobs.cancel(self.job_id)
            self.state.content = f"`{self.job_id}`: {status.reason or status.state}"

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
        now = time.monotonic()
        if now - self._shown.get("runs_at", 0.0) > 3.0:
            self._shown["runs_at"] = now
            self._show_runs()
            self._refresh_checkpoints()

    def _show_job(self, tracked) -> None:
        st, p = tracked.status, tracked.progress
        running = st is not None and st.state in ("queued", "running")
        self.cancel.disabled = not running
        self.start.disabled = running
        parts = [f"`{tracked.job}` — **{st.state if st else 'submitting'}**"]
        if st is not None and st.state in ("queued", "failed", "cancelled") and st.reason:
            parts.append(st.reason)
        if p is not None and p.total:
            frac = min(1.0, p.step / p.total)
            self.progress.visible = True
            if abs(self.progress.value - 100 * frac) > 0.05:
                self.progress.value = 100.0 * frac
            m = p.metrics
            parts.append(
                f"step {p.step}/{p.total} · loss {m.get('loss', float('nan')):.4f} · lr {m.get('lr', float('nan')):.2e}"
                f" · {m.get('samples_per_s', float('nan')):.1f} pairs/s · ETA {_fmt_eta(p.eta_s)}"
            )
        elif p is not None and p.message:
            parts.append(p.message)
        if st is not None and st.terminal and self._shown.get("catalog_done") != tracked.job:
            self._shown["catalog_done"] = tracked.job
            self._record_end(tracked)
        if tracked.result is not None:
            r = tracked.result
            best = r.get("best_val_loss")
            best_text = f"; best validation loss {best:.4f}" if isinstance(best, float) else ""
            parts.append(f"ended: {r.get('status')} at step {r.get('step')}{best_text}")
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
        catalog.update_run(tracked.job, status=status, finished=tracked.status.updated_at,
                           error=tracked.status.reason if status == "failed" else None)  # fmt: skip

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
        else:
            step, loss, sdtw, wm, lr = (curves[k] for k in ("step", "loss", "loss_sdtw", "loss_wm", "lr"))
        key = (len(step), float(step[-1]) if len(step) else 0.0)
        if self._shown.get("curves") == key:
            return
        self._shown["curves"] = key
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
            for r in reversed(runs[-10:]):
                total = f"/{r.total}" if r.total else ""
                best = f"{r.best_val:.4f}" if r.best_val is not None else "—"
                cks = ", ".join(c.id.split("/")[-1] for c in r.checkpoints) or "—"
                rows.append(
                    f"| `{r.id.removeprefix('train-')}` | {r.config} | {r.step}{total} | {r.ended or '…'} | {best} | {cks} |"
                )
            text = "\n".join(rows)
        if self._shown.get("runs") != text:
            self._shown["runs"] = text
            self.runs_table.content = text

    def close(self) -> None:
        pass
