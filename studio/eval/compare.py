"""`studio compare`: two checkpoints on the identical seeded scenes and demonstrations, seed by seed.

    studio compare --a CKPT_A --b CKPT_B [--label-a NAME] [--label-b NAME] [--scene pick_place] [--tasks held-out]
                   [--episodes 10] [--seed 0] [--replan 0] [--workers 1] [--data-dir DIR] [--out FILE.md] [--json]

The episodes are those of ``studio eval`` with the same ``--tasks``, ``--episodes`` and ``--seed``: per (task,
index) a scene seed and a demonstration drawn from the store's expert episodes. The demonstrations are drawn once,
before anything runs, and both checkpoints (either may be ``oracle``) then roll out every episode, A and B one
after the other, in the same pool of processes: a demonstration recorded meanwhile changes nothing, and since a
rollout is deterministic for its (checkpoint, task, seed, demonstration) whatever process runs it, A and B differ
only by their checkpoints. Each plan's execution is bounded as the scene's protocol says (Meta-World: the paper's
500 control ticks; :func:`studio.eval.rollout.protocol_plan_ticks`), as in ``studio eval``. Every rollout is stored
with its recording, under one evaluation id per side (``<compare-id>-a``, ``-b``) and tagged with the comparison in
its ``extra``, so that the studio's *Compare* tab can play the two side by side.

The table has a row per episode — task, index, scene seed, demonstration, A's and B's outcome (✔, or ✘ and the
stage it failed at) and the difference (``A only``, ``B only``, ``both``, ``neither`` succeeded) — differing rows
first, then the totals. :func:`pair_rollouts` builds the same rows from rollouts already in the catalog: any two
evaluations that share (task, seed, demonstration) episodes can be compared without running anything.

:func:`default_pair` is what the studio's *Compare* tab starts with for a scene: among the checkpoints of that
scene, the scene's active policy (A) and the best other one (B), where *best* means the highest held-out success
recorded with the policy (:func:`recorded_held_out`: its ``NAME.json``), then — for checkpoints that record none,
such as a run's — the newest file.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
import uuid
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

from studio.data.catalog import RolloutRecord
from studio.data.paths import add_data_dir_argument
from studio.data.splits import SPLIT_WORDS, resolve_tasks, scene_of_task
from studio.eval.evaluation import RolloutSummary, add_expert_embodiment_argument, expert_embodiments_of

ORACLE = "oracle"
#: The difference column: which of A and B succeeded.
DIFFERENCES = ("A only", "B only", "both", "neither")


class CompareInputError(ValueError):
    """A comparison that cannot run as asked (unknown checkpoint file or task, a scene the checkpoint was not
    trained on, no demonstrations): found before any rollout runs."""


@dataclass(frozen=True)
class Outcome:
    """How one side's rollout of an episode ended."""

    rollout_id: str
    success: bool
    failure_stage: str | None = None

    @property
    def mark(self) -> str:
        return "✔" if self.success else f"✘ {self.failure_stage or 'failed'}"


@dataclass(frozen=True)
class CompareRow:
    """One episode — (task, scene seed, demonstration) — rolled out by A and by B."""

    task: str
    index: int
    seed: int
    expert_episode_id: str
    a: Outcome
    b: Outcome

    @property
    def difference(self) -> str:
        if self.a.success != self.b.success:
            return "A only" if self.a.success else "B only"
        return "both" if self.a.success else "neither"

    @property
    def differs(self) -> bool:
        return self.a.success != self.b.success

    def to_dict(self) -> dict:
        return {**asdict(self), "difference": self.difference}

    @classmethod
    def from_dict(cls, d: dict) -> CompareRow:
        return cls(
            d["task"],
            int(d["index"]),
            int(d["seed"]),
            d["expert_episode_id"],
            Outcome(**d["a"]),
            Outcome(**d["b"]),
        )


def order_rows(rows: Iterable[CompareRow]) -> list[CompareRow]:
    """Differing rows first (A only, then B only), then the rest; by task and index within each group."""
    rank = {d: i for i, d in enumerate(DIFFERENCES)}
    return sorted(
        rows, key=lambda r: (not r.differs, rank[r.difference] if r.differs else 0, r.task, r.index)
    )


