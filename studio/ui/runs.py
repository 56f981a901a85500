"""Training runs and checkpoints as the studio shows them, and which checkpoint is the active policy of each scene.

Runs started from the browser live in ``<data-dir>/runs/<job-id>/`` (the train job's run directory:
``config.json``, ``metrics.jsonl``, ``last.pt``, ``best.pt``). A policy shipped with the package is a
checkpoint file under ``studio/policies/`` (or the file named by ``STUDIO_DEFAULT_POLICY``).

Every checkpoint knows the scene it was trained on: the scene of the tasks recorded in the file itself
(:func:`studio.model.checkpoint_info.checkpoint_scene`, read without torch), so it cannot drift from what the
model learnt. The active policy is per scene: a task is planned with the user's choice for its scene if there is
one (the oracle, or a checkpoint trained on that scene), else the first shipped policy of that scene by name (the
first trained on the demonstrator's embodiment when one is: a human video is imitated by the policy that learnt
from human demonstrations), else the *oracle* planner, labelled as what it is: the execution ceiling, not the
model. A checkpoint trained on one scene never plans another scene's task: choosing it for another scene is
refused with the reason.

The user's choices are kept in ``<data-dir>/ui/active_checkpoint.json`` (``{"scenes": {scene: id}, "id": the
latest}``) so that they survive restarts and are shared by every tab. A file from before per-scene choices,
``{"id": ...}``, is honoured for the scene its checkpoint was trained on (the oracle: for every scene).
"""

from __future__ import annotations

import json
import os
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from studio.data.paths import SHIPPED_POLICY_DIR, SHIPPED_RUN_ID, SHIPPED_RUN_NAME
from studio.model.checkpoint_info import checkpoint_demonstrators, checkpoint_scene

RUNS_DIR = "runs"
ACTIVE_FILE = "ui/active_checkpoint.json"
DEFAULT_POLICY_DIR = SHIPPED_POLICY_DIR
DEFAULT_POLICY_ENV = "STUDIO_DEFAULT_POLICY"
ORACLE = "oracle"
#: The scene families the studio offers (Teleop, Train and Imitate list them in this order).
SCENES = ("pick_place", "push", "metaworld")


class SceneMismatch(ValueError):
    """A checkpoint chosen for a scene it was not trained on (or whose scene cannot be told)."""


@dataclass(frozen=True)
class Checkpoint:
    """A choice of planner: a checkpoint file, or the oracle (``path == "oracle"``)."""

    id: str
    path: str
    label: str
    run_id: str | None = None
    step: int | None = None
    summary: str = ""  # a shipped policy's measured results in one line (``NAME.json``), shown beside it
    scene: str | None = None  # the scene it was trained on (None: the oracle, or a file that does not say)
    #: the embodiments whose demonstrations it learnt to imitate (empty: not recorded)
    demonstrators: tuple[str, ...] = ()

    @property
    def is_oracle(self) -> bool:
        return self.path == ORACLE

    def plans(self, scene: str) -> bool:
        """Whether this choice may plan ``scene``'s tasks: the oracle plans every scene, a checkpoint its own."""
        return self.is_oracle or self.scene == scene


def mismatch_reason(ck: Checkpoint, scene: str | None) -> str:
    """Why ``ck`` does not plan ``scene``'s tasks (None: any scene's), for a checkpoint that does not."""
    if ck.scene is None:
        unknown = (
            f"`{ck.id}` does not say which scene it was trained on (its file names no tasks of one scene)"
        )
        return f"{unknown}: it plans no {scene} task" if scene else f"{unknown}: it plans no scene's tasks"
    return f"`{ck.id}` was trained on {ck.scene} tasks: it does not plan {scene} tasks"


ORACLE_CHOICE = Checkpoint(
    ORACLE, ORACLE, "oracle — execution ceiling (plans from the true state, not a model)"
)


@dataclass
class RunInfo:
    """What the Train panel lists about one run directory."""

    id: str
    path: Path
    config: str
    tasks: list[str]
    step: int
    total: int | None
    ended: str | None
    best_val: float | None
    checkpoints: list[Checkpoint] = field(default_factory=list)


_JSONL_CACHE: dict[str, tuple[tuple[int, int], list[dict]]] = {}
_JSONL_LOCK = threading.Lock()


