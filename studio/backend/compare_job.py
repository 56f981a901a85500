"""The ``compare`` job of a sim worker: two checkpoints on the identical seeded episodes, as ``studio compare``.

A thin handler: the comparison is :func:`studio.eval.compare.compare`; this module turns the job's spec into its
arguments and its episodes into job progress ("episode i of N"), and returns the table's rows. Rollouts run in the
worker's own process (``workers`` > 1 starts that many processes beside it) and are stored as each ends; the rows
are the job's result, published only when every episode has both sides. A worker that dies mid-way fails the job
(the queue says it was lost), and the rollouts it stored before are marked as part of a comparison that planned
more: nothing half-done passes for a result.
"""

from __future__ import annotations

from studio.eval.compare import CompareRow, compare, task_list


def run_compare_job(ctx) -> dict:
    """The ``compare`` job of a sim worker.

    Spec: ``a``, ``b`` (checkpoint paths or ``"oracle"``), ``tasks`` (a list of task names or one string, as
    ``studio compare --tasks``: ``held-out`` by default), ``scene`` (for the split words; default
    ``pick_place``), ``episodes`` (per task, default 10), ``seed`` (default 0), ``replan`` (default 0),
    ``workers`` (default 1), ``robot``, ``label_a`` / ``label_b`` (names in the table), ``checkpoint_id_a`` /
    ``checkpoint_id_b`` (catalog ids the rollouts are stored under; default: the files registered as ``studio
    eval`` does). Returns the comparison (:meth:`studio.eval.compare.Comparison.to_dict`: ``compare_id``, the
    labels, ``eval_ids``, ``totals``, ``rows`` in table order) with its Markdown table as ``markdown``.
    """
    spec = dict(ctx.spec)
    missing = [k for k in ("a", "b") if not spec.get(k)]
    if missing:
        raise ValueError(f"compare job spec lacks {missing}")
    if ctx.data_dir is None:
        raise ValueError(
            "compare jobs need a worker started with --data-dir (the store with the demonstrations)"
        )
    tasks = task_list(str(spec.get("scene", "pick_place")), spec.get("tasks", "held-out"))
    episodes = int(spec.get("episodes", 10))
    total = episodes * len(tasks)
    ctx.progress(0, total, message=f"starting: {total} episodes, each rolled out by A and by B")

    def on_episode(done: int, total: int, row: CompareRow) -> None:
        ctx.progress(done, total, message=f"episode {done} of {total}: A {row.a.mark}, B {row.b.mark}",
                     a_success=float(row.a.success), b_success=float(row.b.success))  # fmt: skip

    try:
        result = compare(
            str(spec["a"]),
            str(spec["b"]),
            tasks,
            episodes,
            int(spec.get("seed", 0)),
            replan=int(spec.get("replan", 0)),
            workers=int(spec.get("workers", 1)),
            data_dir=ctx.data_dir,
            robot=spec.get("robot"),
            label_a=spec.get("label_a"),
            label_b=spec.get("label_b"),
            checkpoint_ids=(spec.get("checkpoint_id_a"), spec.get("checkpoint_id_b")),
            on_episode=on_episode,
            should_stop=lambda: ctx.cancelled,
        )
    except InterruptedError:
        ctx.raise_if_cancelled()  # stopped because the job was cancelled: it ends as cancelled, not failed
        raise
    return {**result.to_dict(), "markdown": result.markdown()}
