"""`studio eval`: imitation success on (unseen) tasks, with the paper's breakdown, every rollout stored.

For each rollout: a fresh scene from a seed derived from (``--seed``, task, index), a demonstration of that
task drawn (with a seed derived the same way) from the store's expert episodes — by default Sawyer or human
(uploaded videos and the simulated hand), so the agent (Panda) imitates another embodiment as in the paper;
``--expert-embodiment human`` draws from the human demonstrations only (Human-Franka), ``panda`` from the
Panda's own (Two-Franka) — one planning call, execution with grasp correction,
and up to ``--replan`` re-plans inside the same episode, each plan's execution bounded as the scene's protocol says
(``--plan-ticks``; Meta-World: the paper's 500 control ticks). Rollouts run in parallel worker processes; each is
stored (recording as an agent episode, plans and predicted latents in its folder) and indexed in the catalog.
Every process plans on the same number of torch threads (``planners.PLANNING_THREADS``), so a rollout is the
same bit for bit whatever ``--workers`` says.

``--checkpoint oracle`` plans from the simulator's true state instead of a model: the ceiling of the
execution stack, reported as such. ``--end-offsets`` also measures where each first plan ends against the scripted
expert's own plan for the same scene (the oracle's last waypoint), per rollout and per task.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import uuid
from collections.abc import Callable, Collection, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field, replace
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from studio.data.paths import add_data_dir_argument
from studio.data.splits import SPLIT_WORDS, resolve_tasks, scene_of_task


@dataclass
class EvalJob:
    task: str
    index: int
    env_seed: int
    expert_seed: int
    #: The demonstration to imitate; None: drawn with ``expert_seed`` from the store's when the rollout runs.
    expert_episode_id: str | None = None


@dataclass
class PolicyRun:
    """One policy's share of a run of rollouts: what plans, and what its rollouts are stored under."""

    checkpoint: str  # a checkpoint file, or "oracle"
    checkpoint_id: str | None  # the catalog id (None for the oracle)
    eval_id: str
    extra: dict = field(default_factory=dict)  # added to each stored rollout's ``extra``
    grasp: str = "auto"  # grasp correction (studio.eval.rollout.GRASP_MODES)
    plan_ticks: int | None = None  # control ticks each plan may execute (None: no bound)
    end_offsets: bool = False  # measure each first plan's end against the scripted expert's (RolloutSummary)


@dataclass(frozen=True)
class RolloutSummary:
    """One stored rollout's outcome: the episode it ran, how far it got, its re-plans and timings."""

    rollout_id: str
    task: str
    index: int
    seed: int
    expert_episode_id: str
    success: bool
    reached: bool
    grasped: bool
    placed: bool
    failure_stage: str | None
    replans: int
    planning_time_s: float
    duration_s: float
    # Per attempt: the breakdown after it and its planning time (``with_budget`` derives smaller budgets).
    attempt_stages: list[dict[str, bool]] = field(default_factory=list)
    attempt_planning_s: list[float] = field(default_factory=list)
    #: The first plan's last waypoint minus the scripted expert's last waypoint for the same scene (the oracle's
    #: plan), world frame, metres; None unless asked for (``--end-offsets``).
    end_offset: tuple[float, float, float] | None = None

    def to_dict(self) -> dict:
        """JSON-ready built-ins; ``end_offset`` only when measured."""
        out = asdict(self)
        if self.end_offset is None:
            del out["end_offset"]
        else:
            out["end_offset"] = list(self.end_offset)
        return out


def make_jobs(tasks: list[str], episodes: int, seed: int) -> list[EvalJob]:
    """Deterministic (task, index) -> scene seed and demonstration-choice seed."""
    jobs = []
    for t_idx, task in enumerate(tasks):
        for i in range(episodes):
            ss = np.random.SeedSequence([seed, t_idx, i, 0x5EED])
            env_seed, expert_seed = (int(x) for x in ss.generate_state(2))
            jobs.append(EvalJob(task, i, env_seed % (2**31), expert_seed))
    return jobs


#: Whose demonstrations a rollout imitates unless told otherwise: another embodiment than the Panda agent's.
DEFAULT_EXPERT_EMBODIMENTS = ("sawyer", "human")
#: How to collect demonstrations of an embodiment (for the message when there are none).
_COLLECT_HINT = {"sawyer": "--robot sawyer", "human": "--robot hand", "panda": "--robot panda --role expert"}