def _read_jsonl(path: Path) -> list[dict]:
    """The records of a JSON-lines file (a torn last line is ignored); re-read only when the file changed."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return []
    stamp = (st.st_size, st.st_mtime_ns)
    key = str(path)
    with _JSONL_LOCK:
        hit = _JSONL_CACHE.get(key)
    if hit is not None and hit[0] == stamp:
        return hit[1]
    rows = _parse_jsonl(path)
    with _JSONL_LOCK:
        if len(_JSONL_CACHE) > 256:
            _JSONL_CACHE.clear()
        _JSONL_CACHE[key] = (stamp, rows)
    return rows


def _parse_jsonl(path: Path) -> list[dict]:
    out = []
    try:
        with open(path, encoding="utf-8") as f:
            for line in f:
                line = line.strip()
                if not line:
                    continue
                try:
                    out.append(json.loads(line))
                except json.JSONDecodeError:
                    break  # a line being written right now
    except FileNotFoundError:
        pass
    return out


def _read_json(path: Path) -> dict:
    """A JSON object from a file ({} when it is missing, torn or not an object)."""
    try:
        value = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return {}
    return value if isinstance(value, dict) else {}


def read_metrics(run_dir: Path) -> dict[str, np.ndarray]:
    """Training curves of a run: ``step`` and every logged series (loss, loss_sdtw, loss_wm, lr, ...),
    plus ``val_step`` / ``val_loss_sdtw`` when validation ran. Missing values are NaN."""
    rows = _read_jsonl(Path(run_dir) / "metrics.jsonl")
    train = [r for r in rows if "step" in r and "loss" in r and r.get("split") != "val"]
    val = [r for r in rows if r.get("split") == "val"]
    out: dict[str, np.ndarray] = {"step": np.array([r["step"] for r in train], dtype=np.float64)}
    for key in ("loss", "loss_sdtw", "loss_wm", "lr"):
        out[key] = np.array([float(r.get(key, np.nan)) for r in train], dtype=np.float64)
    out["val_step"] = np.array([r["step"] for r in val], dtype=np.float64)
    out["val_loss_sdtw"] = np.array([float(r.get("val_loss_sdtw", np.nan)) for r in val], dtype=np.float64)
    return out


def _shipped(policy: Path) -> Checkpoint:
    """A shipped policy, with the one-line summary of its measured results from ``NAME.json`` if present (so
    that nobody mistakes a weak default policy for a good one)."""
    try:
        about = json.loads(policy.with_suffix(".json").read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        about = {}
    about = about if isinstance(about, dict) else {}
    summary = about.get("summary")
    summary = summary if isinstance(summary, str) else ""
    # Who demonstrated its training pairs: the file's configuration, else what its NAME.json says.
    listed = about.get("demonstrators")
    demonstrators = checkpoint_demonstrators(policy) or (
        tuple(str(e) for e in listed) if isinstance(listed, list) else ()
    )
    label = f"shipped policy {policy.stem}"  # short: its measured summary is shown in a fold, not in lists
    return Checkpoint(
        f"default/{policy.stem}",
        str(policy),
        label,
        summary=summary,
        scene=checkpoint_scene(policy),
        demonstrators=demonstrators,
    )


class RunRegistry:
    """Runs under ``<data-dir>/runs``, shipped policies, and the active checkpoint."""

    def __init__(self, data_dir: str | os.PathLike, policy_dir: str | os.PathLike | None = None):
        self.data_dir = Path(data_dir)
        self.runs_dir = self.data_dir / RUNS_DIR
        self.policy_dir = Path(policy_dir) if policy_dir is not None else DEFAULT_POLICY_DIR
        self._lock = threading.Lock()

    def new_run_dir(self, run_id: str) -> Path:
        path = self.runs_dir / run_id
        path.mkdir(parents=True, exist_ok=False)
        return path

    # ------------------------------------------------------------------ listing
    def default_policies(self) -> list[Checkpoint]:
        files = []
        env = os.environ.get(DEFAULT_POLICY_ENV)
        if env and Path(env).is_file():
            files.append(Path(env))
        if self.policy_dir.is_dir():
            files += sorted(f for f in self.policy_dir.glob("*.pt") if not f.name.endswith(".decoder.pt"))
        return [_shipped(f) for f in files]

    def runs(self) -> list[RunInfo]:
        out: list[RunInfo] = []
        if not self.runs_dir.is_dir():
            return out
        for d in sorted(self.runs_dir.iterdir()):
            if not d.is_dir():
                continue
            try:
                cfg = json.loads((d / "config.json").read_text())
            except (FileNotFoundError, json.JSONDecodeError):
                cfg = {}
            rows = _read_jsonl(d / "metrics.jsonl")
            steps = [r["step"] for r in rows if "step" in r and "loss" in r]
            starts = [r for r in rows if r.get("event") in ("start", "resume")]
            ends = [r for r in rows if r.get("event") == "end"]
            vals = [r["val_loss_sdtw"] for r in rows if r.get("split") == "val" and "val_loss_sdtw" in r]
            cks = []
            for name in ("best", "last"):
                f = d / f"{name}.pt"
                if f.is_file():
                    scene = checkpoint_scene(f)
                    label = f"run {d.name} — {name}.pt ({scene or 'scene unknown'})"
                    cks.append(Checkpoint(f"{d.name}/{name}", str(f), label, d.name, scene=scene))
            spec = _read_json(d / "spec.json")
            preset = "fine-tune" if spec.get("fine_tune") else spec.get("config")
            # a run cancelled between two training records ended past the last one
            reached = [int(steps[-1])] if steps else []
            reached += [int(r["step"]) for r in ends[-1:] if isinstance(r.get("step"), int)]
            out.append(
                RunInfo(
                    id=d.name,
                    path=d,
                    config=str(preset or "?"),
                    tasks=list(cfg.get("tasks", [])),
                    step=max(reached, default=0),
                    total=int(starts[-1]["total_steps"]) if starts and "total_steps" in starts[-1] else None,
                    ended=ends[-1].get("status")
                    if ends and (not starts or ends[-1]["time"] >= starts[-1]["time"])
                    else None,
                    best_val=min(vals) if vals else None,
                    checkpoints=cks,
                )
            )
        return out

    def step_seconds(self, config: str, batch_size: int) -> tuple[float, str] | None:
        """Seconds per optimiser step measured here: the median pace of the newest run of ``config`` (a preset, or
        ``fine-tune``) at this batch size whose metrics record it, with that run's id; None when no run has."""
        for run in reversed(self.runs()):
            train = _read_json(run.path / "config.json").get("config", {}).get("train", {})
            if run.config != config or train.get("batch_size") != batch_size:
                continue
            rows = _read_jsonl(run.path / "metrics.jsonl")
            rates = [r["samples_per_s"] for r in rows if isinstance(r.get("samples_per_s"), int | float)]
            rates = [r for r in rates if r > 0]
            if rates:
                return batch_size / float(np.median(rates)), run.id
        return None

    def checkpoints(self) -> list[Checkpoint]:
        """Every choice, best first: shipped policies, each run's best and last checkpoints, the oracle."""
        cks = self.default_policies()
        for run in reversed(self.runs()):
            cks += run.checkpoints
        return [*cks, ORACLE_CHOICE]

    # ------------------------------------------------------------------ the active choice
    def chosen_ids(self) -> dict[str, str]:
        """The user's choice of checkpoint id per scene, as stored (a file from before per-scene choices,
        ``{"id": ...}``, counts for the scene its checkpoint was trained on, the oracle for every scene)."""
        try:
            stored = json.loads((self.data_dir / ACTIVE_FILE).read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            return {}
        if not isinstance(stored, dict):
            return {}
        scenes = stored.get("scenes")
        if isinstance(scenes, dict):
            return {str(k): v for k, v in scenes.items() if isinstance(v, str)}
        chosen = stored.get("id")
        if not isinstance(chosen, str):
            return {}
        if chosen == ORACLE:
            return dict.fromkeys(SCENES, ORACLE)
        ck = next((c for c in self.checkpoints() if c.id == chosen), None)
        return {ck.scene: chosen} if ck is not None and ck.scene is not None else {}

    def shipped_for(self, scene: str, demonstrator: str | None = None) -> Checkpoint | None:
        """The first shipped policy (by name) trained on ``scene``; with ``demonstrator`` (an embodiment), the first
        one trained on that embodiment's demonstrations if one is shipped."""
        of_scene = [c for c in self.default_policies() if c.scene == scene]
        if demonstrator is not None:
            same = next((c for c in of_scene if demonstrator in c.demonstrators), None)
            if same is not None:
                return same
        return of_scene[0] if of_scene else None

    def active(self, scene: str, demonstrator: str | None = None) -> Checkpoint:
        """The policy that plans ``scene``'s tasks: the user's choice for that scene if it still exists, else the
        scene's shipped policy (the one trained on ``demonstrator``'s demonstrations when that embodiment is
        given and such a policy is shipped), else the oracle.

        Raises :class:`SceneMismatch` when the user's choice for ``scene`` was trained on another scene: it is
        not run, and not silently replaced either."""
        choices = {c.id: c for c in self.checkpoints()}
        chosen = choices.get(self.chosen_ids().get(scene, ""))
        if chosen is not None:
            if not chosen.plans(scene):
                raise SceneMismatch(
                    f"{mismatch_reason(chosen, scene)}; choose a policy for {scene} in Train (Scene: {scene})"
                )
            return chosen
        return self.shipped_for(scene, demonstrator) or ORACLE_CHOICE

    def set_active(self, checkpoint_id: str, scene: str | None = None) -> Checkpoint:
        """Make ``checkpoint_id`` the active policy of ``scene`` (None: of the scene it was trained on; the
        oracle, which has none, for every scene). Raises :class:`SceneMismatch` for a checkpoint trained on
        another scene, ``KeyError`` for an unknown id."""
        choices = {c.id: c for c in self.checkpoints()}
        if checkpoint_id not in choices:
            raise KeyError(f"no checkpoint {checkpoint_id!r}; known: {sorted(choices)}")
        ck = choices[checkpoint_id]
        if scene is not None and not ck.plans(scene):
            raise SceneMismatch(mismatch_reason(ck, scene))
        if scene is None and not ck.is_oracle and ck.scene is None:
            raise SceneMismatch(mismatch_reason(ck, None))
        scenes = (scene,) if scene is not None else (SCENES if ck.is_oracle else (str(ck.scene),))
        path = self.data_dir / ACTIVE_FILE
        with self._lock:
            stored = self.chosen_ids()
            stored.update(dict.fromkeys(scenes, checkpoint_id))
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(path.name + ".tmp")
            # "id" keeps the latest choice for a studio from before per-scene choices, which reads only that.
            tmp.write_text(json.dumps({"scenes": stored, "id": checkpoint_id}, indent=1))
            os.replace(tmp, path)
        return ck

    # ------------------------------------------------------------------ the catalog's runs and checkpoints
    def register_run(
        self,
        catalog,
        run_id: str,
        *,
        status: str = "queued",
        scene: str | None = None,
        config: dict | None = None,
    ) -> None:
        """Add a run started from the browser to the store's catalog (once)."""
        from studio.data.catalog import RunRecord

        if any(r.id == run_id for r in catalog.runs()):
            return
        with catalog.transaction():
            catalog.add_run(
                RunRecord(
                    id=run_id,
                    status=status,
                    name=run_id,
                    scene=scene,
                    config=config or {},
                    path=str(self.runs_dir / run_id),
                )
            )

    def register_checkpoint(self, catalog, ck: Checkpoint) -> None:
        """Make ``ck`` known to the catalog (rollouts refer to their checkpoint by id), with its run."""
        from studio.data.catalog import CheckpointRecord, RunRecord

        if ck.is_oracle:
            return
        run_id = ck.run_id or SHIPPED_RUN_ID
        if catalog.has_checkpoint(ck.id):
            return
        info = next((r for r in self.runs() if r.id == ck.run_id), None)
        ended = (info.ended if info else None) or ""  # a run without an end is still running
        status = {"finished": "done", "cancelled": "cancelled"}.get(ended, "running")
        name = SHIPPED_RUN_NAME if ck.run_id is None else run_id
        catalog.ensure_checkpoint(
            CheckpointRecord(
                id=ck.id,
                run_id=run_id,
                step=info.step if info else 0,
                path=ck.path,
                val_loss=info.best_val if info else None,
                is_best=ck.id.endswith("/best"),
            ),
            RunRecord(
                id=run_id,
                status="done" if ck.run_id is None else status,
                name=name,
                path=str(Path(ck.path).parent),
            ),
        )
