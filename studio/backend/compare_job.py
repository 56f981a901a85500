"""The ``compare`` job of a sim worker: two checkpoints on the identical seeded episodes, as ``studio compare``.

A thin handler: the comparison is :func:`studio.eval.compare.compare`; this module turns the job's spec into its
arguments and its episodes into job progress ("episode i of N"), and returns the table's rows. Rollouts run in the
worker's own process (``workers`` > 1 starts that many processes beside it) and are stored as each ends; the rows
are the job's result, published only when every episode has both sides. A worker that dies mid-way fails the job
(the queue says it was lost), and the rollouts it stored before are marked as part of a comparison that planned
more: nothing half-done passes for a result.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Any, Literal

import msgspec

from studio.backend.messages import ContentId
from studio.backend.plan_job import checked_checkpoint

if TYPE_CHECKING:
    from studio.eval.compare import CompareRow

PathText = Annotated[str, msgspec.Meta(min_length=1, max_length=4096)]
Name = Annotated[str, msgspec.Meta(min_length=1, max_length=200)]


class CompareJobSpec(msgspec.Struct, forbid_unknown_fields=True):
    """What a ``compare`` job runs (the options of ``studio compare``).

    Attributes:
        a, b: checkpoint paths or ``"oracle"``.
        tasks: task names, or one string as ``studio compare --tasks`` takes it (``held-out``, ``train``,
            ``all`` or comma-separated names).
        scene: the scene the split words refer to.
        episodes: episodes per task; seed: the evaluation seed; replan: re-plans allowed on failure.
        workers: rollout processes; robot: the agent (default: the scene's).
        label_a, label_b: names in the table; checkpoint_id_a, checkpoint_id_b: catalog ids the rollouts are
            stored under (default: the files registered as ``studio eval`` does).
        inputs: content id of the job's inputs (:class:`~studio.backend.artifact_transfer.InputManifest`), which
            a worker with its own data dir fetches before the job runs (set by the hub's job client).
    """

    a: PathText
    b: PathText
    tasks: Annotated[list[Name], msgspec.Meta(min_length=1, max_length=200)] | Name = "held-out"
    scene: Name = "pick_place"
    episodes: Annotated[int, msgspec.Meta(ge=1, le=1000)] = 10
    seed: Annotated[int, msgspec.Meta(ge=0, le=2**63 - 1)] = 0
    replan: Annotated[int, msgspec.Meta(ge=0, le=20)] = 0
    workers: Annotated[int, msgspec.Meta(ge=1, le=64)] = 1
    robot: Literal["panda", "sawyer"] | None = None
    label_a: Name | None = None
    label_b: Name | None = None
    checkpoint_id_a: Name | None = None
    checkpoint_id_b: Name | None = None
    inputs: ContentId | None = None


def parse_spec(spec: dict[str, Any]) -> CompareJobSpec:
    """The spec as a :class:`CompareJobSpec`; ``ValueError`` naming what is missing or wrong."""
    missing = [k for k in ("a", "b") if not spec.get(k)]
    if missing:
        raise ValueError(f"compare job spec lacks {missing}")
    try:
        return msgspec.convert(spec, CompareJobSpec)
    except msgspec.ValidationError as e:
        raise ValueError(f"invalid compare job spec: {e}") from None


def run_compare_job(ctx) -> dict:
    """The ``compare`` job of a sim worker (spec: :class:`CompareJobSpec`).

    Returns the comparison (:meth:`studio.eval.compare.Comparison.to_dict`: ``compare_id``, the labels,
    ``eval_ids``, ``totals``, ``rows`` in table order) with its Markdown table as ``markdown``.
    """
    from studio.eval.compare import compare, task_list

    spec = parse_spec(dict(ctx.spec))
    if ctx.data_dir is None:
        raise ValueError(
            "compare jobs need a worker started with --data-dir (the store with the demonstrations)"
        )
    spec = msgspec.structs.replace(
        spec,
        a=checked_checkpoint(ctx.data_dir, spec.a, "compare"),
        b=checked_checkpoint(ctx.data_dir, spec.b, "compare"),
    )
    tasks = task_list(spec.scene, spec.tasks)
    episodes = spec.episodes
    total = episodes * len(tasks)
    ctx.progress(0, total, message=f"starting: {total} episodes, each rolled out by A and by B")

    def on_episode(done: int, total: int, row: CompareRow) -> None:
        ctx.progress(
            done,
            total,
            message=f"episode {done} of {total}: A {row.a.mark}, B {row.b.mark}",
            a_success=float(row.a.success),
            b_success=float(row.b.success),
        )

    try:
        result = compare(
            spec.a,
            spec.b,
            tasks,
            episodes,
            spec.seed,
            replan=spec.replan,
            workers=spec.workers,
            data_dir=ctx.data_dir,
            robot=spec.robot,
            label_a=spec.label_a,
            label_b=spec.label_b,
            checkpoint_ids=(spec.checkpoint_id_a, spec.checkpoint_id_b),
            on_episode=on_episode,
            should_stop=lambda: ctx.cancelled,
        )
    except InterruptedError:
        ctx.raise_if_cancelled()  # stopped because the job was cancelled: it ends as cancelled, not failed
        raise
    return {**result.to_dict(), "markdown": result.markdown()}