@dataclass(frozen=True)
class ComparisonTotals:
    """A comparison's episodes summed up: A's and B's successes and how many episodes fall in each difference."""

    episodes: int
    a_successes: int
    b_successes: int
    a_success: float  # a fraction of the episodes (0 when there are none)
    b_success: float
    a_only: int
    b_only: int
    both: int
    neither: int

    def to_dict(self) -> dict:
        return asdict(self)


def totals(rows: Sequence[CompareRow]) -> ComparisonTotals:
    """Success rates of A and B over the rows, and how many episodes fall in each difference."""
    n = len(rows)
    counts = {d: sum(1 for r in rows if r.difference == d) for d in DIFFERENCES}
    a_successes = sum(1 for r in rows if r.a.success)
    b_successes = sum(1 for r in rows if r.b.success)
    return ComparisonTotals(
        episodes=n,
        a_successes=a_successes,
        b_successes=b_successes,
        a_success=a_successes / n if n else 0.0,
        b_success=b_successes / n if n else 0.0,
        a_only=counts["A only"],
        b_only=counts["B only"],
        both=counts["both"],
        neither=counts["neither"],
    )


def _cell(text: str) -> str:
    return str(text).replace("|", "\\|")


def totals_line(t: ComparisonTotals, label_a: str = "A", label_b: str = "B") -> str:
    return (
        f"**A {t.a_success:.1%}** ({t.a_successes} / {t.episodes}, {_cell(label_a)}) · "
        f"**B {t.b_success:.1%}** ({t.b_successes} / {t.episodes}, {_cell(label_b)}) · "
        f"A only {t.a_only} · B only {t.b_only} · both {t.both} · neither {t.neither}"
    )


def render_markdown(
    rows: Sequence[CompareRow], label_a: str = "A", label_b: str = "B", *, compact: bool = False
) -> str:
    """The per-episode table (in the order given; see :func:`order_rows`) followed by the totals.

    ``compact`` (for a narrow panel): task names without their scene, no index, the demonstration's id by its last
    part, columns headed ``A`` and ``B``, no totals.
    """
    if compact:
        lines = ["| task | seed | demo | A | B | difference |", "| --- | ---: | --- | --- | --- | --- |"]
    else:
        lines = [
            f"| task | # | seed | demonstration | A: {_cell(label_a)} | B: {_cell(label_b)} | difference |",
            "| --- | ---: | ---: | --- | --- | --- | --- |",
        ]
    for r in rows:
        diff = f"**{r.difference}**" if r.differs else r.difference
        if compact:
            task, demo = r.task.split("/", 1)[-1], "…" + r.expert_episode_id.rsplit("-", 1)[-1]
            lines.append(f"| {task} | {r.seed} | `{demo}` | {r.a.mark} | {r.b.mark} | {diff} |")
        else:
            lines.append(
                f"| {r.task} | {r.index} | {r.seed} | `{r.expert_episode_id}` | {r.a.mark} | {r.b.mark} | {diff} |"
            )
    table = "\n".join(lines) + "\n"
    return table if compact else table + "\n" + totals_line(totals(rows), label_a, label_b) + "\n"


def stage_at(stage_ticks: dict | None, step: int) -> str | None:
    """What a rollout was doing at control step ``step`` from the ticks it first reached each stage (a stored
    rollout's ``extra["stage_ticks"]``): ``reaching``, ``grasping``, ``placing`` or ``placed``; None if unknown."""
    if not stage_ticks:
        return None
    for stage, doing in (("reached", "reaching"), ("grasped", "grasping"), ("placed", "placing")):
        tick = stage_ticks.get(stage)
        if tick is None or step < int(tick):
            return doing
    return "placed"


