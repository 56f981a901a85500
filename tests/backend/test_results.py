"""`studio results` rendering: per-task columns, the split's test groups (Table 1 layout), the breakdown."""

from __future__ import annotations

import argparse

import pytest

from studio.backend.results import parse_policy, render_markdown
from studio.data.splits import load_split


def _report(rates: dict[str, float], n: int = 10) -> dict:
    tasks = {t: {"success": r, "reached": r, "grasped": r, "placed": r, "rollouts": n} for t, r in rates.items()}
    return {"tasks": tasks, "success": sum(rates.values()) / len(rates), "rollouts": n * len(rates),
            "mean_planning_ms": 80.0, "wall_s": 120.0}  # fmt: skip


def test_metaworld_table_has_easy_hard_and_all_columns():
    groups = load_split("metaworld").test_groups
    rates = {"metaworld/button-press-v3": 0.9, "metaworld/pick-place-wall-v3": 0.5,
             "metaworld/window-open-v3": 0.2, "metaworld/door-unlock-v3": 0.0}  # fmt: skip
    table = render_markdown([("osvi-wm", 0, _report(rates)), ("osvi-wm", 2, _report(rates | {"metaworld/door-unlock-v3": 0.4}))],
                            groups)  # fmt: skip
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