def demonstration_order(meta) -> tuple:
    """Where a demonstration stands among those a rollout draws from: by what it is — embodiment, source, its
    scripted collection slot (base seed, index) and scene seed — and by its id only among demonstrations that
    share all of those (teleoperated or uploaded ones). Ids carry the time of storing, so ordering by id alone
    made the same ``studio collect`` into a fresh data directory draw other demonstrations for the same seeds."""

    def number(v: int | None) -> tuple[int, int]:
        return (0, 0) if v is None else (1, int(v))

    return (
        meta.embodiment,
        meta.source,
        number(meta.collect_seed),
        number(meta.collect_index),
        number(meta.seed),
        meta.num_frames,
        meta.id,
    )


class EvaluationInputError(ValueError):
    """An evaluation that cannot run as asked, found before any rollout: no checkpoint file, a file that is not a
    checkpoint or was trained on another scene, no demonstration of a task. The message says what to do."""


def check_checkpoint(checkpoint: str, scene: str) -> None:
    """Raise :class:`EvaluationInputError` unless ``checkpoint`` is ``oracle`` or a checkpoint file that may plan
    in ``scene``: one whose recorded training tasks (when it records them) include tasks of that scene. Reads the
    file's metadata only, without torch and without running anything in it."""
    if checkpoint == "oracle":
        return
    path = Path(checkpoint)
    if not path.is_file():
        raise EvaluationInputError(f"no checkpoint file {checkpoint!r} (give a .pt file or 'oracle')")
    from studio.model.checkpoint_info import read_checkpoint_info

    try:
        trained = read_checkpoint_info(path).get("tasks") or []
    except ValueError as e:
        raise EvaluationInputError(f"{checkpoint} is not a checkpoint ({str(e).splitlines()[0]})") from None
    if not isinstance(trained, (list, tuple)):
        trained = []
    scenes = sorted({scene_of_task(t) for t in trained if "/" in str(t)})
    if scenes and scene not in scenes:
        raise EvaluationInputError(
            f"{checkpoint} was trained on {', '.join(scenes)} tasks, not on scene {scene!r}"
        )


def _expert_choices(store, task: str, embodiments: Sequence[str] = DEFAULT_EXPERT_EMBODIMENTS) -> list[str]:
    """Ids of the stored demonstrations of ``task`` by one of ``embodiments``, in :func:`demonstration_order`;
    :class:`EvaluationInputError` saying how to collect some when there is none."""
    metas = sorted(
        store.episodes(task=task, role="expert", embodiment=list(embodiments)), key=demonstration_order
    )
    ids = [m.id for m in metas]
    if not ids:
        hint = _COLLECT_HINT.get(embodiments[0], "--robot sawyer")
        raise EvaluationInputError(
            f"no expert demonstration of {task!r} by {' or '.join(embodiments)} in the store; "
            f"collect some with: studio collect {hint} --tasks {task}"
        )
    return ids


def choose_demonstration(store, job: EvalJob, embodiments: Sequence[str] = DEFAULT_EXPERT_EMBODIMENTS) -> str:
    """The demonstration ``job`` imitates: its own, or one drawn with its ``expert_seed`` from the store's expert
    episodes of its task by ``embodiments`` as they are now — a demonstration recorded meanwhile changes the draw."""
    if job.expert_episode_id is not None:
        return job.expert_episode_id
    choices = _expert_choices(store, job.task, embodiments)
    return choices[np.random.default_rng(job.expert_seed).integers(len(choices))]


def with_demonstrations(
    store, jobs: list[EvalJob], embodiments: Sequence[str] = DEFAULT_EXPERT_EMBODIMENTS
) -> list[EvalJob]:
    """``jobs`` with their demonstrations drawn now, once: rollouts of these jobs by several policies imitate the
    same demonstrations even if the store gains episodes while they run."""
    return [replace(j, expert_episode_id=choose_demonstration(store, j, embodiments)) for j in jobs]


# ---------------------------------------------------------------------------------------------- worker side
_W: dict = {}


def _init_worker(checkpoints: tuple[str, ...], data_dir: str, scene: str, robot: str) -> None:
    os.environ.setdefault("MUJOCO_GL", "egl")
    from studio.data.store import EpisodeStore
    from studio.sim.env import make_env

    _W["store"] = EpisodeStore(data_dir)
    _W["env"] = make_env(scene, robot)
    _W["planners"] = {}
    for checkpoint in dict.fromkeys(checkpoints):
        if checkpoint == "oracle":
            from studio.eval.oracle import OraclePlanner

            _W["planners"][checkpoint] = OraclePlanner(_W["env"])
        else:
            from studio.eval.planners import use_planning_threads
            from studio.model.planner import Planner

            _W.setdefault("threads_before", use_planning_threads())
            _W["planners"][checkpoint] = Planner.load(checkpoint)