# ---------------------------------------------------------------------------------------------- stored rollouts
@dataclass
class StoredEvaluation:
    """The rollouts of one evaluation id in the catalog (a ``studio eval``, or one side of a comparison)."""

    eval_id: str
    checkpoint: str  # the catalog's checkpoint id, or "oracle"
    rollouts: int
    tasks: list[str]
    created: float
    label: str = ""
    #: How many rollouts the comparison that made it meant to store (None: not from a comparison).
    planned: int | None = None

    @property
    def complete(self) -> bool:
        return self.planned is None or self.rollouts >= self.planned

    def describe(self) -> str:
        when = time.strftime("%Y-%m-%d %H:%M", time.localtime(self.created))
        count = (
            f"{self.rollouts} rollouts"
            if self.complete
            else f"{self.rollouts} of {self.planned} rollouts (stopped)"
        )
        tasks = ", ".join(t.split("/", 1)[-1] for t in self.tasks[:3]) + (" …" if len(self.tasks) > 3 else "")
        return f"{self.eval_id} · {self.label or self.checkpoint} · {count} · {tasks} · {when}"


def stored_evaluations(catalog, limit: int = 20000) -> list[StoredEvaluation]:
    """The catalog's evaluations (rollouts grouped by evaluation id), newest first."""
    groups: dict[str, list] = {}
    for r in catalog.rollouts(limit=limit):
        if r.eval_id:
            groups.setdefault(r.eval_id, []).append(r)
    out = []
    for eval_id, rs in groups.items():
        extra = rs[0].extra or {}
        planned = extra.get("compare_episodes")
        out.append(
            StoredEvaluation(
                eval_id,
                rs[0].checkpoint_id or ORACLE,
                len(rs),
                sorted({r.task for r in rs}),
                min(r.created for r in rs),
                str(extra.get("compare_label", "")),
                int(planned) if planned is not None else None,
            )
        )
    return sorted(out, key=lambda e: -e.created)


def pair_rollouts(a: Iterable[RolloutRecord], b: Iterable[RolloutRecord]) -> list[CompareRow]:
    """Rows for the episodes two sets of stored rollouts (:class:`~studio.data.catalog.RolloutRecord`) share: the
    same task, scene seed and demonstration. Unordered; episodes only one side has are left out."""

    def key(r: RolloutRecord) -> tuple:
        return (r.task, r.seed, r.expert_episode_id)

    first: dict[tuple, RolloutRecord] = {}
    for r in sorted(a, key=lambda r: r.created):
        first.setdefault(key(r), r)
    rows, seen = [], set()
    for rb in sorted(b, key=lambda r: r.created):
        ra = first.get(key(rb))
        if ra is None or key(rb) in seen or rb.seed is None or rb.expert_episode_id is None:
            continue
        seen.add(key(rb))
        rows.append(
            CompareRow(
                rb.task,
                int((ra.extra or {}).get("index", 0)),
                int(rb.seed),
                rb.expert_episode_id,
                Outcome(ra.id, ra.success, ra.failure_stage),
                Outcome(rb.id, rb.success, rb.failure_stage),
            )
        )
    return rows


def compare_stored(catalog, eval_a: str, eval_b: str) -> list[CompareRow]:
    """The ordered rows of two stored evaluations' shared episodes."""
    return order_rows(pair_rollouts(catalog.rollouts(eval_id=eval_a), catalog.rollouts(eval_id=eval_b)))


# ---------------------------------------------------------------------------------------------- default choice
@dataclass(frozen=True)
class Candidate:
    """A checkpoint the comparison may run, as :func:`default_pair` ranks it."""

    id: str
    held_out: float | None = None  # the held-out success recorded with it (a fraction), if any
    created: float = 0.0  # when its file was written (seconds since the epoch)
    oracle: bool = False


_PERCENT = re.compile(r"(\d+(?:\.\d+)?)\s*%")


def recorded_held_out(about: Mapping) -> float | None:
    """The held-out success a policy's ``NAME.json`` records, as a fraction: its ``held_out_success`` when it has
    one (a number in [0, 1]), else the first percentage of its ``summary`` (every shipped summary leads with its
    held-out success); None when it records neither."""
    value = about.get("held_out_success")
    if isinstance(value, (int, float)) and not isinstance(value, bool) and 0.0 <= value <= 1.0:
        return float(value)
    summary = about.get("summary")
    found = _PERCENT.search(summary) if isinstance(summary, str) else None
    if found is None:
        return None
    share = float(found.group(1)) / 100.0
    return share if 0.0 <= share <= 1.0 else None


