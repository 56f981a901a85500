"""`studio results`: the held-out evaluations behind ``docs/results.md``, rendered as a Markdown table.

    studio results --policy NAME=CKPT [--policy NAME=CKPT ...] [--scene pick_place] [--episodes 100]
                   [--replan 0 2] [--seed 0] [--workers 2] [--expert-embodiment human] [--grasp-correction auto]
                   [--data-dir DIR] [--out results.md]

Each policy (the main checkpoint first, then e.g. ablations trained on the same data and budget) is evaluated on
the scene's held-out tasks once, with the largest ``--replan`` budget and the same seeds — so every row sees the
same scenes and demonstrations; the rows of smaller budgets are those rollouts cut after fewer attempts
(``evaluation.with_budget``: exact, since re-plans continue the same deterministic episode), which halves the
cost of the usual ``--replan 0 2``. A split with ``replan_groups`` (Meta-World: hard) adds a row per policy in the
paper's protocol: re-plans on those groups' tasks only, one attempt on the rest; each plan is bounded as the
split's protocol says (its ``plan_ticks``: the paper's 500 control ticks in Meta-World; ``--plan-ticks``). Writes
the Markdown (per-task success, the mean over each of the split's test groups — Meta-World's easy and hard, the
layout of the paper's Table 1 — the reached/grasped/placed breakdown, planning time, wall time) and, beside it,
the full JSON reports.
``oracle`` as a checkpoint gives the execution ceiling. ``--expert-embodiment`` picks whose demonstrations are
imitated (``studio eval``'s option; e.g. ``human`` for Human-Franka, ``panda`` for Two-Franka).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path

from studio.data.paths import add_data_dir_argument
from studio.data.splits import SplitSpec, load_split, resolve_tasks
from studio.eval.evaluation import (
    PAPER_PLAN_TICKS,
    EvaluationInputError,
    EvaluationReport,
    add_expert_embodiment_argument,
    add_grasp_correction_argument,
    evaluate,
    expert_embodiments_of,
    plan_ticks_of,
    with_budget,
)


def parse_policy(spec: str) -> tuple[str, str]:
    name, sep, path = spec.partition("=")
    if not sep or not name or not path:
        raise argparse.ArgumentTypeError(f"--policy takes NAME=CHECKPOINT, got {spec!r}")
    return name, path


def _mean(report: EvaluationReport, stage: str) -> str:
    """The share of all of a report's rollouts that reached ``stage`` (tasks weighted by their rollout counts)."""
    n = max(report.rollouts, 1)
    return f"{sum(getattr(v, stage) * v.rollouts for v in report.tasks.values()) / n:.1%}"


def _group_mean(report: EvaluationReport, tasks) -> str:
    """Mean success over a group's tasks (the paper's Table 1 averages tasks), or – if none was evaluated."""
    rates = [report.tasks[t].success for t in tasks if t in report.tasks]
    return f"{sum(rates) / len(rates):.1%}" if rates else "–"


