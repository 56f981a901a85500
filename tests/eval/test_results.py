"""`studio results` rendering: per-task columns, the split's test groups (Table 1 layout), the breakdown."""

from __future__ import annotations

import argparse

import pytest

from studio.data.splits import load_split
from studio.eval.evaluation import EvaluationReport, RolloutSummary, RolloutTotals, TaskBreakdown, summarise
from studio.eval.results import budget_rows, json_rows, parse_policy, render_markdown

MW_TASKS = (
    "metaworld/button-press-v3",
    "metaworld/pick-place-wall-v3",
    "metaworld/window-open-v3",
    "metaworld/door-unlock-v3",
)


def _as_report(
    totals: RolloutTotals, replan: int, wall_s: float, rows: tuple[RolloutSummary, ...] = ()
) -> EvaluationReport:
    """An evaluation report with these totals and rows, run on nothing in particular."""
    return EvaluationReport(
        tasks=totals.tasks,
        success=totals.success,
        rollouts=totals.rollouts,
        mean_planning_ms=totals.mean_planning_ms,
        eval_id="eval-made-up",
        checkpoint="oracle",
        robot="sawyer",
        scene="metaworld",
        seed=0,
        replan=replan,
        grasp_correction="auto",
        expert_embodiments=("sawyer",),
        episodes_per_task=max((t.rollouts for t in totals.tasks.values()), default=0),
        wall_s=wall_s,
        workers=1,
        rows=rows,
    )


def _report(rates: dict[str, float], n: int = 10) -> EvaluationReport:
    tasks = {t: TaskBreakdown(n, r, r, r, r, 0.0, 80.0, {}) for t, r in rates.items()}
    totals = RolloutTotals(tasks, sum(rates.values()) / len(rates), n * len(rates), 80.0)
    return _as_report(totals, replan=0, wall_s=120.0)


def test_metaworld_table_has_easy_hard_and_all_columns():
    groups = load_split("metaworld").test_groups
    rates = {
        "metaworld/button-press-v3": 0.9,
        "metaworld/pick-place-wall-v3": 0.5,
        "metaworld/window-open-v3": 0.2,
        "metaworld/door-unlock-v3": 0.0,
    }
    table = render_markdown(
        [("osvi-wm", 0, _report(rates)), ("osvi-wm", 2, _report(rates | {"metaworld/door-unlock-v3": 0.4}))],
        groups,
    )
    head, _, row0, row2 = table.strip().splitlines()
    cells = [c.strip() for c in head.strip("|").split("|")]
    assert cells[6:9] == ["easy", "hard", "all"]
    values = [c.strip() for c in row0.strip("|").split("|")]
    assert values[6:9] == ["70.0%", "10.0%", "**40.0%**"]  # easy = mean(0.9, 0.5), hard = mean(0.2, 0.0)
    values = [c.strip() for c in row2.strip("|").split("|")]
    assert values[1] == "2" and values[7] == "30.0%" and values[8] == "**50.0%**"


def test_table_without_groups_and_a_group_never_evaluated():
    report = _report({"pick_place/bar->blue": 0.25, "pick_place/bar->yellow": 0.75})
    plain = render_markdown([("p", 0, report)])
    assert plain.splitlines()[0].count("|") == 12 and "**50.0%**" in plain
    partial = render_markdown([("p", 0, report)], {"other": ("pick_place/cube->red",)})
    assert "| – |" in partial


def test_policy_argument_needs_a_name_and_a_path():
    assert parse_policy("osvi=runs/a/best.pt") == ("osvi", "runs/a/best.pt")
    with pytest.raises(argparse.ArgumentTypeError, match="NAME=CHECKPOINT"):
        parse_policy("runs/a/best.pt")


def _attempts(outcomes: list[bool]) -> list[dict[str, bool]]:
    return [{"reached": True, "grasped": ok, "placed": ok} for ok in outcomes]


def _evaluated(outcomes_by_task: dict[str, list[list[bool]]], replan: int) -> EvaluationReport:
    """An evaluation report with rows whose attempts end as given (each list: one rollout's attempts in order)."""
    rows = []
    for task, rollouts in outcomes_by_task.items():
        for i, outcomes in enumerate(rollouts):
            rows.append(
                RolloutSummary(
                    rollout_id=f"{task}-{i}",
                    task=task,
                    index=i,
                    seed=i,
                    expert_episode_id="e",
                    success=outcomes[-1],
                    reached=True,
                    grasped=outcomes[-1],
                    placed=outcomes[-1],
                    failure_stage=None if outcomes[-1] else "grasp",
                    replans=len(outcomes) - 1,
                    planning_time_s=0.1,
                    duration_s=1.0,
                    attempt_stages=_attempts(outcomes),
                    attempt_planning_s=[0.1] * len(outcomes),
                )
            )
    return _as_report(summarise(rows), replan, 60.0, tuple(rows))