def rank_candidates(candidates: Iterable[Candidate]) -> list[Candidate]:
    """Best first: recorded held-out success (highest first), then checkpoints that record none (newest first),
    the oracle last (the execution ceiling, not a model)."""
    return sorted(
        candidates,
        key=lambda c: (c.oracle, c.held_out is None, -(c.held_out or 0.0), -c.created, c.id),
    )


def default_pair(candidates: Sequence[Candidate], active: str | None = None) -> tuple[str, str]:
    """The ids of A and B a comparison of these candidates starts with: A the ``active`` policy when it is among
    them (else the best), B the best other one (see :func:`rank_candidates`). With a single candidate, both."""
    ranked = rank_candidates(candidates)
    if not ranked:
        raise ValueError("no checkpoint to compare")
    ids = [c.id for c in ranked]
    a = active if active in ids else ids[0]
    others = [i for i in ids if i != a]
    return a, (others[0] if others else a)


# ---------------------------------------------------------------------------------------------- running
@dataclass(frozen=True)
class Comparison:
    """What :func:`compare` returns: what ran and the rows, in table order.

    :meth:`to_dict` is its JSON form (the ``compare`` job's result on the bus, ``studio compare --json`` and the
    JSON beside ``--out``).
    """

    compare_id: str
    checkpoint_a: str
    checkpoint_b: str
    label_a: str
    label_b: str
    scene: str
    robot: str
    tasks: tuple[str, ...]
    episodes: int
    seed: int
    replan: int
    workers: int
    wall_s: float
    rows: tuple[CompareRow, ...] = ()
    #: Control ticks each plan could execute (the scene's protocol; None: no bound).
    plan_ticks: int | None = None

    @property
    def eval_ids(self) -> tuple[str, str]:
        return f"{self.compare_id}-a", f"{self.compare_id}-b"

    def totals(self) -> ComparisonTotals:
        return totals(self.rows)

    def markdown(self) -> str:
        head = (
            f"A = {self.label_a} (`{self.checkpoint_a}`), B = {self.label_b} (`{self.checkpoint_b}`): "
            f"{', '.join(self.tasks)}; {self.episodes} episodes per task, seed {self.seed}, {self.replan} re-plan(s), "
            + (f"each plan at most {self.plan_ticks} control ticks, " if self.plan_ticks is not None else "")
            + f"the same scene and demonstration for A and B in every row. Comparison `{self.compare_id}`, "
            f"{self.wall_s / 60:.1f} min.\n\n"
        )
        return head + render_markdown(self.rows, self.label_a, self.label_b)

    def to_dict(self) -> dict:
        return {
            "compare_id": self.compare_id,
            "checkpoint_a": self.checkpoint_a,
            "checkpoint_b": self.checkpoint_b,
            "label_a": self.label_a,
            "label_b": self.label_b,
            "scene": self.scene,
            "robot": self.robot,
            "tasks": list(self.tasks),
            "episodes": self.episodes,
            "seed": self.seed,
            "replan": self.replan,
            "workers": self.workers,
            "wall_s": self.wall_s,
            "eval_ids": list(self.eval_ids),
            "totals": self.totals().to_dict(),
            "rows": [r.to_dict() for r in self.rows],
        } | ({} if self.plan_ticks is None else {"plan_ticks": self.plan_ticks})


def default_label(checkpoint: str) -> str:
    """``oracle``, or the checkpoint's name: the file's stem, with its run directory unless it is shipped."""
    if checkpoint == ORACLE:
        return ORACLE
    from studio.data.paths import SHIPPED_POLICY_DIR

    path = Path(checkpoint)
    shipped = path.resolve().parent == SHIPPED_POLICY_DIR.resolve()
    return path.stem if shipped or not path.parent.name else f"{path.parent.name}/{path.stem}"


def check_checkpoint(checkpoint: str, scene: str) -> None:
    """Raise :class:`CompareInputError` unless ``checkpoint`` is ``oracle`` or a checkpoint file that may plan in
    ``scene`` (:func:`studio.eval.evaluation.check_checkpoint`)."""
    from studio.eval.evaluation import EvaluationInputError
    from studio.eval.evaluation import check_checkpoint as check

    try:
        check(checkpoint, scene)
    except EvaluationInputError as e:
        raise CompareInputError(str(e)) from None