def render_markdown(
    reports: list[tuple[str, int | str, EvaluationReport]], groups: dict[str, tuple[str, ...]] | None = None
) -> str:
    """Rows of (policy name, replans, evaluation report) → a Markdown table (one row per policy × replans).

    ``groups`` (a split's ``test_groups``, e.g. Meta-World's easy/hard) adds a column per group after the tasks.
    """
    groups = groups or {}
    tasks = sorted({t for _, _, r in reports for t in r.tasks})
    head = [
        "policy",
        "re-plans",
        *tasks,
        *groups,
        "all",
        "reached",
        "grasped",
        "placed",
        "plan ms",
        "rollouts",
        "wall min",
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, replan, r in reports:
        per_task = [f"{r.tasks[t].success:.1%}" if t in r.tasks else "–" for t in tasks]
        per_group = [_group_mean(r, g) for g in groups.values()]
        row = [
            name,
            str(replan),
            *per_task,
            *per_group,
            f"**{r.success:.1%}**",
            _mean(r, "reached"),
            _mean(r, "grasped"),
            _mean(r, "placed"),
            f"{r.mean_planning_ms:.0f}",
            str(r.rollouts),
            f"{r.wall_s / 60:.1f}",
        ]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"


def budget_rows(
    name: str, report: EvaluationReport, replans: list[int], split: SplitSpec
) -> list[tuple[str, int | str, EvaluationReport]]:
    """A policy's table rows from its one evaluation at the largest budget: one per budget in ``replans``, then,
    if the split names ``replan_groups``, the paper's protocol — the largest budget on those groups' tasks, one
    attempt on the other test tasks (Meta-World: re-plans on the hard tasks only)."""
    most = max(replans)
    rows: list[tuple[str, int | str, EvaluationReport]] = [
        (name, k, report if k == most else with_budget(report, k)) for k in replans
    ]
    replanned = split.replanned_tasks()
    if replanned and most > 0:
        once = [t for t in report.tasks if t not in replanned]
        rows.append((name, f"{most}, {'/'.join(split.replan_groups)} only", with_budget(report, 0, once)))
    return rows


def json_rows(reports: list[tuple[str, int | str, EvaluationReport]]) -> list[dict]:
    """The table's rows as the JSON beside it: each report without its per-rollout rows, named by policy and by
    the row's re-plan label (the paper-protocol row's report says 0 re-plans for its cut tasks; the label wins)."""
    return [
        {"policy": n, **{key: v for key, v in r.to_dict().items() if key != "rows"}, "replan": k}
        for n, k, r in reports
    ]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--policy",
        type=parse_policy,
        action="append",
        required=True,
        metavar="NAME=CKPT",
        help="a checkpoint to evaluate, named for the table (repeatable; 'oracle' allowed)",
    )
    parser.add_argument("--scene", default="pick_place")
    parser.add_argument("--episodes", type=int, default=100, help="rollouts per held-out task")
    parser.add_argument(
        "--replan",
        type=int,
        nargs="+",
        default=[0, 2],
        help="re-plan budgets to report (a split with replan_groups, e.g. Meta-World, also gets the paper's "
        "row: the largest budget on those groups only)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument(
        "--plan-ticks",
        type=int,
        default=None,
        metavar="TICKS",
        help="control ticks each plan may execute (default: the split's protocol, the paper's "
        f"{PAPER_PLAN_TICKS} in Meta-World and no bound elsewhere; 0: no bound)",
    )
    add_grasp_correction_argument(parser)
    add_expert_embodiment_argument(parser)
    parser.add_argument("--out", default=None, help="Markdown file to write (default: print only)")
    add_data_dir_argument(parser)


def run(args: argparse.Namespace) -> int:
    try:
        experts = expert_embodiments_of(args)
    except ValueError as err:
        print(f"studio results: {err}", file=sys.stderr)
        return 2
    tasks = resolve_tasks(args.scene, "held-out")
    split = load_split(args.scene)
    try:
        plan_ticks = plan_ticks_of(args.plan_ticks, args.scene)
    except ValueError as err:
        print(f"studio results: {err}", file=sys.stderr)
        return 2
    reports: list[tuple[str, int | str, EvaluationReport]] = []
    # One evaluation per policy at the largest budget; the smaller budgets are its rollouts cut after fewer attempts.
    most = max(args.replan)
    for name, checkpoint in args.policy:
        print(f"== {name}, re-plans {most}", file=sys.stderr, flush=True)
        try:
            report = evaluate(
                checkpoint,
                tasks,
                args.episodes,
                args.seed,
                most,
                args.workers,
                args.data_dir,
                expert_embodiments=experts,
                grasp=args.grasp_correction,
                plan_ticks=plan_ticks,
            )
        except EvaluationInputError as err:
            print(f"studio results: {name}: {err}", file=sys.stderr)
            return 2
        reports += budget_rows(name, report, args.replan, split)
    table = render_markdown(reports, split.test_groups)
    machine = f"{platform.machine()}, {__import__('os').cpu_count()} CPU cores, {platform.platform()}"
    demos = f"; demonstrations by {', '.join(experts)}" if experts else ""
    grasp = "" if args.grasp_correction == "auto" else f"; grasp correction: {args.grasp_correction}"
    bound = "" if plan_ticks is None else f"; each plan executes at most {plan_ticks} control ticks"
    text = (
        f"Held-out tasks of `{args.scene}` ({', '.join(tasks)}), {args.episodes} rollouts per task, seed "
        f"{args.seed}{demos}{grasp}{bound}; {machine}.\n\n{table}"
    )
    print(text)
    if args.out:
        out = Path(args.out)
        out.write_text(text)
        out.with_suffix(".json").write_text(json.dumps(json_rows(reports), indent=2, default=float))
    return 0