def test_paper_protocol_row_replans_on_the_hard_tasks_only():
    # Every task: one rollout that succeeds at once, one that succeeds on its second attempt, one that never does.
    rollouts = [[True], [False, True], [False, False, False]]
    report = _evaluated({t: rollouts for t in MW_TASKS}, replan=2)
    rows = budget_rows("osvi-wm", report, [0, 2], load_split("metaworld"))
    assert [(name, k) for name, k, _ in rows] == [("osvi-wm", 0), ("osvi-wm", 2), ("osvi-wm", "2, hard only")]
    (_, _, none), (_, _, full), (_, _, paper) = rows
    for task in MW_TASKS:
        assert none.tasks[task].success == pytest.approx(1 / 3)
        assert full.tasks[task].success == pytest.approx(2 / 3)
    hard = ("metaworld/window-open-v3", "metaworld/door-unlock-v3")
    assert {t: paper.tasks[t].success for t in MW_TASKS} == pytest.approx(
        {t: 2 / 3 if t in hard else 1 / 3 for t in MW_TASKS}
    )
    assert paper.success == pytest.approx(0.5) and paper.replan_cut_tasks == tuple(
        sorted(set(MW_TASKS) - set(hard))
    )
    table = render_markdown(rows, load_split("metaworld").test_groups)
    paper_line = table.strip().splitlines()[-1]
    assert paper_line.startswith("| osvi-wm | 2, hard only |") and "**50.0%**" in paper_line
    assert [row["replan"] for row in json_rows(rows)] == [0, 2, "2, hard only"]
    assert all("rows" not in row for row in json_rows(rows))
    none_json, full_json, paper_json = json_rows(rows)
    assert paper_json["replan_cut_tasks"] == sorted(set(MW_TASKS) - set(hard))
    assert none_json["derived_from_replan"] == 2 and "derived_from_replan" not in full_json
    # No such row without re-plans to keep, nor for a split that names no replan groups.
    single = _evaluated({t: [[True]] for t in MW_TASKS}, replan=0)
    assert [k for _, k, _ in budget_rows("p", single, [0], load_split("metaworld"))] == [0]
    assert [k for _, k, _ in budget_rows("p", report, [0, 2], load_split("pick_place"))] == [0, 2]


@pytest.mark.parametrize(
    ("scene", "given", "bound"),
    [("metaworld", None, 500), ("pick_place", None, None), ("metaworld", 300, 300), ("metaworld", 0, None)],
)
def test_results_bound_each_plan_as_the_paper_on_meta_world(scene, given, bound, monkeypatch, capsys):
    """The paper's Meta-World protocol gives each plan 500 steps: `studio results` evaluates Meta-World so unless
    told otherwise, says so above the table, and bounds nothing elsewhere."""
    import studio.eval.results as results

    seen = {}

    def fake_evaluate(checkpoint, tasks, *args, plan_ticks=None, **kwargs):
        seen["plan_ticks"] = plan_ticks
        return _evaluated({t: [[True]] for t in tasks}, replan=2)

    monkeypatch.setattr(results, "evaluate", fake_evaluate)
    parser = argparse.ArgumentParser()
    results.add_arguments(parser)
    argv = [
        "--policy",
        "p=oracle",
        "--scene",
        scene,
        *(["--plan-ticks", str(given)] if given is not None else []),
    ]
    assert results.run(parser.parse_args(argv)) == 0
    out = capsys.readouterr().out
    assert seen["plan_ticks"] == bound
    assert (f"each plan executes at most {bound} control ticks" in out) == (bound is not None)


def test_results_say_which_policy_cannot_be_evaluated_and_why(tmp_path, capsys):
    """A policy file that is not there, or a store without the held-out tasks' demonstrations: one line naming the
    policy and what to do, exit status 2, no table written."""
    import studio.eval.results as results

    out = tmp_path / "table.md"
    for policy, said in [
        (
            f"gone={tmp_path / 'gone.pt'}",
            f"studio results: gone: no checkpoint file '{tmp_path / 'gone.pt'}'",
        ),
        ("ceiling=oracle", "studio results: ceiling: no expert demonstration of 'pick_place/"),
    ]:
        parser = argparse.ArgumentParser()
        results.add_arguments(parser)
        args = parser.parse_args(
            [
                "--policy",
                policy,
                "--scene",
                "pick_place",
                "--data-dir",
                str(tmp_path / "d"),
                "--out",
                str(out),
            ]
        )
        assert results.run(args) == 2
        last = capsys.readouterr().err.splitlines()[-1]
        assert last.startswith(said), last
    assert "collect some with: studio collect --robot sawyer" in last
    assert not out.exists()