def compare(
    checkpoint_a: str,
    checkpoint_b: str,
    tasks: list[str],
    episodes: int,
    seed: int,
    *,
    replan: int = 0,
    workers: int = 1,
    data_dir=None,
    robot: str | None = None,
    label_a: str | None = None,
    label_b: str | None = None,
    expert_embodiments: Sequence[str] | None = None,
    checkpoint_ids: tuple[str | None, str | None] | None = None,
    on_episode: Callable[[int, int, CompareRow], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> Comparison:
    """Roll out both checkpoints on the same episodes (see the module's docstring) and return the comparison.

    Input is checked before anything runs (:class:`CompareInputError`). ``checkpoint_ids`` are the catalog ids
    the rollouts are stored under (default: each file registered as ``studio eval`` does). ``expert_embodiments``
    picks whose demonstrations both imitate, as in ``studio eval``. ``on_episode(done,
    total, row)`` is called each time both sides of an episode have finished; ``should_stop`` is polled between
    rollouts and stops the comparison with :class:`InterruptedError` (the rollouts stored so far stay, marked as
    part of a comparison that planned more).
    """
    from studio.data.paths import resolve_data_dir
    from studio.data.store import EpisodeStore
    from studio.eval.evaluation import (
        EvaluationInputError,
        PolicyRun,
        default_expert_embodiments,
        default_robot,
        make_jobs,
        register_checkpoint,
        run_rollouts,
        with_demonstrations,
    )
    from studio.eval.rollout import protocol_plan_ticks
    from studio.sim.tasks import get_task

    if episodes < 1:
        raise CompareInputError(f"--episodes must be at least 1, got {episodes}")
    if not tasks:
        raise CompareInputError("no tasks to compare on")
    try:
        scenes = {get_task(t).scene for t in tasks}
    except ValueError as e:
        raise CompareInputError(str(e)) from None
    if len(scenes) != 1:
        raise CompareInputError(f"compare on one scene at a time, got tasks from {sorted(scenes)}")
    scene = scenes.pop()
    for checkpoint in (checkpoint_a, checkpoint_b):
        check_checkpoint(checkpoint, scene)
    robot = robot or default_robot(scene)
    experts = tuple(expert_embodiments or default_expert_embodiments(scene))
    root = str(resolve_data_dir(data_dir))
    jobs = make_jobs(tasks, episodes, seed)
    with EpisodeStore(root) as store:
        try:
            jobs = with_demonstrations(store, jobs, experts)  # drawn once: A and B imitate the same ones
        except EvaluationInputError as e:
            raise CompareInputError(str(e)) from None
    ids = list(checkpoint_ids or (None, None))
    for k, checkpoint in enumerate((checkpoint_a, checkpoint_b)):
        if checkpoint != ORACLE and not ids[k]:
            ids[k] = register_checkpoint(root, checkpoint)
    labels = (label_a or default_label(checkpoint_a), label_b or default_label(checkpoint_b))
    compare_id = f"cmp-{uuid.uuid4().hex[:10]}"
    plan_ticks = protocol_plan_ticks(scene)
    sides = [
        PolicyRun(
            checkpoint,
            None if checkpoint == ORACLE else ids[k],
            f"{compare_id}-{side}",
            {
                "compare_id": compare_id,
                "compare_side": side,
                "compare_label": labels[k],
                "compare_episodes": len(jobs),
                "checkpoint": checkpoint,
            },
            plan_ticks=plan_ticks,
        )
        for k, (side, checkpoint) in enumerate((("a", checkpoint_a), ("b", checkpoint_b)))
    ]
    work = [(job, side) for job in jobs for side in sides]  # A and B of an episode one after the other
    got: dict[int, dict[int, RolloutSummary]] = {}

    def done(i: int, summary: RolloutSummary) -> None:
        pair = got.setdefault(i // 2, {})
        pair[i % 2] = summary
        if len(pair) == 2 and on_episode is not None:
            on_episode(
                sum(len(p) == 2 for p in got.values()), len(jobs), _row(jobs[i // 2].index, pair[0], pair[1])
            )

    started = time.perf_counter()
    summaries = run_rollouts(
        work,
        scene=scene,
        robot=robot,
        data_dir=root,
        replan=replan,
        workers=workers,
        on_done=done,
        should_stop=should_stop,
    )
    rows = [_row(job.index, summaries[2 * k], summaries[2 * k + 1]) for k, job in enumerate(jobs)]
    return Comparison(
        compare_id,
        checkpoint_a,
        checkpoint_b,
        labels[0],
        labels[1],
        scene,
        robot,
        tuple(tasks),
        episodes,
        seed,
        replan,
        max(1, min(workers, len(work))),
        time.perf_counter() - started,
        tuple(order_rows(rows)),
        plan_ticks,
    )


def _row(index: int, a: RolloutSummary, b: RolloutSummary) -> CompareRow:
    if (a.task, a.seed, a.expert_episode_id) != (b.task, b.seed, b.expert_episode_id):
        raise AssertionError(f"A and B ran different episodes: {a} / {b}")  # never: both come from one job
    return CompareRow(
        a.task,
        index,
        a.seed,
        a.expert_episode_id,
        Outcome(a.rollout_id, a.success, a.failure_stage),
        Outcome(b.rollout_id, b.success, b.failure_stage),
    )


# ---------------------------------------------------------------------------------------------- command line
def task_list(scene: str, tasks: str | Sequence[str]) -> list[str]:
    """``--tasks`` resolved as ``studio eval`` does (task names give their own scene; ``--scene`` is for the split
    words), an unknown task being a :class:`CompareInputError`."""
    names = [
        n.strip() for n in ([tasks] if isinstance(tasks, str) else tasks) for n in n.split(",") if n.strip()
    ]
    try:
        if names and names[0] not in SPLIT_WORDS:
            scene = scene_of_task(names[0])
        return resolve_tasks(scene, names)
    except ValueError as e:
        raise CompareInputError(str(e)) from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--a", required=True, metavar="CKPT_A", help="checkpoint file A, or 'oracle'")
    parser.add_argument("--b", required=True, metavar="CKPT_B", help="checkpoint file B, or 'oracle'")
    parser.add_argument("--label-a", default=None, help="A's name in the table (default: the file's name)")
    parser.add_argument("--label-b", default=None, help="B's name in the table (default: the file's name)")
    parser.add_argument("--scene", default="pick_place", help="scene whose split 'held-out' refers to")
    parser.add_argument(
        "--tasks",
        default="held-out",
        help="held-out (= test) | train | all | comma-separated task names of one scene",
    )
    parser.add_argument(
        "--episodes", type=int, default=10, help="episodes per task (each rolled out by A and B)"
    )
    parser.add_argument("--seed", type=int, default=0, help="the evaluation seed (as in studio eval)")
    parser.add_argument("--replan", type=int, default=0, help="re-plans allowed inside an episode on failure")
    parser.add_argument("--workers", type=int, default=1, help="parallel rollout processes")
    parser.add_argument(
        "--robot", default=None, help="the agent robot (default: panda; sawyer for metaworld)"
    )
    parser.add_argument("--out", default=None, help="Markdown file to write (the JSON goes beside it)")
    parser.add_argument(
        "--json", action="store_true", help="print the comparison as JSON instead of the table"
    )
    add_expert_embodiment_argument(parser)
    add_data_dir_argument(parser)


def run(args: argparse.Namespace) -> int:
    try:
        tasks = task_list(args.scene, args.tasks)
        try:
            experts = expert_embodiments_of(args)
        except ValueError as e:
            raise CompareInputError(str(e)) from None
        result = compare(
            args.a,
            args.b,
            tasks,
            args.episodes,
            args.seed,
            replan=args.replan,
            workers=args.workers,
            data_dir=args.data_dir,
            robot=args.robot,
            label_a=args.label_a,
            label_b=args.label_b,
            expert_embodiments=experts,
        )
    except CompareInputError as e:
        print(f"studio compare: {e}", file=sys.stderr)
        return 2
    text = result.markdown()
    if args.out:
        out = Path(args.out)
        out.write_text(text)
        out.with_suffix(".json").write_text(json.dumps(result.to_dict(), indent=2, default=float))
    print(json.dumps(result.to_dict(), default=float) if args.json else text)
    return 0