def _close_worker() -> None:
    env, store, reference = _W.pop("env", None), _W.pop("store", None), _W.pop("reference", None)
    if reference is not None:
        reference.close()
    threads = _W.pop("threads_before", None)
    _W.clear()
    if env is not None:
        env.close()
    if store is not None:
        store.close()
    if threads is not None:  # the caller's own process (one worker): leave torch as it was
        import torch

        torch.set_num_threads(threads)


def _run_job(
    job: EvalJob, policy: PolicyRun, replan: int, keep: bool, should_stop: Callable[[], bool] | None = None
) -> RolloutSummary:
    from studio.eval.latents import attach_latent_images
    from studio.eval.rollout import grasp_controller, run_rollout, store_rollout

    store, env = _W["store"], _W["env"]
    planner = _W["planners"][policy.checkpoint]
    expert_id = choose_demonstration(store, job)
    expert_frames = store.load_frames(expert_id)
    if hasattr(planner, "clear_cache"):
        planner.clear_cache()
    # When each stage was first reached, for viewers that follow the rollout step by step (read only: the
    # simulator tracks its stages every tick anyway).
    stage_ticks: dict[str, int | None] = dict.fromkeys(("reached", "grasped", "placed"))
    reference_end = _expert_end(env, job) if policy.end_offsets else None

    def on_tick() -> None:
        for k, v in env.stages().items():
            if v and k in stage_ticks and stage_ticks[k] is None:
                stage_ticks[k] = int(env.steps)

    out = run_rollout(
        env,
        planner,
        expert_frames,
        job.task,
        job.env_seed,
        replans=replan,
        on_tick=on_tick,
        should_stop=should_stop,
        controller_config=grasp_controller(env.scene, policy.grasp),
        plan_ticks=policy.plan_ticks,
    )
    if out.failure_stage == "cancelled":
        raise InterruptedError("stopped before the rollout ended")
    if keep and policy.checkpoint != "oracle":
        attach_latent_images(policy.checkpoint, out.plans)
    record = store_rollout(
        store,
        out,
        expert_episode_id=expert_id,
        checkpoint_id=policy.checkpoint_id,
        eval_id=policy.eval_id,
        keep=keep,
        extra={
            "index": job.index,
            "stage_ticks": stage_ticks,
            "grasp_correction": policy.grasp,
            **policy.extra,
        },
    )
    return RolloutSummary(
        record.id,
        job.task,
        job.index,
        job.env_seed,
        expert_id,
        out.success,
        out.stages["reached"],
        out.stages["grasped"],
        out.stages["placed"],
        out.failure_stage,
        out.replans,
        out.planning_time_s,
        out.duration_s,
        out.attempt_stages,
        [p.planning_time_s for p in out.plans],
        end_offset=None if reference_end is None or not out.plans else _offset(out.plans[0], reference_end),
    )


def _offset(plan, reference_end: np.ndarray) -> tuple[float, float, float]:
    """``plan``'s last waypoint minus ``reference_end`` (world frame, m)."""
    x, y, z = (float(v) for v in np.asarray(plan.waypoints_world, dtype=float)[-1, :3] - reference_end)
    return x, y, z


def _expert_end(env, job: EvalJob) -> np.ndarray | None:
    """Where the scripted expert's plan for ``job``'s scene ends (the oracle planner's last waypoint, world
    frame); None where Meta-World's scripted policy fails in that scene (a few seeds in a hundred), whose path
    ends nowhere worth measuring against. The scene is reset for it, and ``run_rollout`` resets it again, so the
    rollout is the same."""
    from studio.eval.oracle import OraclePlanner

    if "reference" not in _W:
        _W["reference"] = OraclePlanner(env, strict=True)
    env.reset(job.task, job.env_seed)
    try:
        plan = _W["reference"].plan(None, None, None, None)
    except RuntimeError:
        return None
    return np.asarray(plan.waypoints_world, dtype=float)[-1, :3]


def _run_chunk(work: list[tuple[int, EvalJob, PolicyRun]], replan: int, keep: bool):
    return [(i, _run_job(job, policy, replan, keep)) for i, job, policy in work]


def run_rollouts(
    work: list[tuple[EvalJob, PolicyRun]],
    *,
    scene: str,
    robot: str,
    data_dir: str,
    replan: int = 0,
    workers: int = 1,
    keep: bool = True,
    on_done: Callable[[int, RolloutSummary], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> list[RolloutSummary]:
    """Run each (job, policy) of ``work`` and store it; the summaries come back in the order of ``work``.

    ``workers`` > 1 runs them in that many processes, each with the scene and every policy's planner loaded.
    ``on_done(i, summary)`` is called (in this process) as each finishes, in any order; ``should_stop`` is polled
    between rollouts (and every tick of an in-process one) and raises :class:`InterruptedError` when it says so.
    Whatever runs them, each process plans on :data:`studio.eval.planners.PLANNING_THREADS` torch threads, so a
    rollout does not depend on ``workers``.
    """
    checkpoints = tuple(dict.fromkeys(p.checkpoint for _, p in work))
    done: dict[int, RolloutSummary] = {}
    workers = max(1, min(workers, len(work)))

    def finished(i: int, summary: RolloutSummary) -> None:
        done[i] = summary
        if on_done is not None:
            on_done(i, summary)

    def stop_now() -> None:
        if should_stop is not None and should_stop():
            raise InterruptedError(f"stopped after {len(done)} of {len(work)} rollouts")

    if workers == 1:
        _init_worker(checkpoints, data_dir, scene, robot)
        try:
            for i, (job, policy) in enumerate(work):
                stop_now()
                finished(i, _run_job(job, policy, replan, keep, should_stop))
        finally:
            _close_worker()  # the renderer's GL context must not outlive the call (a crash at exit otherwise)
    else:
        # Small chunks keep progress moving while each worker keeps its env and models loaded.
        items = [(i, job, policy) for i, (job, policy) in enumerate(work)]
        chunks = [items[k : k + 4] for k in range(0, len(items), 4)]
        with ProcessPoolExecutor(
            workers,
            mp_context=get_context("spawn"),
            initializer=_init_worker,
            initargs=(checkpoints, data_dir, scene, robot),
        ) as pool:
            futures = [pool.submit(_run_chunk, c, replan, keep) for c in chunks]
            try:
                for f in as_completed(futures):
                    for i, summary in f.result():
                        finished(i, summary)
                    stop_now()
            except BaseException:
                for f in futures:
                    f.cancel()
                raise
    return [done[i] for i in range(len(work))]


# ---------------------------------------------------------------------------------------------- driver side
@dataclass(frozen=True)
class TaskBreakdown:
    """One task's rollouts summed up: success, the share that reached each stage, re-plans, planning time."""

    rollouts: int
    success: float
    reached: float
    grasped: float
    placed: float
    mean_replans: float
    mean_planning_ms: float
    #: How many rollouts failed at each stage (only the stages some rollout failed at).
    failure_stages: dict[str, int]
    #: Over the rollouts with an ``end_offset`` (``end_measured`` of them): its mean and standard deviation per
    #: axis (m), and the mean distance between the two ends (m); None when none was measured.
    end_offset_mean: tuple[float, float, float] | None = None
    end_offset_sd: tuple[float, float, float] | None = None
    end_distance_mean: float | None = None
    end_measured: int | None = None

    def end_offsets_text(self) -> str | None:
        """The end offsets in cm as ``studio eval`` prints them (None when not measured)."""
        mean, sd, distance, measured = (
            self.end_offset_mean,
            self.end_offset_sd,
            self.end_distance_mean,
            self.end_measured,
        )
        if mean is None or sd is None or distance is None or measured is None:
            return None
        axes = "  ".join(
            f"{axis} {100 * m:+6.1f} ± {100 * d:4.1f}" for axis, m, d in zip("xyz", mean, sd, strict=True)
        )
        missing = self.rollouts - measured
        unmeasured = f"; {missing} not measured: the scripted expert failed there" if missing else ""
        return f"{axes}  ({100 * distance:.1f}{unmeasured})"

    def to_dict(self) -> dict:
        """JSON-ready built-ins; the ``end_*`` keys only when measured."""
        out = asdict(self)
        for key in ("end_offset_mean", "end_offset_sd", "end_distance_mean", "end_measured"):
            value = out.pop(key)
            if value is not None:
                out[key] = list(value) if isinstance(value, tuple) else value
        return out


@dataclass(frozen=True)
class RolloutTotals:
    """Rollouts summed up per task (sorted by name) and over all of them."""

    tasks: dict[str, TaskBreakdown]
    success: float
    rollouts: int
    mean_planning_ms: float


@dataclass(frozen=True)
class EvaluationReport:
    """What :func:`evaluate` returns: the totals, what was evaluated and how, and every rollout by (task, index).

    :meth:`to_dict` is its JSON form (``studio eval --json``, the reports beside ``studio results``' table).
    """

    tasks: dict[str, TaskBreakdown]
    success: float
    rollouts: int
    mean_planning_ms: float
    eval_id: str
    checkpoint: str  # the checkpoint file, or "oracle"
    robot: str
    scene: str
    seed: int
    replan: int
    grasp_correction: str
    expert_embodiments: tuple[str, ...]
    episodes_per_task: int
    wall_s: float
    workers: int
    rows: tuple[RolloutSummary, ...]
    #: Control ticks each plan could execute (None: no bound; the paper's Meta-World protocol: 500).
    plan_ticks: int | None = None
    #: Set by :func:`with_budget`: the budget of the evaluation these rows were cut from.
    derived_from_replan: int | None = None
    #: Set by :func:`with_budget` when it cut some tasks only: those tasks.
    replan_cut_tasks: tuple[str, ...] | None = None

    def to_dict(self) -> dict:
        """The report as JSON-ready built-ins; the keys ``plan_ticks``, ``derived_from_replan`` and
        ``replan_cut_tasks`` only when set."""
        out: dict = {
            "tasks": {task: breakdown.to_dict() for task, breakdown in self.tasks.items()},
            "success": self.success,
            "rollouts": self.rollouts,
            "mean_planning_ms": self.mean_planning_ms,
            "eval_id": self.eval_id,
            "checkpoint": self.checkpoint,
            "robot": self.robot,
            "scene": self.scene,
            "seed": self.seed,
            "replan": self.replan,
            "grasp_correction": self.grasp_correction,
            "expert_embodiments": list(self.expert_embodiments),
            "episodes_per_task": self.episodes_per_task,
            "wall_s": self.wall_s,
            "workers": self.workers,
        }
        if self.plan_ticks is not None:
            out["plan_ticks"] = self.plan_ticks
        if self.derived_from_replan is not None:
            out["derived_from_replan"] = self.derived_from_replan
        if self.replan_cut_tasks is not None:
            out["replan_cut_tasks"] = list(self.replan_cut_tasks)
        out["rows"] = [r.to_dict() for r in self.rows]
        return out


def summarise(rows: Sequence[RolloutSummary]) -> RolloutTotals:
    """Per-task breakdowns and overall success and planning time of ``rows`` (zeros when there are none)."""
    by_task: dict[str, TaskBreakdown] = {}
    for task in sorted({r.task for r in rows}):
        rs = [r for r in rows if r.task == task]
        by_task[task] = TaskBreakdown(
            rollouts=len(rs),
            success=float(np.mean([r.success for r in rs])),
            reached=float(np.mean([r.reached for r in rs])),
            grasped=float(np.mean([r.grasped for r in rs])),
            placed=float(np.mean([r.placed for r in rs])),
            mean_replans=float(np.mean([r.replans for r in rs])),
            mean_planning_ms=1000 * float(np.mean([r.planning_time_s for r in rs])),
            failure_stages={
                s: sum(1 for r in rs if r.failure_stage == s)
                for s in sorted({r.failure_stage for r in rs if r.failure_stage})
            },
            **_end_offsets(rs),
        )
    return RolloutTotals(
        tasks=by_task,
        success=float(np.mean([r.success for r in rows])) if rows else 0.0,
        rollouts=len(rows),
        mean_planning_ms=1000 * float(np.mean([r.planning_time_s for r in rows])) if rows else 0.0,
    )


def _end_offsets(rows: Sequence[RolloutSummary]) -> dict:
    """A task's ``end_*`` fields of :class:`TaskBreakdown` from its rows' end offsets (none measured: empty)."""
    offsets = np.array([r.end_offset for r in rows if r.end_offset is not None], dtype=float).reshape(-1, 3)
    if not len(offsets):
        return {}
    return {
        "end_offset_mean": tuple(offsets.mean(axis=0).tolist()),
        "end_offset_sd": tuple(offsets.std(axis=0).tolist()),
        "end_distance_mean": float(np.linalg.norm(offsets, axis=1).mean()),
        "end_measured": len(offsets),
    }


def with_budget(
    report: EvaluationReport, replan: int, tasks: Collection[str] | None = None
) -> EvaluationReport:
    """The report ``report`` (evaluated with a larger re-plan budget) would have been with ``replan`` re-plans.

    Exact, not an estimate: a rollout is deterministic for its seed, and a re-plan happens only after an attempt
    failed inside the same episode, so a budget of k replays the first k + 1 attempts of a larger budget's
    rollout — its outcome is the breakdown recorded after attempt k + 1. (The wall time is the larger run's.)
    ``tasks`` limits the cut to those tasks' rollouts, the others keep the full budget: the paper's Meta-World
    protocol, which re-plans on the hard tasks only, is ``with_budget(report, 0, easy_tasks)``.
    """
    from studio.eval.rollout import failure_stage  # the simulator: loaded only when a budget is derived

    if replan > report.replan:
        raise ValueError(f"cannot derive {replan} re-plans from an evaluation with {report.replan}")
    rows = []
    for r in report.rows:
        cut = tasks is None or r.task in tasks
        if cut and len(r.attempt_stages) > replan + 1:  # it used more attempts than the smaller budget allows
            stages, times = r.attempt_stages[replan], r.attempt_planning_s[: replan + 1]
            r = replace(
                r,
                success=stages["placed"],
                reached=stages["reached"],
                grasped=stages["grasped"],
                placed=stages["placed"],
                failure_stage=failure_stage(stages),
                replans=replan,
                planning_time_s=float(np.mean(times)),
                attempt_stages=r.attempt_stages[: replan + 1],
                attempt_planning_s=times,
            )
        rows.append(r)
    derived = summarise(rows)
    return replace(
        report,
        tasks=derived.tasks,
        success=derived.success,
        rollouts=derived.rollouts,
        mean_planning_ms=derived.mean_planning_ms,
        replan=replan,
        derived_from_replan=report.replan,
        replan_cut_tasks=report.replan_cut_tasks if tasks is None else tuple(sorted(tasks)),
        rows=tuple(rows),
    )


def default_expert_embodiments(scene: str) -> tuple[str, ...]:
    """Whose demonstrations a scene's rollouts imitate unless told: the Sawyer on Meta-World, else the Sawyer or a
    person."""
    return ("sawyer",) if scene == "metaworld" else DEFAULT_EXPERT_EMBODIMENTS


def default_robot(scene: str) -> str:
    """The agent of a scene family: the Panda on the tabletop, the Sawyer in Meta-World (same pool, as in the paper)."""
    return "sawyer" if scene == "metaworld" else "panda"


def register_checkpoint(data_dir, checkpoint: str | os.PathLike) -> str:
    """The catalog id of a checkpoint file, registering it (and its run) on first use.

    Ids follow the studio's naming (``studio.ui.runs``): ``<run-dir>/<name>`` for ``<run-dir>/<name>.pt``, and
    ``default/<name>`` in run ``shipped`` for a policy shipped with the package.
    """
    from studio.data.catalog import Catalog, CheckpointRecord, RunRecord
    from studio.data.paths import CATALOG_NAME, SHIPPED_POLICY_DIR, SHIPPED_RUN_ID, SHIPPED_RUN_NAME
    from studio.model.checkpoint import load_checkpoint

    path = Path(checkpoint).resolve()
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint file {str(checkpoint)!r}")
    shipped = path.parent == SHIPPED_POLICY_DIR.resolve()
    run_id = SHIPPED_RUN_ID if shipped else path.parent.name
    checkpoint_id = f"default/{path.stem}" if shipped else f"{run_id}/{path.stem}"
    with Catalog(Path(data_dir) / CATALOG_NAME) as catalog:
        if not catalog.has_checkpoint(checkpoint_id):  # reading the file (for its step) only the first time
            step = int(load_checkpoint(path).get("step", 0))
            catalog.ensure_checkpoint(
                CheckpointRecord(id=checkpoint_id, run_id=run_id, step=step, path=str(path)),
                RunRecord(
                    id=run_id,
                    status="done",
                    name=SHIPPED_RUN_NAME if shipped else run_id,
                    path=str(path.parent),
                ),
            )
    return checkpoint_id


def evaluate(
    checkpoint: str,
    tasks: list[str],
    episodes: int,
    seed: int,
    replan: int = 0,
    workers: int = 1,
    data_dir=None,
    robot: str | None = None,
    keep: bool = True,
    progress: bool = True,
    expert_embodiments: Sequence[str] | None = None,
    grasp: str = "auto",
    plan_ticks: int | None = None,
    end_offsets: bool = False,
) -> EvaluationReport:
    """Run the evaluation and return its report (the rollouts are also written into the catalog).

    ``expert_embodiments`` picks whose demonstrations the rollouts imitate (None: Sawyer or human; Meta-World: the
    Sawyer, its only demonstrator). The demonstrations are drawn before the first rollout; a checkpoint or store
    that cannot be evaluated raises :class:`EvaluationInputError` before any rollout runs. ``grasp`` is the grasp
    correction (:data:`studio.eval.rollout.GRASP_MODES`; ``auto``: the scene's own). ``plan_ticks`` bounds each
    plan's execution in control ticks (None: no bound). ``end_offsets`` measures each first plan's end against
    the scripted expert's for the same scene (``RolloutSummary.end_offset``, the ``end_*`` of each task's
    breakdown); it costs a scripted plan per rollout and leaves the rollouts as they are.
    """
    from studio.data.paths import resolve_data_dir
    from studio.eval.rollout import grasp_controller
    from studio.sim.tasks import get_task

    scenes = {get_task(t).scene for t in tasks}
    if len(scenes) != 1:
        raise ValueError(f"evaluate one scene at a time, got tasks from {sorted(scenes)}")
    scene = scenes.pop()
    grasp_controller(scene, grasp)  # a bad mode fails here, before any worker starts
    check_checkpoint(checkpoint, scene)
    robot = robot or default_robot(scene)
    root = str(resolve_data_dir(data_dir))
    eval_id = f"eval-{uuid.uuid4().hex[:10]}"
    experts = tuple(expert_embodiments or default_expert_embodiments(scene))
    from studio.data.store import EpisodeStore

    with EpisodeStore(root) as store:
        jobs = with_demonstrations(store, make_jobs(tasks, episodes, seed), experts)
    checkpoint_id = None if checkpoint == "oracle" else register_checkpoint(root, checkpoint)
    started = time.perf_counter()
    if plan_ticks is not None and plan_ticks < 1:
        raise ValueError(f"plan_ticks must be >= 1, got {plan_ticks}")
    policy = PolicyRun(
        checkpoint, checkpoint_id, eval_id, grasp=grasp, plan_ticks=plan_ticks, end_offsets=end_offsets
    )
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(jobs), desc="rollouts", unit="rollout", file=sys.stderr)

    def tick(_i: int, _row: RolloutSummary) -> None:
        if bar is not None:
            bar.update(1)

    try:
        rows = run_rollouts(
            [(j, policy) for j in jobs],
            scene=scene,
            robot=robot,
            data_dir=root,
            replan=replan,
            workers=workers,
            keep=keep,
            on_done=tick,
        )
    finally:
        if bar:
            bar.close()
    workers = max(1, min(workers, len(jobs)))
    rows.sort(key=lambda r: (r.task, r.index))
    totals = summarise(rows)
    return EvaluationReport(
        tasks=totals.tasks,
        success=totals.success,
        rollouts=totals.rollouts,
        mean_planning_ms=totals.mean_planning_ms,
        eval_id=eval_id,
        checkpoint=checkpoint,
        robot=robot,
        scene=scene,
        seed=seed,
        replan=replan,
        grasp_correction=grasp,
        plan_ticks=plan_ticks,
        expert_embodiments=experts,
        episodes_per_task=episodes,
        wall_s=time.perf_counter() - started,
        workers=workers,
        rows=tuple(rows),
    )


def add_expert_embodiment_argument(parser: argparse.ArgumentParser) -> None:
    """``--expert-embodiment``: whose demonstrations the rollouts imitate (repeatable or comma-separated)."""
    parser.add_argument(
        "--expert-embodiment",
        action="append",
        default=None,
        metavar="EMBODIMENT",
        help="imitate demonstrations by this embodiment only: sawyer, human (uploaded videos and the simulated "
        "hand) or panda; repeatable or comma-separated (default: sawyer and human; metaworld: sawyer)",
    )


def expert_embodiments_of(args: argparse.Namespace) -> list[str] | None:
    """The embodiments ``--expert-embodiment`` named (None: the default); raises ValueError on an unknown one."""
    from studio.data.episode import EMBODIMENTS

    if not args.expert_embodiment:
        return None
    names = [n.strip() for item in args.expert_embodiment for n in item.split(",") if n.strip()]
    unknown = sorted(set(names) - set(EMBODIMENTS))
    if unknown:
        raise ValueError(f"unknown embodiment(s) {', '.join(unknown)}; choose from {', '.join(EMBODIMENTS)}")
    return names


def add_grasp_correction_argument(parser: argparse.ArgumentParser) -> None:
    """``--grasp-correction``: how rollouts correct grasps from the wrist depth camera."""
    from studio.eval.rollout import GRASP_MODES

    parser.add_argument(
        "--grasp-correction",
        choices=GRASP_MODES,
        default="auto",
        help="auto: the scene's default (pick_place and metaworld: height, push: off); height: centre over the "
        "object and grasp no higher than its middle; centre: centre only (the paper's); off: grasp as planned",
    )


#: The paper's bound on one plan's execution in Meta-World, in simulation steps (one step = one control tick).
PAPER_PLAN_TICKS = 500


def add_plan_ticks_argument(parser: argparse.ArgumentParser) -> None:
    """``--plan-ticks``: control ticks each plan may execute before it counts as failed (:func:`plan_ticks_of`)."""
    parser.add_argument(
        "--plan-ticks",
        type=int,
        default=None,
        metavar="TICKS",
        help="control ticks each plan may execute; a plan cut there is a failed attempt, and the next re-plan "
        "starts from where the arm is (default: the scene's protocol, the paper's "
        f"{PAPER_PLAN_TICKS} in Meta-World and no bound elsewhere; 0: no bound)",
    )


def plan_ticks_of(given: int | None, scene: str) -> int | None:
    """A bound on each plan as given (``--plan-ticks``, a ``rollout`` job's ``plan_ticks``) as run: absent, the
    scene's protocol (:func:`studio.eval.rollout.protocol_plan_ticks`); 0, no bound; else as given. ``ValueError``
    below 0."""
    from studio.eval.rollout import protocol_plan_ticks

    if given is None:
        return protocol_plan_ticks(scene)
    if given < 0:
        raise ValueError(f"--plan-ticks must be >= 0 (0: no bound), got {given}")
    return given or None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--checkpoint", required=True, help="checkpoint file, or 'oracle' for the execution ceiling"
    )
    parser.add_argument(
        "--tasks",
        default="held-out",
        help="held-out (= test) | train | all | comma-separated task names of one scene",
    )
    parser.add_argument(
        "--scene",
        default="pick_place",
        help="scene whose split 'held-out' refers to (task names give their own scene)",
    )
    parser.add_argument("--episodes", type=int, default=10, help="rollouts per task")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--replan", type=int, default=0, help="re-plans allowed inside an episode on failure")
    add_plan_ticks_argument(parser)
    parser.add_argument("--workers", type=int, default=1, help="parallel rollout processes")
    parser.add_argument(
        "--robot", default=None, help="the agent robot (default: panda; sawyer for metaworld)"
    )
    parser.add_argument(
        "--no-store", action="store_true", help="do not store the rollouts (catalog rows only)"
    )
    parser.add_argument("--json", action="store_true", help="print the full report as JSON")
    parser.add_argument(
        "--end-offsets",
        action="store_true",
        help="also measure where each first plan ends against the scripted expert's plan for the same scene "
        "(the oracle's last waypoint): per rollout in the JSON, per task as mean ± sd in cm",
    )
    add_grasp_correction_argument(parser)
    add_expert_embodiment_argument(parser)
    add_data_dir_argument(parser)


def run(args: argparse.Namespace) -> int:
    scene = args.scene
    names = [n.strip() for n in args.tasks.split(",") if n.strip()]
    try:
        if names and names[0] not in SPLIT_WORDS:
            scene = scene_of_task(names[0])  # task names give their scene; --scene is for the split words
        tasks = resolve_tasks(scene, names)
        experts = expert_embodiments_of(args)
        plan_ticks = plan_ticks_of(args.plan_ticks, scene)
    except ValueError as err:
        print(f"studio eval: {err}", file=sys.stderr)
        return 2
    try:
        report = evaluate(
            args.checkpoint,
            tasks,
            args.episodes,
            args.seed,
            args.replan,
            args.workers,
            args.data_dir,
            args.robot,
            keep=not args.no_store,
            expert_embodiments=experts,
            grasp=args.grasp_correction,
            plan_ticks=plan_ticks,
            end_offsets=args.end_offsets,
        )
    except EvaluationInputError as err:
        print(f"studio eval: {err}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(report.to_dict(), default=float))
        return 0
    print(
        f"eval {report.eval_id}  checkpoint={args.checkpoint}  replan={args.replan}  "
        f"experts={','.join(report.expert_embodiments)}  "
        + (f"plan-ticks={plan_ticks}  " if plan_ticks is not None else "")
        + f"{report.rollouts} rollouts in {report.wall_s:.0f} s"
    )
    w = max([32, *(len(task) for task in report.tasks)])  # the task column, as wide as the longest name
    print(
        f"{'task':{w}s} {'n':>4s} {'success':>8s} {'reached':>8s} {'grasped':>8s} {'placed':>8s} {'plan ms':>8s}"
    )
    for task, t in report.tasks.items():
        print(
            f"{task:{w}s} {t.rollouts:4d} {t.success:8.1%} {t.reached:8.1%} {t.grasped:8.1%} "
            f"{t.placed:8.1%} {t.mean_planning_ms:8.1f}"
        )
    print(f"{'all':{w}s} {report.rollouts:4d} {report.success:8.1%}")
    ends = {task: t.end_offsets_text() for task, t in report.tasks.items()}
    if any(ends.values()):
        print("first plan's last waypoint − the scripted expert's, world frame, cm (mean ± sd; distance):")
        for task, text in ends.items():
            if text:
                print(f"{task:{w}s} {text}")
    return 0
